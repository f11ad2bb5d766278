"""Training loop: tiny runs lower the loss, determinism, resume after interruption, divergence,
warm start, the reference-mask boundary, and the train stage command.

``build_tiny_artifacts`` writes a self-contained set of tiny artifacts (12 images of 32 px) with
pipeline.artifacts; it does not run any other stage.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from scipy import ndimage

from pipeline.artifacts import make_meta, open_artifact, write_parquet, write_zarr
from pipeline.errors import TrainingDiverged
from pipeline.methods import SELECTION_TAU_KEY
from pipeline.params import RECIPES, load_params, section
from pipeline.streaming import spill_rows

REPO = Path(__file__).resolve().parent.parent
PROMPTS = ["spacecraft", "satellite", "space probe", "space vehicle", "p5", "p6"]


def _shape_mask(rng, size):
    yy, xx = np.mgrid[:size, :size]
    cy, cx = rng.uniform(size * 0.3, size * 0.7, 2)
    ry, rx = rng.uniform(size * 0.12, size * 0.3, 2)
    m = ((yy - cy) / ry) ** 2 + ((xx - cx) / rx) ** 2 <= 1
    # a thin "panel" bar so the skeleton and boundary are non-trivial
    bar_y = int(cy)
    m[max(bar_y - 1, 0):bar_y + 1, int(max(cx - 2 * rx, 0)):int(min(cx + 2 * rx, size))] = True
    return m


def _sdf(mask):
    if not mask.any():
        return np.zeros(mask.shape, np.float32)
    if mask.all():
        return np.ones(mask.shape, np.float32)
    d = ndimage.distance_transform_edt(mask) - ndimage.distance_transform_edt(~mask)
    s = max(np.quantile(np.abs(d), 0.95), 1.0)
    return np.clip(d / s, -1, 1).astype(np.float32)


def build_tiny_artifacts(root: Path, n_train: int = 8, n_val: int = 4, n_test: int = 2, size: int = 32,
                         seed: int = 0) -> Path:
    """Tiny artifacts in the pipeline's layout: manifest, images, reference, teacher (with vflip),
    consensus, geometry, gates.  Pseudo-masks are perturbed copies of the reference masks."""
    rng = np.random.default_rng(seed)
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    n = n_train + n_val + n_test
    split = ["train"] * n_train + ["val"] * n_val + ["test"] * n_test
    ids = [f"img{i:03d}" for i in range(n)]
    truth = np.stack([_shape_mask(rng, size) for _ in range(n)])
    img = rng.integers(0, 40, (n, size, size, 3)).astype(np.uint8)
    img[truth] = rng.integers(150, 255, (int(truth.sum()), 3)).astype(np.uint8)
    K = len(PROMPTS)
    masks = np.empty((n, K, size, size), bool)
    for i in range(n):
        for k in range(K):
            shift = rng.integers(-1, 2, 2)
            masks[i, k] = np.roll(truth[i], tuple(shift), axis=(0, 1))
    scores = rng.uniform(0.3, 0.95, (n, K)).astype(np.float32)
    scores[1, 2:] = 0.0  # an image with only two valid prompts
    vflip = np.roll(truth, 1, axis=2)
    vscores = rng.uniform(0.4, 0.9, n).astype(np.float32)
    valid = scores > 0
    agreement = (masks * valid[:, :, None, None]).sum(1) / np.maximum(valid.sum(1), 1)[:, None, None]
    voted = agreement >= 0.5
    a = voted.reshape(n, -1).mean(1)
    c = np.array([agreement[i][voted[i]].mean() if voted[i].any() else 0.0 for i in range(n)])
    g = rng.uniform(0.2, 1.0, n)
    g[0] = 0.0  # a fully suppressed sample

    def meta(schema, stage):
        return make_meta(schema, stage, "test", {"tiny": True, "seed": seed})

    manifest = pd.DataFrame({
        "image_id": ids, "dataset": "tiny", "domain": "synthetic", "split": split,
        "group": split, "spacecraft": [f"sc{i % 3}" for i in range(n)], "image_path": [f"{i}.png" for i in ids],
        "mask_path": [f"{i}_m.png" for i in ids], "part_path": None, "width": size, "height": size,
        "sha256": "0" * 64})
    write_parquet(root / "manifest.parquet", manifest, meta("manifest", "prepare"))
    attrs = {"image_ids": ids}
    write_zarr(root / "images.zarr", {"image": img}, meta("images", "prepare"), attrs)
    write_zarr(root / "reference.zarr", {"mask": truth, "has_mask": np.ones(n, bool)},
               meta("reference", "prepare"), attrs)
    write_zarr(root / "teacher.zarr", {"masks": masks, "scores": scores, "vflip_masks": vflip,
                                       "vflip_scores": vscores},
               meta("teacher", "teacher"), {**attrs, "prompts": PROMPTS})
    write_zarr(root / "consensus.zarr", {"agreement": agreement.astype(np.float32), "voted": voted,
                                         "n_valid": valid.sum(1).astype(np.int16)},
               meta("consensus", "consensus"), attrs)
    write_zarr(root / "geometry.zarr", {"sdf": np.stack([_sdf(m) for m in voted]),
                                        "skeleton": np.stack([m & (ndimage.distance_transform_edt(m) > 1.5)
                                                              for m in voted])},
               meta("geometry", "geometry"), attrs)
    gates = pd.DataFrame({"image_id": ids, "split": split, "c": c, "v": valid.sum(1) / 6.0, "a": a,
                          "a0": float(np.median(a[:n_train])), "g_conf": g, "g_valid": 1.0,
                          "g_area": 1.0, "g": g, "n_valid": valid.sum(1)})
    write_parquet(root / "gates.parquet", gates, meta("gates", "geometry"))
    return root


def tiny_cfg(**over) -> dict:
    """The repo's train section with tiny-run overrides (fp32, 2 epochs, 1 thread)."""
    cfg = section(load_params(REPO / "params.yaml"), "train")
    cfg.update({"epochs_stage1": 2, "epochs_stage2": 2, "precision": "fp32", "num_threads": 1,
                "batch_size": 4})
    # the paper recipe's other parts (the demo's params.yaml may select another recipe): tests that
    # need a part set it themselves
    cfg.update({k: v for k, v in RECIPES["paper"]["train"].items() if k != "precision"}, recipe="paper")
    cfg["gabi"] = {**cfg["gabi"], "epochs": 2}
    cfg.update(over)
    return cfg


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return build_tiny_artifacts(tmp_path_factory.mktemp("tiny") / "artifacts")


def load_arrays(art, method_name, cfg):
    """(TrainData, ValData) of a method from the tiny artifacts, opened by the stage's wiring."""
    from pipeline.methods import get_method
    from stages.train import load_inputs

    data, val, _ = load_inputs(art, get_method(method_name), cfg)
    return data, val


def _run(method_name, art, cfg, seed=42, init_state=None, resume_dir=None, checkpointer=None, **kw):
    from pipeline import training
    from pipeline.methods import get_method
    from pipeline.checkpointing import FileCheckpointer

    data, val = load_arrays(art, method_name, cfg)
    if checkpointer is None:
        checkpointer = FileCheckpointer(resume_dir) if resume_dir is not None else training.NoCheckpointer()
    return training.train(get_method(method_name), cfg, data, val, seed, init_state=init_state,
                          checkpointer=checkpointer, show_progress=False, **kw)


def _weights(model):
    return {k: v.clone() for k, v in model.state_dict().items()}


def _assert_same(a, b):
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


# --------------------------------------------------------------------------------------------------
def test_few_steps_lower_the_loss(tiny):
    res = _run("plain", tiny, tiny_cfg(epochs_stage1=6, lr_stage1=3e-3, schedule="constant"))
    loss = res.log["loss"].to_numpy()
    assert np.all(np.isfinite(loss)) and loss[-1] < 0.8 * loss[0]
    assert set(res.log.columns) >= {"epoch", "stage", "loss", "val_iou", "val_bf1", "lr", "bbce", "dice"}
    assert "seconds" not in res.log.columns  # wall clock lives in res.timings, not in the checkpoint
    assert [t["epoch"] for t in res.timings] == res.log["epoch"].tolist()
    assert all(t["seconds"] >= 0 for t in res.timings)
    assert res.log["val_iou"].notna().all()
    # Stage-I selection = the best validation IoU epoch
    assert res.selected_epoch == int(res.log.loc[res.log["val_iou"].idxmax(), "epoch"])


def test_same_seed_same_weights_and_different_seed_differs(tiny):
    cfg = tiny_cfg(epochs_stage1=1)
    a, b = _run("plain", tiny, cfg), _run("plain", tiny, cfg)
    _assert_same(_weights(a.model), _weights(b.model))
    pd.testing.assert_frame_equal(a.log, b.log)
    c = _run("plain", tiny, cfg, seed=7)
    assert not torch.equal(a.model.enc1[0][0].weight, c.model.enc1[0][0].weight)


def test_bf16_autocast_run_is_deterministic(tiny):
    cfg = tiny_cfg(epochs_stage1=1, precision="bf16")
    a, b = _run("plain", tiny, cfg), _run("plain", tiny, cfg)
    assert a.info["autocast"] == "bfloat16"
    _assert_same(_weights(a.model), _weights(b.model))


@pytest.mark.parametrize("method", ["plain", "geodistill"])
def test_resume_after_interruption_gives_identical_weights(tiny, tmp_path, method):
    cfg = tiny_cfg(epochs_stage1=3, epochs_stage2=3, lr_stage1=2e-3)
    init = _run("plain", tiny, tiny_cfg(epochs_stage1=1)).model.mask_path_state_dict() if method != "plain" else None
    full = _run(method, tiny, cfg, init_state=init, resume_dir=tmp_path / "uninterrupted")

    class Killed(Exception):
        pass

    def kill_after_2(epoch, row):
        if epoch == 2:
            raise Killed

    with pytest.raises(Killed):
        _run(method, tiny, cfg, init_state=init, resume_dir=tmp_path / "r", callback=kill_after_2)
    state = torch.load(tmp_path / "r" / "state.pt", weights_only=False)
    assert state["epoch"] == 2
    seen = []
    resumed = _run(method, tiny, cfg, init_state=init, resume_dir=tmp_path / "r", callback=lambda e, r: seen.append(e))
    assert seen == [3]  # only the missing epoch ran
    _assert_same(_weights(full.model), _weights(resumed.model))
    pd.testing.assert_frame_equal(full.log, resumed.log)
    # a finished state makes a rerun instant (no epoch runs) and gives the same model
    again = _run(method, tiny, cfg, init_state=init, resume_dir=tmp_path / "r", callback=lambda e, r: seen.append(e))
    assert seen == [3]
    _assert_same(_weights(full.model), _weights(again.model))


def test_train_runs_from_arrays_with_an_in_memory_checkpointer_and_resumes():
    """No artifacts: arrays in, model and log out; a MemoryCheckpointer resumes an interrupted run."""
    from pipeline import training
    from pipeline.methods import get_method

    rng = np.random.default_rng(3)
    masks = np.stack([_shape_mask(rng, 24) for _ in range(7)])
    images = np.where(masks[..., None], 200, rng.integers(0, 40, (7, 24, 24, 3))).astype(np.uint8)
    data = training.TrainData(image_ids=[f"t{i}" for i in range(5)], images=images[:5], mask=masks[:5],
                              area=masks[:5].reshape(5, -1).mean(1).astype(np.float32),
                              gate=np.ones(5, np.float32))
    val = training.ValData(image_ids=["v0", "v1"], images=images[5:], masks=masks[5:])
    cfg = tiny_cfg(epochs_stage1=3, lr_stage1=2e-3, batch_size=2)
    m = get_method("plain")
    full = training.train(m, cfg, data, val, 42, checkpointer=training.NoCheckpointer(), show_progress=False)
    assert list(full.log["epoch"]) == [1, 2, 3] and full.log["val_iou"].notna().all()

    class Killed(Exception):
        pass

    def kill_after_1(epoch, row):
        if epoch == 1:
            raise Killed

    ck = training.MemoryCheckpointer()
    with pytest.raises(Killed):
        training.train(m, cfg, data, val, 42, checkpointer=ck, callback=kill_after_1, show_progress=False)
    assert ck.state["epoch"] == 1 and len(ck.state["log"]) == 1
    seen = []
    resumed = training.train(m, cfg, data, val, 42, checkpointer=ck, show_progress=False,
                             callback=lambda e, r: seen.append(e))
    assert seen == [2, 3]
    _assert_same(_weights(full.model), _weights(resumed.model))
    pd.testing.assert_frame_equal(full.log, resumed.log)
    # a state of another run (different seed) is ignored, not resumed
    other = training.train(m, cfg, data, val, 7, checkpointer=ck, show_progress=False,
                           callback=lambda e, r: seen.append(e))
    assert seen == [2, 3, 1, 2, 3] and other.log["epoch"].tolist() == [1, 2, 3]


@pytest.mark.parametrize("method", ["plain", "geodistill", "gabi", "no_gate"])
def test_training_loss_is_the_losses_module_objective(tiny, method):
    """The logged epoch-1 terms of a one-batch run (lr 0) equal losses.refine_loss (eq:refine-loss) with
    the plan's weights -- and, for Stage I, losses.raw_loss (eq:raw-loss) -- on the untrained model."""
    from pipeline import losses, training
    from pipeline.methods import get_method, resolve_plan

    m = get_method(method)
    cfg = tiny_cfg(epochs_stage1=1, epochs_stage2=1, batch_size=64, channels_last=False,
                   gabi={"epochs": 1, "lambda_dist": 0.002, "lambda_boundary": 0.05})
    init = _run("plain", tiny, cfg).model.mask_path_state_dict() if m.init == "stage1" else None
    data, val = load_arrays(tiny, method, cfg)
    res = training.train(m, cfg, data, val, 42, init_state=init, checkpointer=training.NoCheckpointer(),
                         show_progress=False)
    row = res.log.set_index("epoch").loc[1]

    model = training.build_model(m, cfg, 42, init).train()
    x = torch.from_numpy(np.asarray(data.images)).permute(0, 3, 1, 2).float() / 255.0
    targets = {"mask": torch.from_numpy(np.asarray(data.mask)).unsqueeze(1).float(), "area": torch.from_numpy(data.area)}
    if data.sdf is not None:
        targets["sdf"] = torch.from_numpy(np.asarray(data.sdf)).unsqueeze(1)
        targets["skeleton"] = torch.from_numpy(np.asarray(data.skeleton)).unsqueeze(1).float()
    with torch.no_grad():
        out = model.forward_train(x)
    gates = torch.from_numpy(data.gate)
    weights = resolve_plan(m, cfg).weights
    ref = losses.refine_loss(out, targets, gates, weights, training.loss_constants(cfg))
    for k, v in ref.items():
        assert row[k] == pytest.approx(v.item(), rel=1e-5), k
    assert row["raw"] == pytest.approx(losses.raw_loss(out["mask"], targets["mask"]).item(), rel=1e-5)
    if method == "plain":
        assert row["loss"] == pytest.approx(row["raw"], rel=1e-6)
        assert set(ref) == {"loss", "raw", "bbce", "dice"}
    if method == "no_gate":  # g = 1: the ungated geometry terms
        assert np.all(data.gate == 1.0)
        assert row["sdf"] == pytest.approx(losses.sdf_loss(out["sdf"], targets["sdf"], torch.ones(len(data))).item(),
                                           rel=1e-5)


def test_nan_loss_raises_training_diverged(tiny, tmp_path):
    cfg = tiny_cfg(epochs_stage1=1, lr_stage1=float("inf"), epochs_stage2=1)
    with pytest.raises(TrainingDiverged, match="non-finite loss at epoch 1"):
        _run("plain", tiny, cfg, resume_dir=tmp_path / "nan")
    assert not (tmp_path / "nan" / "state.pt").exists()
    # one step per epoch: the loss was finite, the weights after the step are not -> also caught
    with pytest.raises(TrainingDiverged, match="non-finite weights after epoch 1"):
        _run("plain", tiny, {**cfg, "batch_size": 8}, resume_dir=tmp_path / "nan2")
    assert not (tmp_path / "nan2" / "state.pt").exists()


def test_warm_start_copies_stage1_weights_and_adds_fresh_heads(tiny):
    from pipeline.methods import get_method
    from pipeline.training import build_model

    stage1 = _run("plain", tiny, tiny_cfg(epochs_stage1=1))
    init = stage1.model.mask_path_state_dict()
    m = build_model(get_method("geodistill"), tiny_cfg(), 42, init)
    for k, v in m.mask_path_state_dict().items():
        assert torch.equal(v, init[k]), k
    assert m.geometry_heads is not None
    # the Stage-II run's epoch 0 (before any update) is exactly the Stage-I model
    res = _run("geodistill", tiny, tiny_cfg(epochs_stage2=1), init_state=init)
    assert list(res.log["epoch"]) == [0, 1] and np.isnan(res.log.loc[0, "loss"])
    assert res.log.loc[0, "val_iou"] == pytest.approx(stage1.log["val_iou"].max())  # plain selected its best
    assert res.selected_epoch == 1  # stage2_select: last
    assert np.isfinite(res.log.loc[1, ["sdf", "skel", "area", "raw"]].astype(float)).all()
    assert not torch.equal(res.model.enc1[0][0].weight, init["enc1.0.0.weight"])


def test_reference_masks_of_training_rows_never_reach_a_loss(tmp_path):
    """Corrupting reference masks of train (and test) rows leaves the trained weights unchanged;
    corrupting a validation mask may change only the selection."""
    a = build_tiny_artifacts(tmp_path / "a")
    b = build_tiny_artifacts(tmp_path / "b")
    ref = open_artifact(b / "reference.zarr")
    masks = ref.numpy("mask")
    split = open_artifact(b / "manifest.parquet").df["split"].to_numpy()
    masks[split != "val"] = ~masks[split != "val"]
    write_zarr(b / "reference.zarr", {"mask": masks, "has_mask": ref.numpy("has_mask")}, ref.meta,
               {"image_ids": ref.attrs["image_ids"]})
    cfg = tiny_cfg(epochs_stage1=2)
    ra, rb = _run("plain", a, cfg), _run("plain", b, cfg)
    _assert_same(_weights(ra.model), _weights(rb.model))
    from pipeline import training
    from pipeline.methods import get_method

    _, val = load_arrays(b, "plain", cfg)
    assert len(val) == int((split == "val").sum())
    np.testing.assert_array_equal(val.masks, masks[split == "val"])
    # the boundary is explicit in the API: training data refuses reference masks
    m = get_method("plain")
    inputs = {n: open_artifact(b / f, n) for n, f in [("manifest", "manifest.parquet"), ("images", "images.zarr"),
                                                        ("consensus", "consensus.zarr")]}
    assert "reference" not in training.training_inputs(m, cfg)
    with pytest.raises(ValueError, match="reference masks never enter training"):
        training.training_data(m, cfg, {**inputs, "reference": ref})


# --------------------------------------------------------------------------------------------------
# the stage command
# --------------------------------------------------------------------------------------------------
def _params_file(tmp_path, runs=None) -> Path:
    """The repo's params file with 1-epoch fp32 training and ``protocol.runs`` (default: plain and
    geodistill for seed 42)."""
    import yaml

    p = yaml.safe_load((REPO / "params.yaml").read_text())
    p["train"].update({"epochs_stage1": 1, "epochs_stage2": 1, "precision": "fp32", "num_threads": 1})
    p["protocol"]["runs"] = {**{m: [] for m in p["protocol"]["runs"]},
                             **(runs or {"plain": [42], "geodistill": [42]})}
    out = tmp_path / "params.yaml"
    out.write_text(yaml.safe_dump(p))
    return out


def _cli(*args, cwd):
    env = {"GEODISTILL_QUIET": "1", "PATH": "/usr/bin:/bin", "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-m", "stages.train", *args], cwd=cwd, env=env,
                          capture_output=True, text=True)


def test_checkpoint_selection_scores_validation_at_the_selection_tau(tiny):
    """training's selection tau is calibrate.fixed_tau (the default is the schema's value, which the
    train stage passes from params): another tau gives other validation scores, the same tau the same."""
    from pipeline.params import PAPER

    cfg = tiny_cfg(epochs_stage1=1)
    a = _run("plain", tiny, cfg)
    same = _run("plain", tiny, cfg, selection_tau=PAPER.calibrate.fixed_tau)
    other = _run("plain", tiny, cfg, selection_tau=0.95)
    pd.testing.assert_frame_equal(a.log, same.log)
    assert not np.allclose(a.log["val_iou"], other.log["val_iou"])
    assert a.log["val_tau_cal"].equals(other.log["val_tau_cal"])  # the per-epoch calibrated tau does not move


def test_stage_command_trains_writes_checkpoint_and_warm_starts(tiny, tmp_path):
    from pipeline.inference import load_student

    params = _params_file(tmp_path)
    ck = tmp_path / "checkpoints"
    common = ["--params", str(params), "--artifacts", str(tiny), "--device", "cpu",
              "--resume-dir", str(tmp_path / "cache")]
    r1 = _cli("--stage", "1", "--method", "plain", "--seed", "42", "--out", str(ck / "plain/42"), *common, cwd=tmp_path)
    assert r1.returncode == 0, r1.stderr
    r2 = _cli("--stage", "2", "--method", "geodistill", "--seed", "42", "--init", str(ck / "plain/42"),
              "--out", str(ck / "geodistill/42"), *common, cwd=tmp_path)
    assert r2.returncode == 0, r2.stderr
    model, payload = load_student(ck / "geodistill/42")
    assert payload["method"] == "geodistill" and payload["selected_epoch"] == 1
    assert payload["geometry_state_dict"] is not None
    art = open_artifact(ck / "geodistill/42", "checkpoint")
    schemas = sorted(i["schema"] for i in art.meta.inputs)
    assert schemas == sorted(["manifest", "images", "gates", "consensus", "geometry", "checkpoint", "reference"])
    assert art.meta.params["method"] == "geodistill" and art.meta.params["seed"] == 42
    assert not any(k.startswith("train.gabi") for k in art.meta.params["params"])  # only keys the method reads
    # checkpoint selection scores validation masks at calibrate.fixed_tau: it is in the fingerprint
    assert art.meta.params["params"][SELECTION_TAU_KEY] == load_params(params)["calibrate"]["fixed_tau"]
    log = art.table()
    assert list(log["epoch"]) == [0, 1] and set(log["stage"]) == {2}
    assert payload["resolution"] == int(open_artifact(tiny / "images.zarr").numpy("image").shape[1])
    # a second run with the same params and inputs resumes from its state and is byte-for-byte the same
    before = (ck / "geodistill/42" / "model.safetensors").read_bytes()
    r3 = _cli("--stage", "2", "--method", "geodistill", "--seed", "42", "--init", str(ck / "plain/42"),
              "--out", str(ck / "geodistill/42"), *common, cwd=tmp_path)
    assert r3.returncode == 0, r3.stderr
    assert (ck / "geodistill/42" / "model.safetensors").read_bytes() == before


def test_checkpoints_are_byte_identical_under_source_date_epoch(tiny, tmp_path, monkeypatch):
    """Issue 16 item 8: two independent runs (no shared resume state) give the same bytes in every
    checkpoint file; the wall clock goes to the separate timings file only."""

    from pipeline import catalog

    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    params = _params_file(tmp_path)
    outs = []
    out = tmp_path / "ck" / "plain/42"
    for k in range(2):  # the same paths, nothing kept between the runs
        shutil.rmtree(tmp_path / "ck", ignore_errors=True)
        shutil.rmtree(tmp_path / "cache", ignore_errors=True)
        r = subprocess.run([sys.executable, "-m", "stages.train", "--stage", "1", "--method", "plain", "--seed", "42",
                            "--out", str(out), "--params", str(params), "--artifacts", str(tiny), "--device", "cpu",
                            "--resume-dir", str(tmp_path / "cache")], cwd=tmp_path, capture_output=True, text=True,
                           env={"GEODISTILL_QUIET": "1", "PATH": "/usr/bin:/bin", "PYTHONPATH": str(REPO),
                                "SOURCE_DATE_EPOCH": "1700000000"})
        assert r.returncode == 0, r.stderr
        outs.append({f.name: f.read_bytes() for f in sorted(out.iterdir())})
    assert set(outs[0]) == {"model.safetensors", "model.json", "log.parquet", "meta.json"}
    for name in outs[0]:
        assert outs[0][name] == outs[1][name], name
    timings = json.loads(catalog.path("train_timings", tiny, method="plain", seed=42).read_text())
    assert [e["epoch"] for e in timings["epochs"]] == [1] and timings["epochs"][0]["seconds"] > 0


def test_stage_command_errors_are_one_line(tiny, tmp_path):
    params = _params_file(tmp_path)
    r = _cli("--params", str(params), "--stage", "1", "--method", "nope", "--seed", "42",
             "--artifacts", str(tiny), "--out", str(tmp_path / "x"), cwd=tmp_path)
    assert r.returncode == 2 and "--method 'nope'" in r.stderr and "Traceback" not in r.stderr
    r = _cli("--params", str(params), "--stage", "2", "--method", "geodistill", "--seed", "42",
             "--artifacts", str(tiny), "--init", str(tmp_path / "missing"), "--out", str(tmp_path / "y"),
             cwd=tmp_path)
    assert r.returncode == 2 and "missing" in r.stderr and "Traceback" not in r.stderr
    # divergence (a finite but absurd lr: the params schema rejects inf): exit code 1, one line, no checkpoint
    r = _cli("--params", str(params), "--set", "train.lr_stage1=1.0e+30", "--stage", "1", "--method", "plain",
             "--seed", "42", "--artifacts", str(tiny), "--out", str(tmp_path / "z"), "--device", "cpu",
             "--resume-dir", str(tmp_path / "cache2"), cwd=tmp_path)
    assert r.returncode == 1 and "diverged" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "z").exists()


@pytest.fixture(scope="module")
def tiny18(tmp_path_factory):
    """18 training images: several blocks of frozen Stage-I anchors (training.ANCHOR_BATCH = 4), the last one short."""
    return build_tiny_artifacts(tmp_path_factory.mktemp("tiny18") / "artifacts", n_train=18)


@pytest.mark.parametrize("method", ["plain", "geodistill", "afs_control", "supervised_ceiling",
                                    "geodistill_adaptive"])
def test_streaming_data_gives_the_in_memory_batches_and_weights(tiny18, method, tmp_path, monkeypatch):
    """load_inputs reads images and targets from the Zarr artifacts per batch (row sources, prefetched;
    the AFS control's fused mask computed per batch; the adaptive method's frozen Stage-I anchors
    spilled to a scratch Zarr store, removed after the run); the same data loaded into memory gives
    the same batches of an epoch and bit-identical weights and log."""
    import dataclasses
    import tempfile

    from pipeline import training
    from pipeline.methods import get_method
    from pipeline.streaming import MappedRows, RowSource

    m = get_method(method)
    cfg = tiny_cfg(augment_hflip=True)
    cfg["adaptive"] = {**cfg["adaptive"], "ratio_boundary": 0.0}  # anchored mode: the anchor term is on
    init = _run("plain", tiny18, cfg).model.mask_path_state_dict() if m.init == "stage1" else None
    lazy, val = load_arrays(tiny18, method, cfg)
    assert isinstance(lazy.images, RowSource) and isinstance(lazy.mask, RowSource)
    assert isinstance(lazy.mask, MappedRows) == (method == "afs_control")
    assert (lazy.sdf is not None) == m.needs_geometry
    memory = dataclasses.replace(lazy, **{k: np.asarray(getattr(lazy, k)) for k in ("images", "mask", "sdf", "skeleton")
                                          if getattr(lazy, k) is not None})
    dev = torch.device("cpu")
    t_lazy, t_mem = training._tensors(lazy, dev, None), training._tensors(memory, dev, None)
    assert training._streaming(t_lazy) and not training._streaming(t_mem)
    idx = torch.tensor([5, 0, 3])
    flip = torch.tensor([True, False, True])
    for k, v in training._batch(t_mem, idx, flip, True).items():
        assert torch.equal(v, training._batch(t_lazy, idx, flip, True)[k]), k
    spilled = []
    monkeypatch.setattr(training, "spill_rows", lambda *a: spilled.append(a[0]) or spill_rows(*a))
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    runs = [training.train(m, cfg, d, val, 7, init_state=init, checkpointer=training.NoCheckpointer(),
                           show_progress=False) for d in (lazy, memory)]
    _assert_same(_weights(runs[0].model), _weights(runs[1].model))
    timing = [c for c in runs[0].log.columns if "sec" in c or "time" in c]
    pd.testing.assert_frame_equal(runs[0].log.drop(columns=timing), runs[1].log.drop(columns=timing))
    assert len(spilled) == (method == "geodistill_adaptive")  # the streamed run only
    if spilled:
        assert runs[0].info["mode"] == "anchored" and runs[0].log["anchor"].notna().any()
    assert not list(tmp_path.glob("geodistill_anchor_*"))  # the scratch store is removed


def test_prefetch_keeps_order_and_raises_the_producers_error():
    from pipeline.streaming import prefetch

    assert list(prefetch(iter(range(50)), depth=2)) == list(range(50))

    def broken():
        yield 1
        raise ValueError("bad chunk")

    with pytest.raises(ValueError, match="bad chunk"):
        list(prefetch(broken()))
