"""Baselines, ablations and the quality-adaptive mode (issue #6): the method table, the filters,
the mode switch, g = 1 for no_gate, and a few-step run + loadable checkpoint for every method."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline import losses
from pipeline.artifacts.lineage import make_meta
from pipeline.artifacts.store import open_artifact
from pipeline.runtime.errors import InputError
from pipeline.methods import METHODS, adaptive_mode, get_method, input_artifacts, param_keys, resolve_plan
from pipeline.training.filters import afs_fuse, afs_keep, confidence_pass, mean_valid_score, pass_ratio
from pipeline.training.checkpointing import NoCheckpointer
from tests.builders.training import load_arrays, tiny_cfg


def _load(tiny, name, cfg):
    """(TrainData, the artifacts opened) of a method, through the train stage's wiring."""
    from pipeline.training.inputs import load_inputs

    data, _, inputs = load_inputs(tiny, get_method(name), cfg)
    return data, inputs


def _tables(art):
    gates = open_artifact(art / "gates.parquet").df
    manifest = open_artifact(art / "manifest.parquet").df
    teacher = open_artifact(art / "teacher.zarr")
    train = (manifest["split"] == "train").to_numpy()
    return gates[train].reset_index(drop=True), teacher, train


# ---- the table ----------------------------------------------------------------------------------
def test_every_protocol_method_is_defined_with_its_stage():
    from pipeline.params import load_params
    from pipeline.profiles import ABLATIONS, MAIN_METHODS

    runs = load_params()["protocol"]["runs"]
    assert set(runs) <= set(METHODS) and set(MAIN_METHODS) | set(ABLATIONS) <= set(METHODS)
    for name in ("plain", "confidence_filtered", "afs_control"):
        assert get_method(name).stage == 1
    for name in ["geodistill", "gabi", "geodistill_adaptive", *ABLATIONS]:
        assert get_method(name).stage == 2
    with pytest.raises(InputError, match="--method 'nope'"):
        get_method("nope")


def test_method_epochs_and_terms_follow_the_paper_tables():
    from pipeline.methods import method_epochs, method_lr
    from pipeline.profiles import load_profile

    cfg = load_profile("paper")["train"]
    assert method_epochs(get_method("plain"), cfg) == 20 and method_lr(get_method("plain"), cfg) == 5e-4
    assert method_epochs(get_method("geodistill"), cfg) == 10 and method_lr(get_method("geodistill"), cfg) == 1e-4
    assert method_epochs(get_method("gabi"), cfg) == 30
    assert method_epochs(get_method("full_scratch_10"), cfg) == 10
    assert method_epochs(get_method("full_scratch_30"), cfg) == 30
    full = resolve_plan(get_method("geodistill"), cfg).weights
    assert full == {"region": 1.0, "sdf": 0.002, "skel": 0.001, "area": 0.05}
    assert set(resolve_plan(get_method("sdf_gated"), cfg).weights) == {"region", "sdf"}
    assert set(resolve_plan(get_method("sdf_skel_gated"), cfg).weights) == {"region", "sdf", "skel"}
    assert set(resolve_plan(get_method("sdf_area_gated"), cfg).weights) == {"region", "sdf", "area"}
    assert resolve_plan(get_method("no_gate"), cfg).weights == full and get_method("no_gate").gate == "one"
    assert resolve_plan(get_method("geodistill"), cfg).select == "last"
    assert resolve_plan(get_method("plain"), cfg).select == "best_val"
    assert get_method("sdf_scratch").init == get_method("gabi").init == "scratch"


def test_param_keys_are_what_each_method_reads():
    plain, geo, gabi = get_method("plain"), get_method("geodistill"), get_method("gabi")
    assert "train.lr_stage1" in param_keys(plain) and "train.lr_stage2" not in param_keys(plain)
    assert "train.lr_stage2" in param_keys(geo) and "train.lr_stage1" not in param_keys(geo)
    assert "train.lambda_sdf" in param_keys(geo) and "train.lambda_sdf" not in param_keys(plain)
    assert "train.gabi" in param_keys(gabi) and not any(k.startswith("train.gabi.") for k in param_keys(gabi))
    assert "train.adaptive" in param_keys(get_method("geodistill_adaptive"))
    # the boundary: reference masks are read (validation selection), never a teacher-free substitute
    assert input_artifacts(get_method("afs_control"))[:4] == ("manifest", "images", "reference", "teacher")
    assert "geometry" in input_artifacts(geo) and "geometry" not in input_artifacts(plain)


# ---- filters ------------------------------------------------------------------------------------
def test_confidence_criterion_unit():
    c = np.array([0.9, 0.79, 0.95, 0.85])
    n = np.array([6, 6, 1, 2])
    assert confidence_pass(c, n, None, "agreement", 0.8, 2).tolist() == [True, False, False, True]
    s = np.array([[0.9, 0.0, 0.5], [0.0, 0.0, 0.0]])
    assert mean_valid_score(s).tolist() == pytest.approx([0.7, 0.0])
    assert confidence_pass(c[:2], [2, 0], mean_valid_score(s), "mean_score", 0.6, 1).tolist() == [True, False]
    assert pass_ratio(np.array([True, False, True, True])) == 0.75
    with pytest.raises(InputError, match="criterion"):
        confidence_pass(c, n, None, "vibes", 0.8, 2)


def test_confidence_filter_drops_exactly_the_failing_images(tiny):

    gates, _, _ = _tables(tiny)
    cfg = tiny_cfg(confidence={"criterion": "agreement", "threshold": float(np.median(gates["c"])), "min_valid": 3})
    data, inputs = _load(tiny, "confidence_filtered", cfg)
    expect = (gates["c"] >= cfg["confidence"]["threshold"]) & (gates["n_valid"] >= 3)
    assert data.image_ids == gates.loc[expect, "image_id"].tolist()
    assert 0 < len(data) < len(gates)  # the filter really drops something here
    assert data.stats["confidence_pass_ratio"] == pytest.approx(expect.mean())
    assert "teacher" not in {a.meta.schema for a in inputs}  # the agreement criterion reads gates only
    with pytest.raises(InputError, match="no training image passes"):
        _load(tiny, "confidence_filtered", tiny_cfg(confidence={"criterion": "agreement", "threshold": 2.0,
                                                                "min_valid": 1}))


def test_afs_control_fuses_views_and_drops_low_scores(tiny):

    _, teacher, train = _tables(tiny)
    cfg = tiny_cfg(afs={"base_prompt": "spacecraft", "score_threshold": 0.6, "fusion": "intersection"})
    data, inputs = _load(tiny, "afs_control", cfg)
    score = teacher.numpy("scores")[train, 0]
    keep = score >= 0.6
    ids = np.array(teacher.attrs["image_ids"])[train]
    assert data.image_ids == ids[keep].tolist() and 0 < keep.sum() < len(keep)
    fused = teacher.numpy("masks")[train, 0] & teacher.numpy("vflip_masks")[train]
    np.testing.assert_array_equal(data.mask, fused[keep])
    assert data.stats["afs_pass_ratio"] == pytest.approx(keep.mean())
    assert "consensus" not in {a.meta.schema for a in inputs}  # the control never sees the vote
    assert afs_fuse(np.array([1, 1, 0], bool), np.array([1, 0, 0], bool), "union").tolist() == [True, True, False]
    assert afs_keep(np.array([0.59, 0.6])).tolist() == [False, True]


# ---- gating -------------------------------------------------------------------------------------
def test_no_gate_really_sets_g_to_one(tiny):

    gates, _, _ = _tables(tiny)
    cfg = tiny_cfg()
    ng, _ = _load(tiny, "no_gate", cfg)
    gd, _ = _load(tiny, "geodistill", cfg)
    assert np.all(ng.gate == 1.0)
    np.testing.assert_allclose(gd.gate, gates["g"].to_numpy(np.float32))
    assert gd.gate.min() == 0.0  # the tiny set has a suppressed sample, so the two really differ


def test_geodistill_objective_equals_refine_loss():
    """The geodistill plan's weights with the train params' constants are the paper's eq:refine-loss."""
    from pipeline.params import load_params
    from pipeline.training.settings import loss_constants

    cfg = load_params()["train"]
    torch.manual_seed(1)
    out = {"mask": torch.randn(3, 1, 8, 8), "sdf": torch.tanh(torch.randn(3, 1, 8, 8)),
           "skeleton": torch.randn(3, 1, 8, 8)}
    batch = {"mask": (torch.rand(3, 1, 8, 8) > 0.6).float(), "sdf": torch.rand(3, 1, 8, 8) * 2 - 1,
             "skeleton": (torch.rand(3, 1, 8, 8) > 0.9).float(), "area": torch.tensor([0.1, 0.3, 0.0]),
             "gate": torch.tensor([0.0, 0.5, 1.0])}
    mine = losses.refine_loss(out, batch, batch["gate"], resolve_plan(get_method("geodistill"), cfg).weights,
                              loss_constants(cfg))
    ref = losses.refine_loss(out, batch, batch["gate"])
    assert loss_constants(cfg) == losses.LossConstants()
    for k in ("loss", "raw", "bbce", "dice", "sdf", "skel", "area"):
        assert mine[k].item() == pytest.approx(ref[k].item(), rel=1e-6), k


# ---- quality-adaptive mode ----------------------------------------------------------------------
def test_adaptive_mode_switch_follows_r():
    cfg = tiny_cfg()
    assert adaptive_mode(0.5) == "anchored" and adaptive_mode(0.4999) == "geometry_only"
    assert adaptive_mode(0.724) == adaptive_mode(0.544) == "anchored" and adaptive_mode(0.308) == "geometry_only"
    m = get_method("geodistill_adaptive")
    hi, lo = resolve_plan(m, cfg, 0.724), resolve_plan(m, cfg, 0.308)
    assert hi.mode == "anchored" and "region" in hi.weights and hi.weights["anchor"] == 0.1
    assert not hi.epoch0_eligible
    assert lo.mode == "geometry_only" and "region" not in lo.weights and lo.epoch0_eligible
    assert set(lo.weights) == {"sdf", "skel", "area"}  # default: no anchor in geometry_only mode
    kept = resolve_plan(m, {**cfg, "adaptive": {**cfg["adaptive"], "anchor_geometry_only": True}}, 0.308)
    assert set(kept.weights) == {"sdf", "skel", "area", "anchor"}


# min_valid 7 of 6 prompts: no image passes (r = 0)
@pytest.mark.parametrize("min_valid,mode", [(1, "anchored"), (7, "geometry_only")])
def test_adaptive_run_decides_mode_from_training_pseudo_labels(tiny, stage1_state, min_valid, mode):
    from pipeline.training import loop as training
    m = get_method("geodistill_adaptive")
    cfg = tiny_cfg(epochs_stage2=1, confidence={"criterion": "agreement", "threshold": 0.0, "min_valid": min_valid})
    data, val = load_arrays(tiny, m.name, cfg)
    assert len(data) == 8  # the adaptive method filters nothing; r only picks the mode
    res = training.train(m, cfg, data, val, 42, init_state=stage1_state, checkpointer=NoCheckpointer(),
                         show_progress=False)
    assert res.info["mode"] == mode
    assert res.info["confidence_pass_ratio"] == (1.0 if mode == "anchored" else 0.0)
    row = res.log.set_index("epoch").loc[1]
    # anchored: L_refine + anchor; geometry_only (default params): geometry terms only
    assert np.isfinite(row["anchor"]) == np.isfinite(row["raw"]) == (mode == "anchored")
    assert np.isfinite(row[["sdf", "skel", "area"]].astype(float)).all()
    assert res.info["epoch0_eligible"] == (mode == "geometry_only")
    best = int(res.log.loc[res.log["val_iou"].idxmax(), "epoch"])
    if mode == "geometry_only":  # epoch 0 competes with epoch 1 on val IoU
        assert res.selected_epoch == best
    else:
        assert res.selected_epoch == 1


# ---- every method: a few steps + a loadable checkpoint -------------------------------------------
@pytest.mark.parametrize("name", sorted(METHODS))
def test_every_method_trains_and_writes_a_loadable_checkpoint(tiny, stage1_state, tmp_path, name):
    from pipeline.training import loop as training
    from pipeline.evaluation.inference import load_student, predict_probs, save_checkpoint

    m = get_method(name)
    cfg = tiny_cfg(epochs_stage1=1, epochs_stage2=1, gabi={"epochs": 1, "lambda_dist": 0.002, "lambda_boundary": 0.05})
    data, val = load_arrays(tiny, name, cfg)
    res = training.train(m, cfg, data, val, 42, init_state=stage1_state if m.init == "stage1" else None,
                         checkpointer=NoCheckpointer(), show_progress=False)
    assert np.isfinite(res.log["loss"].dropna()).all() and len(res.log["loss"].dropna()) >= 1
    for term in m.terms:
        if term != "region" or not res.info["mode"] == "geometry_only":
            col = "raw" if term == "region" else term
            assert np.isfinite(res.log[col].dropna()).all() and res.log[col].notna().any(), col
    meta = make_meta("checkpoint", "train", "test", {"method": name}, [])
    save_checkpoint(tmp_path / name, res.model, meta, res.log, method=name, seed=42,
                    selected_epoch=res.selected_epoch)
    model, payload = load_student(tmp_path / name)
    assert payload["method"] == name and (payload["geometry_state_dict"] is not None) == m.geometry_heads
    probs = predict_probs(model, data.images[:2], precision="fp32")
    assert probs.shape == (2, 32, 32) and np.isfinite(probs).all()
