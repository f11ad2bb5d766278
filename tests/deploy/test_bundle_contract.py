"""The deploy bundle's written contract (contract.json) and golden pair: software that has only
onnxruntime and numpy -- not this project -- reads the contract, preprocesses the golden input by it,
runs model.onnx and reproduces the golden output."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from pipeline import catalog
from pipeline.deploy.bundle import read_deploy_info
from pipeline.deploy.segmenter import Segmenter
from tests.builders.deploy import HAS_ONNX, RES, make_checkpoint, run_export

pytestmark = pytest.mark.skipif(not HAS_ONNX, reason="needs onnx + onnxruntime (the onnx extra)")

NAMES = {k: catalog.bundle_file(k) for k in ("contract", "golden_input", "golden_probs", "golden_mask", "onnx")}


@pytest.fixture(scope="module")
def bundles(tmp_path_factory) -> dict[str, Path]:
    """A squash bundle (the default) and a letterbox bundle (``data.letterbox: true``) of one tiny student."""
    root = tmp_path_factory.mktemp("contract")
    ckpt = make_checkpoint(root / "ckpt", seed=5)
    out = {}
    for name, extra in (("squash", ()), ("letterbox", ("--set", "data.letterbox=true"))):
        r = run_export(ckpt, root / name, "--no-int8", *extra)
        assert r.exit_code == 0, r.output
        out[name] = root / name
    return out


def test_the_contract_states_the_input_the_output_and_the_golden_pair(bundles):
    b = bundles["squash"]
    contract = json.loads((b / NAMES["contract"]).read_text())
    info = read_deploy_info(b)
    assert contract["contract_version"] == 1
    assert contract["input"]["shape"] == ["N", 3, RES, RES] and contract["input"]["channel_order"] == "RGB"
    assert contract["input"]["dtype"] == "float32" and "/ 255" in contract["input"]["normalisation"]
    assert contract["output"]["tau"] == info["tau"] and contract["output"]["logit_tau"] == info["output"]["logit_tau"]
    assert contract["frame_to_input"]["aspect"] == "squash" and contract["frame_to_input"]["bit_depth"] == "auto"
    assert contract["model"]["onnx"] == NAMES["onnx"]
    for key in ("contract", "golden_input", "golden_probs", "golden_mask"):   # listed with their sha256s
        assert NAMES[key] in info["files"], key
    golden = np.load(b / NAMES["golden_input"])
    probs, mask = np.load(b / NAMES["golden_probs"]), np.load(b / NAMES["golden_mask"])
    assert golden.shape == (RES, RES, 3) and golden.dtype == np.uint8 and golden.std() > 10
    assert probs.shape == mask.shape == (RES, RES) and probs.dtype == np.float32 and mask.dtype == bool
    np.testing.assert_array_equal(mask, probs >= np.float32(contract["output"]["tau"]))
    # the project's own reader agrees with the golden output
    seg = Segmenter.from_bundle(b, engine="torch")
    got_mask, score = seg.predict(golden, return_score=True)
    assert np.abs(seg.probabilities(golden) - probs).max() <= contract["golden"]["atol_probabilities"]
    assert (got_mask != mask).sum() <= (np.abs(probs - seg.tau) <= contract["golden"]["atol_probabilities"]).sum()
    assert 0.0 <= score <= 1.0


def test_a_letterbox_bundle_says_so_and_its_segmenter_letterboxes(bundles):
    b = bundles["letterbox"]
    contract = json.loads((b / NAMES["contract"]).read_text())
    assert contract["frame_to_input"]["aspect"] == "letterbox" and "crop the pad" in contract["output"]["back_to_frame"]
    assert read_deploy_info(b)["frames"] == {"bit_depth": "auto", "letterbox": True}
    assert Segmenter.from_bundle(b, engine="torch").letterbox is True
    assert Segmenter.from_bundle(bundles["squash"], engine="torch").letterbox is False
    assert Segmenter.from_bundle(b, engine="torch", letterbox=False).letterbox is False


#: the consumer: numpy + onnxruntime only, from the contract alone (argv: bundle folder, contract name)
CONSUMER = textwrap.dedent('''
    import json, sys
    from pathlib import Path
    try:
        import pipeline  # noqa: F401
        raise SystemExit("this project is importable: the test is not clean")
    except ImportError:
        pass
    import numpy as np
    import onnxruntime as ort

    bundle = Path(sys.argv[1])
    c = json.loads((bundle / sys.argv[2]).read_text())
    frame = np.load(bundle / c["golden"]["input"])                      # RGB uint8 at the working size
    assert list(frame.shape) == c["input"]["shape"][2:] + [3]
    x = (frame.astype(np.float32) / np.float32(255.0)).transpose(2, 0, 1)[None]   # per "normalisation"
    x = np.ascontiguousarray(x, dtype=c["input"]["dtype"])
    sess = ort.InferenceSession(str(bundle / c["model"]["onnx"]), providers=["CPUExecutionProvider"])
    z = sess.run([c["output"]["name"]], {c["input"]["name"]: x})[0][0, 0]
    p = 1.0 / (1.0 + np.exp(-z.astype(np.float64)))
    mask = p >= c["output"]["tau"]
    want_p = np.load(bundle / c["golden"]["probabilities"])
    want_mask = np.load(bundle / c["golden"]["mask"])
    atol = c["golden"]["atol_probabilities"]
    err = float(np.abs(p - want_p).max())
    assert err <= atol, err
    flips = mask != want_mask
    assert (np.abs(want_p[flips] - c["output"]["tau"]) <= atol).all()
    assert (z >= c["output"]["logit_tau"]).sum() == mask.sum()
    print("reproduced", err, int(mask.sum()))
''')


def clean_site(tmp: Path) -> Path:
    """A folder that holds numpy and onnxruntime only (links into this interpreter's site-packages)."""
    import numpy
    import onnxruntime

    site = tmp / "site"
    site.mkdir()
    for mod in (numpy, onnxruntime):
        pkg = Path(mod.__file__).parent
        for p in (pkg, pkg.with_name(pkg.name + ".libs")):
            if p.exists():
                (site / p.name).symlink_to(p, target_is_directory=True)
    return site


def test_onnxruntime_and_numpy_alone_reproduce_the_golden_output(bundles, tmp_path):
    site = clean_site(tmp_path)
    code = f"import sys; sys.path.append({str(site)!r})\n" + CONSUMER
    # -I: no PYTHON* variables, no user site, not the script's folder; -S: not site-packages (where this
    # project is installed), so only the standard library and the two linked packages can be imported
    env = {"PATH": os.environ.get("PATH", "/usr/bin:/bin")}
    for name in ("squash", "letterbox"):
        r = subprocess.run([sys.executable, "-I", "-S", "-c", code, str(bundles[name]), NAMES["contract"]],
                           cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr + r.stdout
        assert r.stdout.startswith("reproduced"), r.stdout
