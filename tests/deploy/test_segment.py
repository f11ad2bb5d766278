"""``geodistill segment`` on files of odd sizes and formats, a corrupt file among good ones, both a
checkpoint and a deploy bundle with every engine (torch, torchscript, onnxruntime_fp32 / _int8), and the rule that
outputs never overwrite inputs."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from pipeline.deploy.bundle import INT8_FILE

from pipeline.deploy.image_files import plan_outputs
from pipeline.datasets.loading import read_rgb, resize_image
from pipeline.runtime.errors import InputError
from pipeline.evaluation.inference import load_student
from pipeline.cli.segment import main as segment_main
from tests.builders.deploy import HAS_ONNX, make_artifacts, make_checkpoint, make_thresholds, run_export

RES = 32


@pytest.fixture(autouse=True)
def quiet(monkeypatch):
    monkeypatch.setenv("GEODISTILL_QUIET", "1")


def write_inputs(folder: Path) -> dict[str, tuple[int, int]]:
    """Odd-sized RGB, grey, RGBA, 16-bit and JPEG images; returns name -> (height, width)."""
    rng = np.random.default_rng(0)
    folder.mkdir(parents=True, exist_ok=True)
    yy, xx = np.mgrid[0:53, 0:37]
    blob = (((yy - 26) ** 2 + (xx - 18) ** 2) < 120)[..., None]
    rgb = np.where(blob, 210, 25).astype(np.uint8) + rng.integers(0, 20, (53, 37, 3), dtype=np.uint8)
    cv2.imwrite(str(folder / "odd.png"), rgb)                                              # 53 x 37
    cv2.imwrite(str(folder / "grey.png"), rng.integers(0, 255, (41, 29), dtype=np.uint8))  # grey
    cv2.imwrite(str(folder / "alpha.png"), rng.integers(0, 255, (30, 70, 4), dtype=np.uint8))  # RGBA
    cv2.imwrite(str(folder / "deep.tif"), rng.integers(0, 65535, (33, 35, 3), dtype=np.uint16))  # 16-bit
    sub = folder / "sub"
    sub.mkdir()
    cv2.imwrite(str(sub / "odd.jpg"), rgb)
    cv2.imwrite(str(sub / "odd.png"), rgb[:37])  # same stem as odd.jpg in the same folder
    return {"odd.png": (53, 37), "grey.png": (41, 29), "alpha.png": (30, 70), "deep.tif": (33, 35),
            "sub/odd.jpg": (53, 37), "sub/odd.png": (37, 37)}


def segment(*args):
    return CliRunner().invoke(segment_main, ["--device", "cpu", *map(str, args)])


def reference_probs(ckpt: Path, path: Path) -> np.ndarray:
    """The documented recipe, computed here: area-resize to R x R, logits, sigmoid, bilinear back."""
    model, _ = load_student(ckpt)
    img = read_rgb(path)
    x = torch.from_numpy(resize_image(img, RES)).permute(2, 0, 1)[None].float() / 255
    with torch.no_grad():
        p = torch.sigmoid(model(x))[0, 0].numpy()
    return cv2.resize(p, (img.shape[1], img.shape[0]), interpolation=cv2.INTER_LINEAR)


def test_segment_checkpoint_folder_odd_sizes_formats_and_corrupt_file(tmp_path):
    ckpt = make_checkpoint(tmp_path / "ckpt")
    thr = make_thresholds(tmp_path / "thr.parquet", [("geodistill", 42, 0.5, 0.8)])
    sizes = write_inputs(tmp_path / "in")
    (tmp_path / "in" / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n not really a png")
    (tmp_path / "in" / "empty.jpg").write_bytes(b"")
    (tmp_path / "in" / "notes.txt").write_text("not an image, not a candidate")
    before = {p: p.read_bytes() for p in (tmp_path / "in").rglob("*") if p.is_file()}
    r = segment("--checkpoint", ckpt, "--input", tmp_path / "in", "--output", tmp_path / "out",
                "--thresholds", thr, "--resolution", RES, "--save-prob", "--overlay", "--batch-size", 3, "--skip-bad")
    assert r.exit_code == 0, r.output
    out = tmp_path / "out"
    for name, (h, w) in sizes.items():
        mask = cv2.imread(str(out / f"{name}.mask.png"), cv2.IMREAD_UNCHANGED)
        assert mask.shape == (h, w) and mask.dtype == np.uint8 and set(np.unique(mask)) <= {0, 255}
        assert cv2.imread(str(out / f"{name}.overlay.png")).shape == (h, w, 3)
        prob = cv2.imread(str(out / f"{name}.prob.png"), cv2.IMREAD_UNCHANGED)
        assert prob.shape == (h, w)
    # content: the mask is [P >= tau] of the documented recipe at the original size
    for name in ("odd.png", "alpha.png", "deep.tif", "grey.png"):
        p = reference_probs(ckpt, tmp_path / "in" / name)
        mask = cv2.imread(str(out / f"{name}.mask.png"), cv2.IMREAD_UNCHANGED) > 0
        decided = np.abs(p - 0.5) > 1e-4
        assert np.array_equal(mask[decided], (p >= 0.5)[decided])
        prob = cv2.imread(str(out / f"{name}.prob.png"), cv2.IMREAD_UNCHANGED)
        assert np.abs(prob.astype(float) - p * 255).max() <= 0.51
    # with --skip-bad the corrupt and zero-byte files are listed and skipped; the text file is not a candidate
    rows = list(csv.DictReader(open(out / "skipped.csv")))
    assert sorted(Path(r["path"]).name for r in rows) == ["broken.png", "empty.jpg", "notes.txt"]
    assert all(r["reason"] for r in rows)
    assert [r["reason"] for r in rows if r["path"].endswith("notes.txt")][0].startswith("not an image file")
    assert "segment: skipped 2 bad file(s) (first: " in r.output and str(out / "skipped.csv") in r.output
    # inputs untouched
    assert all(p.read_bytes() == b for p, b in before.items())


def toy_trained_checkpoint(path: Path) -> Path:
    """A tiny TinyUNet fitted for 60 steps to 'bright blob = foreground' on generated 32 px images.

    A random TinyUNet outputs nearly constant probabilities (every mask empty or full), which would
    make any engine agreement trivially 100 %.  The toy target is computed from the generated image
    itself (blob interior), a fixture only -- no reference mask and no pipeline stage is involved.
    """
    import pandas as pd

    from pipeline.artifacts.lineage import make_meta
    from pipeline.evaluation.inference import save_checkpoint
    from tests.builders.deploy import tiny_model

    rng = np.random.default_rng(1)
    yy, xx = np.mgrid[0:RES, 0:RES]
    x = np.empty((16, 3, RES, RES), np.float32)
    y = np.empty((16, 1, RES, RES), np.float32)
    for i in range(16):
        cy, cx, ry, rx = rng.uniform(8, 24), rng.uniform(8, 24), rng.uniform(4, 10), rng.uniform(4, 10)
        blob = ((yy - cy) / ry) ** 2 + ((xx - cx) / rx) ** 2 < 1
        x[i] = np.where(blob, rng.uniform(0.6, 0.9), rng.uniform(0.05, 0.3)) + rng.normal(0, 0.08, (3, RES, RES))
        y[i, 0] = blob
    x, y = torch.from_numpy(x.clip(0, 1)), torch.from_numpy(y)
    model = tiny_model(5).train()
    opt = torch.optim.Adam(model.parameters(), lr=0.02)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny ops: one thread avoids OpenMP spin-waits on a shared, loaded CPU
    try:
        for _ in range(40):
            opt.zero_grad()
            torch.nn.functional.binary_cross_entropy_with_logits(model(x), y).backward()
            opt.step()
    finally:
        torch.set_num_threads(threads)
    log = pd.DataFrame({"epoch": [1], "stage": [1], "loss": [0.1], "val_iou": [0.5], "val_bf1": [0.5],
                        "lr": [0.02]})
    meta = make_meta("checkpoint", "train", "test", {"seed": 42, "method": "geodistill"})
    return save_checkpoint(path, model.eval(), meta, log, method="geodistill", seed=42, stage=1, selected_epoch=1)


def read_masks(folder: Path) -> dict[str, np.ndarray]:
    return {p.relative_to(folder).as_posix(): cv2.imread(str(p), cv2.IMREAD_UNCHANGED) > 0
            for p in sorted(folder.rglob("*.mask.png"))}


def test_segment_deploy_bundle_engines_agree_and_use_bundle_tau(tmp_path):
    ckpt = toy_trained_checkpoint(tmp_path / "ckpt")
    thr = make_thresholds(tmp_path / "thr.parquet", [("geodistill", 42, 0.47, 0.8)])
    art = make_artifacts(tmp_path / "art")
    assert run_export(ckpt, tmp_path / "deploy", "--thresholds", str(thr), "--artifacts", str(art)).exit_code == 0
    sizes = write_inputs(tmp_path / "in")
    engines = ["torch", "torchscript"] + (["onnxruntime_fp32", "onnxruntime_int8"] if HAS_ONNX else [])
    masks = {}
    for e in engines:
        r = segment("--checkpoint", tmp_path / "deploy", "--input", tmp_path / "in",
                    "--output", tmp_path / f"out_{e}", "--engine", e)
        assert r.exit_code == 0, r.output
        assert "tau=0.47" in r.output and f"engine {e}," in r.output and "ms/image" in r.output
        masks[e] = read_masks(tmp_path / f"out_{e}")
        assert {k: v.shape for k, v in masks[e].items()} == {f"{n}.mask.png": hw for n, hw in sizes.items()}
    fg = np.mean(np.concatenate([m.ravel() for m in masks["torch"].values()]))
    assert 0.05 < fg < 0.95, fg  # both classes present, so agreement below is not trivially 100 %
    for e in ("torchscript", "onnxruntime_fp32"):  # fp32 engines: identical masks
        if e in masks:
            for name, m in masks["torch"].items():
                assert np.array_equal(masks[e][name], m), (e, name)
    if HAS_ONNX:  # int8 is approximate: >= 99 % of all pixels agree with torch
        same = sum(int(np.count_nonzero(masks["onnxruntime_int8"][k] == m)) for k, m in masks["torch"].items())
        assert same / sum(m.size for m in masks["torch"].values()) >= 0.99
        # an old name (pipeline.engine_table.ENGINE_ALIASES) runs its engine: the same masks
        r = segment("--checkpoint", tmp_path / "deploy", "--input", tmp_path / "in", "--output", tmp_path / "old",
                    "--engine", "int8")
        assert r.exit_code == 0 and "engine onnxruntime_int8," in r.output, r.output
        assert read_masks(tmp_path / "old").keys() == masks["onnxruntime_int8"].keys()
        assert all(np.array_equal(m, masks["onnxruntime_int8"][k]) for k, m in read_masks(tmp_path / "old").items())
        # auto picks an exact engine (onnxruntime_fp32) even when the bundle has int8: int8 must be asked for
        r = segment("--checkpoint", tmp_path / "deploy", "--input", tmp_path / "in" / "odd.png",
                    "--output", tmp_path / "out_auto")
        assert r.exit_code == 0 and "engine onnxruntime_fp32 (auto)" in r.output, r.output
        assert np.array_equal(read_masks(tmp_path / "out_auto")["odd.png.mask.png"], masks["torch"]["odd.png.mask.png"])
    # --tau overrides the bundle's tau: tau = 0 keeps every pixel
    r = segment("--checkpoint", tmp_path / "deploy", "--input", tmp_path / "in" / "grey.png",
                "--output", tmp_path / "all", "--tau", 0)
    assert r.exit_code == 0 and (cv2.imread(str(tmp_path / "all" / "grey.png.mask.png"), 0) == 255).all()
    info = json.loads((tmp_path / "deploy" / "deploy.json").read_text())
    assert info["resolution"] == RES


def test_segment_engine_choice_and_refusals(tmp_path):
    ckpt = make_checkpoint(tmp_path / "ckpt", seed=2)
    write_inputs(tmp_path / "in")
    img = tmp_path / "in" / "odd.png"
    # a checkpoint directory: auto = torch; any other engine is refused with one line, exit 2
    r = segment("--checkpoint", ckpt, "--input", img, "--output", tmp_path / "o1", "--tau", 0.5,
                "--resolution", RES)
    assert r.exit_code == 0 and "engine torch (auto)" in r.output, r.output
    for e in ("onnxruntime_fp32", "int8", "torchscript"):  # int8: an old name
        r = segment("--checkpoint", ckpt, "--input", img, "--output", tmp_path / f"x_{e}", "--tau", 0.5,
                    "--resolution", RES, "--engine", e)
        lines = r.output.strip().splitlines()
        assert r.exit_code == 2 and len(lines) == 1 and "--engine" in lines[0] and "checkpoint" in lines[0], r.output
        assert not (tmp_path / f"x_{e}").exists()
    r = segment("--checkpoint", ckpt, "--input", img, "--output", tmp_path / "x", "--engine", "tpu")
    assert r.exit_code == 2 and "--engine" in r.output and len(r.output.strip().splitlines()) == 1
    # a bundle without an int8 model (no --artifacts at export): auto = onnxruntime_fp32, a forced int8 says why not
    assert run_export(ckpt, tmp_path / "deploy", "--tau", "0.5").exit_code == 0
    r = segment("--checkpoint", tmp_path / "deploy", "--input", img, "--output", tmp_path / "o2")
    assert r.exit_code == 0 and f"engine {'onnxruntime_fp32' if HAS_ONNX else 'torch'} (auto)" in r.output, r.output
    r = segment("--checkpoint", tmp_path / "deploy", "--input", img, "--output", tmp_path / "o3",
                "--engine", "onnxruntime_int8")
    lines = r.output.strip().splitlines()
    assert r.exit_code == 2 and len(lines) == 1 and (INT8_FILE in lines[0] or "onnx" in lines[0]), r.output
    # a bundle exported without onnx: auto = torch
    assert run_export(ckpt, tmp_path / "ts_only", "--tau", "0.5", "--no-onnx").exit_code == 0
    r = segment("--checkpoint", tmp_path / "ts_only", "--input", img, "--output", tmp_path / "o4")
    assert r.exit_code == 0 and "engine torch (auto)" in r.output, r.output
    assert np.array_equal(read_masks(tmp_path / "o4")["odd.png.mask.png"], read_masks(tmp_path / "o1")["odd.png.mask.png"])


def test_segment_never_overwrites_inputs_and_rejects_bad_options(tmp_path):
    ckpt = make_checkpoint(tmp_path / "ckpt")
    write_inputs(tmp_path / "in")
    base = ["--checkpoint", ckpt, "--resolution", RES, "--tau", 0.5]
    cases = [
        (["--input", tmp_path / "in", "--output", tmp_path / "in"], "inside the input folder"),
        (["--input", tmp_path / "in", "--output", tmp_path / "in" / "masks"], "inside the input folder"),
        (["--checkpoint", tmp_path / "missing", "--input", tmp_path / "in", "--output", tmp_path / "o"], "missing"),
        (["--input", tmp_path / "nowhere", "--output", tmp_path / "o"], "nowhere"),
        (["--input", tmp_path / "in", "--output", tmp_path / "o", "--tau", 2], "--tau"),
        (["--input", tmp_path / "in", "--output", tmp_path / "o", "--engine", "onnxruntime_fp32"], "deploy bundle"),
    ]
    for extra, needle in cases:
        r = segment(*base, *extra)
        assert r.exit_code == 2, (extra, r.output)
        lines = r.output.strip().splitlines()
        assert len(lines) == 1 and needle in lines[0], (extra, r.output)
    # a missing required option: click's usage error (exit 2), its last line naming the option, as for
    # label and distill; --help marks the three as [required]
    r = segment(*base, "--input", tmp_path / "in")
    assert r.exit_code == 2 and r.output.strip().splitlines()[-1] == "Error: Missing option '--output'.", r.output
    assert segment("--help").output.count("[required]") == 3
    assert not (tmp_path / "in" / "masks").exists() and not (tmp_path / "o").exists()
    # an input that is itself named like an output of another input in the same folder
    flat = tmp_path / "flat"
    flat.mkdir()
    img = read_rgb(tmp_path / "in" / "odd.png")
    cv2.imwrite(str(flat / "a.png"), img)
    cv2.imwrite(str(flat / "b.png"), img)
    r = segment(*base, "--input", flat / "a.png", "--output", flat)  # a.png.mask.png: no collision -> fine
    assert r.exit_code == 0 and (flat / "a.png.mask.png").exists()
    before = (flat / "a.png.mask.png").read_bytes()
    r = segment(*base, "--input", flat / "a.png.mask.png", "--output", tmp_path / "elsewhere")
    assert r.exit_code == 0  # a mask file is an image too; output goes elsewhere
    # a.png's mask would land on the input a.png.mask.png: refused before anything is written, even
    # with overwrite
    for overwrite in (False, True):
        with pytest.raises(InputError, match="overwrite the input"):
            plan_outputs(flat, [flat / "a.png", flat / "a.png.mask.png"], tmp_path / "flat", False,
                                overwrite=overwrite)
    assert (flat / "a.png.mask.png").read_bytes() == before


def test_segment_all_files_unreadable_is_an_error(tmp_path):
    ckpt = make_checkpoint(tmp_path / "ckpt")
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "x.png").write_bytes(b"junk")
    r = segment("--checkpoint", ckpt, "--input", tmp_path / "in", "--output", tmp_path / "out", "--resolution", RES,
                "--tau", 0.5, "--skip-bad")
    assert r.exit_code == 2 and "could be read" in r.output.strip().splitlines()[-1]
    assert list(csv.DictReader(open(tmp_path / "out" / "skipped.csv")))[0]["path"].endswith("x.png")
