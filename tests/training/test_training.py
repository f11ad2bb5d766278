"""Training loop: tiny runs lower the loss, determinism, resume after interruption, divergence,
warm start, the reference-mask boundary, and the train stage command, on the tiny artifacts of
tests/builders/training.py (the ``tiny`` fixture is in tests/conftest.py).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
import torch

from pipeline.artifacts.store import open_artifact, write_zarr
from pipeline.runtime.errors import TrainingDiverged
from pipeline.methods import SELECTION_TAU_KEY
from pipeline.params import load_params
from pipeline.training.streaming import spill_rows
from tests.builders.training import (REPO, assert_same_state, build_tiny_artifacts, clone_state, load_arrays, shape_mask,
                                     tiny_cfg, train_cli, train_params_file)
from pipeline.training.settings import loss_constants
from pipeline.training.checkpointing import FileCheckpointer, NoCheckpointer
from tests.builders.training import MemoryCheckpointer


def _run(method_name, art, cfg, seed=42, init_state=None, resume_dir=None, checkpointer=None, **kw):
    from pipeline.training import loop as training
    from pipeline.methods import get_method

    data, val = load_arrays(art, method_name, cfg)
    if checkpointer is None:
        checkpointer = FileCheckpointer(resume_dir) if resume_dir is not None else NoCheckpointer()
    return training.train(get_method(method_name), cfg, data, val, seed, init_state=init_state,
                          checkpointer=checkpointer, show_progress=False, **kw)


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
    assert_same_state(clone_state(a.model), clone_state(b.model))
    pd.testing.assert_frame_equal(a.log, b.log)
    c = _run("plain", tiny, cfg, seed=7)
    assert not torch.equal(a.model.enc1[0][0].weight, c.model.enc1[0][0].weight)


def test_bf16_autocast_run_is_deterministic(tiny):
    cfg = tiny_cfg(epochs_stage1=1, precision="bf16")
    a, b = _run("plain", tiny, cfg), _run("plain", tiny, cfg)
    assert a.info["autocast"] == "bfloat16"
    assert_same_state(clone_state(a.model), clone_state(b.model))


@pytest.mark.parametrize("method", ["plain", "geodistill"])
def test_resume_after_interruption_gives_identicalclone_state(tiny, tmp_path, method):
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
    assert_same_state(clone_state(full.model), clone_state(resumed.model))
    pd.testing.assert_frame_equal(full.log, resumed.log)
    # a finished state makes a rerun instant (no epoch runs) and gives the same model
    again = _run(method, tiny, cfg, init_state=init, resume_dir=tmp_path / "r", callback=lambda e, r: seen.append(e))
    assert seen == [3]
    assert_same_state(clone_state(full.model), clone_state(again.model))


def test_train_runs_from_arrays_with_an_in_memory_checkpointer_and_resumes():
    """No artifacts: arrays in, model and log out; a MemoryCheckpointer resumes an interrupted run."""
    from pipeline.training import loop as training
    from pipeline.methods import get_method

    rng = np.random.default_rng(3)
    masks = np.stack([shape_mask(rng, 24) for _ in range(7)])
    images = np.where(masks[..., None], 200, rng.integers(0, 40, (7, 24, 24, 3))).astype(np.uint8)
    data = training.TrainData(image_ids=[f"t{i}" for i in range(5)], images=images[:5], mask=masks[:5],
                              area=masks[:5].reshape(5, -1).mean(1).astype(np.float32),
                              gate=np.ones(5, np.float32))
    val = training.ValData(image_ids=["v0", "v1"], images=images[5:], masks=masks[5:])
    cfg = tiny_cfg(epochs_stage1=3, lr_stage1=2e-3, batch_size=2)
    m = get_method("plain")
    full = training.train(m, cfg, data, val, 42, checkpointer=NoCheckpointer(), show_progress=False)
    assert list(full.log["epoch"]) == [1, 2, 3] and full.log["val_iou"].notna().all()

    class Killed(Exception):
        pass

    def kill_after_1(epoch, row):
        if epoch == 1:
            raise Killed

    ck = MemoryCheckpointer()
    with pytest.raises(Killed):
        training.train(m, cfg, data, val, 42, checkpointer=ck, callback=kill_after_1, show_progress=False)
    assert ck.state["epoch"] == 1 and len(ck.state["log"]) == 1
    seen = []
    resumed = training.train(m, cfg, data, val, 42, checkpointer=ck, show_progress=False,
                             callback=lambda e, r: seen.append(e))
    assert seen == [2, 3]
    assert_same_state(clone_state(full.model), clone_state(resumed.model))
    pd.testing.assert_frame_equal(full.log, resumed.log)
    # a state of another run (different seed) is ignored, not resumed
    other = training.train(m, cfg, data, val, 7, checkpointer=ck, show_progress=False,
                           callback=lambda e, r: seen.append(e))
    assert seen == [2, 3, 1, 2, 3] and other.log["epoch"].tolist() == [1, 2, 3]


@pytest.mark.parametrize("method", ["plain", "geodistill", "gabi", "no_gate"])
def test_training_loss_is_the_losses_module_objective(tiny, method):
    """The logged epoch-1 terms of a one-batch run (lr 0) equal losses.refine_loss (eq:refine-loss) with
    the plan's weights -- and, for Stage I, losses.raw_terms (eq:raw-loss) -- on the untrained model."""
    from pipeline import losses
    from pipeline.training import loop as training
    from pipeline.methods import get_method, resolve_plan

    m = get_method(method)
    cfg = tiny_cfg(epochs_stage1=1, epochs_stage2=1, batch_size=64, channels_last=False,
                   gabi={"epochs": 1, "lambda_dist": 0.002, "lambda_boundary": 0.05})
    init = _run("plain", tiny, cfg).model.mask_path_state_dict() if m.init == "stage1" else None
    data, val = load_arrays(tiny, method, cfg)
    res = training.train(m, cfg, data, val, 42, init_state=init, checkpointer=NoCheckpointer(),
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
    ref = losses.refine_loss(out, targets, gates, weights, loss_constants(cfg))
    for k, v in ref.items():
        assert row[k] == pytest.approx(v.item(), rel=1e-5), k
    assert row["raw"] == pytest.approx(losses.raw_terms(out["mask"], targets["mask"])["raw"].item(), rel=1e-5)
    if method == "plain":
        assert row["loss"] == pytest.approx(row["raw"], rel=1e-6)
        assert set(ref) == {"loss", "raw", "bbce", "dice"}
    if method == "no_gate":  # g = 1: the ungated geometry terms
        assert np.all(data.gate == 1.0)
        assert row["sdf"] == pytest.approx(losses.sdf_loss(out["sdf"], targets["sdf"], torch.ones(len(data))).item(),
                                           rel=1e-5)


def test_nan_loss_raises_training_diverged(tiny, tmp_path, monkeypatch):
    # an infinite learning rate, which the schema refuses in params: the first step makes the weights inf
    monkeypatch.setattr("pipeline.training.settings.method_lr", lambda method, cfg: float("inf"))
    cfg = tiny_cfg(epochs_stage1=1, epochs_stage2=1)
    with pytest.raises(TrainingDiverged, match="non-finite loss at epoch 1"):
        _run("plain", tiny, cfg, resume_dir=tmp_path / "nan")
    assert not (tmp_path / "nan" / "state.pt").exists()
    # one step per epoch: the loss was finite, the weights after the step are not -> also caught
    with pytest.raises(TrainingDiverged, match="non-finite weights after epoch 1"):
        _run("plain", tiny, {**cfg, "batch_size": 8}, resume_dir=tmp_path / "nan2")
    assert not (tmp_path / "nan2" / "state.pt").exists()


def test_warm_start_copies_stage1_weights_and_adds_fresh_heads(tiny):
    from pipeline.methods import get_method
    from pipeline.training.loop import build_model

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
    assert_same_state(clone_state(ra.model), clone_state(rb.model))
    from pipeline.training import inputs as training
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
    from pipeline.evaluation.inference import load_student

    params = train_params_file(tmp_path)
    ck = tmp_path / "checkpoints"
    common = ["--params", str(params), "--artifacts", str(tiny), "--device", "cpu",
              "--resume-dir", str(tmp_path / "cache")]
    r1 = train_cli("--stage", "1", "--method", "plain", "--seed", "42", "--out", str(ck / "plain/42"), *common, cwd=tmp_path)
    assert r1.returncode == 0, r1.stderr
    r2 = train_cli("--stage", "2", "--method", "geodistill", "--seed", "42", "--init", str(ck / "plain/42"),
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
    r3 = train_cli("--stage", "2", "--method", "geodistill", "--seed", "42", "--init", str(ck / "plain/42"),
              "--out", str(ck / "geodistill/42"), *common, cwd=tmp_path)
    assert r3.returncode == 0, r3.stderr
    assert (ck / "geodistill/42" / "model.safetensors").read_bytes() == before


def test_checkpoints_are_byte_identical_under_source_date_epoch(tiny, tmp_path, monkeypatch):
    """Issue 16 item 8: two independent runs (no shared resume state) give the same bytes in every
    checkpoint file; the wall clock goes to the separate timings file only."""

    from pipeline import catalog

    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    params = train_params_file(tmp_path)
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
    params = train_params_file(tmp_path)
    r = train_cli("--params", str(params), "--stage", "1", "--method", "nope", "--seed", "42",
             "--artifacts", str(tiny), "--out", str(tmp_path / "x"), cwd=tmp_path)
    assert r.returncode == 2 and "--method 'nope'" in r.stderr and "Traceback" not in r.stderr
    r = train_cli("--params", str(params), "--stage", "2", "--method", "geodistill", "--seed", "42",
             "--artifacts", str(tiny), "--init", str(tmp_path / "missing"), "--out", str(tmp_path / "y"),
             cwd=tmp_path)
    assert r.returncode == 2 and "missing" in r.stderr and "Traceback" not in r.stderr
    # divergence (a finite but absurd lr: the params schema rejects inf): exit code 1, one line, no checkpoint
    r = train_cli("--params", str(params), "--set", "train.lr_stage1=1.0e+30", "--stage", "1", "--method", "plain",
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
def test_streaming_data_gives_the_in_memory_batches_andclone_state(tiny18, method, tmp_path, monkeypatch):
    """load_inputs reads images and targets from the Zarr artifacts per batch (row sources, prefetched;
    the AFS control's fused mask computed per batch; the adaptive method's frozen Stage-I anchors
    spilled to a scratch Zarr store, removed after the run); the same data loaded into memory gives
    the same batches of an epoch and bit-identical weights and log."""
    import dataclasses
    import tempfile

    from pipeline.training import loop as training
    from pipeline.methods import get_method
    from pipeline.training.streaming import MappedRows, RowSource

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
    for k, v in training.make_batch(t_mem, idx, flip, True).items():
        assert torch.equal(v, training.make_batch(t_lazy, idx, flip, True)[k]), k
    spilled = []
    monkeypatch.setattr(training, "spill_rows", lambda *a: spilled.append(a[0]) or spill_rows(*a))
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    runs = [training.train(m, cfg, d, val, 7, init_state=init, checkpointer=NoCheckpointer(),
                           show_progress=False) for d in (lazy, memory)]
    assert_same_state(clone_state(runs[0].model), clone_state(runs[1].model))
    timing = [c for c in runs[0].log.columns if "sec" in c or "time" in c]
    pd.testing.assert_frame_equal(runs[0].log.drop(columns=timing), runs[1].log.drop(columns=timing))
    assert len(spilled) == (method == "geodistill_adaptive")  # the streamed run only
    if spilled:
        assert runs[0].info["mode"] == "anchored" and runs[0].log["anchor"].notna().any()
    assert not list(tmp_path.glob("geodistill_anchor_*"))  # the scratch store is removed


def test_prefetch_keeps_order_and_raises_the_producers_error():
    from pipeline.training.streaming import prefetch

    assert list(prefetch(iter(range(50)), depth=2)) == list(range(50))

    def broken():
        yield 1
        raise ValueError("bad chunk")

    with pytest.raises(ValueError, match="bad chunk"):
        list(prefetch(broken()))
