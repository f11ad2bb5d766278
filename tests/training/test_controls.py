"""Controls the paper lacks (issue 17 item 2): the budget-matched continuation, the supervised ceiling
(and the guard that keeps reference masks out of every other loss), the teacher vote as a predictor,
their place in evaluate's gains and in the report; the per-epoch calibrated-tau log columns."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from pipeline.artifacts.store import open_artifact, write_zarr
from pipeline.runtime.errors import InputError
from pipeline.methods import (METHODS, SUPERVISED_CEILING, Method, check_reference_boundary, gain_treatments,
                              get_method, param_keys, resolve_plan)
from pipeline.training.checkpointing import NoCheckpointer
from tests.builders.training import build_tiny_artifacts, load_arrays, tiny_cfg, train_cli, train_params_file


def _train(tiny, name, cfg, init_state=None, art=None):
    from pipeline.training import loop as training
    data, val = load_arrays(art or tiny, name, cfg)
    return training.train(get_method(name), cfg, data, val, 42, init_state=init_state,
                          checkpointer=NoCheckpointer(), show_progress=False)


# ---- 2a: the budget-matched continuation ---------------------------------------------------------
def test_continuation_is_stage2_budget_with_raw_loss_only():
    from pipeline.methods import method_epochs, method_lr
    from pipeline.profiles import load_profile

    cfg = load_profile("paper")["train"]
    c, g = get_method("continuation"), get_method("geodistill")
    assert (c.stage, c.init, c.select) == (g.stage, g.init, g.select) == (2, "stage1", "stage2")
    assert method_epochs(c, cfg) == method_epochs(g, cfg) == 10 and method_lr(c, cfg) == method_lr(g, cfg) == 1e-4
    assert resolve_plan(c, cfg).weights == {"region": 1.0} and resolve_plan(c, cfg).select == "last"
    assert not c.geometry_heads and not c.needs_geometry and not c.needs_gates and c.annotation_free
    keys = param_keys(c)
    assert {"train.lr_stage2", "train.epochs_stage2", "train.stage2_select"} <= set(keys)
    assert not any(k in keys for k in ("train.lambda_sdf", "train.lr_stage1", "train.epochs_stage1"))
    # the continuation is the control of the warm-started Stage-II methods only; never of the ceiling
    names = list(METHODS)
    assert set(gain_treatments("continuation", names)) == {m for m in METHODS if METHODS[m].init == "stage1"} - {
        "continuation"}
    assert SUPERVISED_CEILING not in gain_treatments("plain", names) and "continuation" in gain_treatments("plain", names)


def test_continuation_equals_geodistill_without_geometry_weights(tiny, stage1_state):
    """The hand-made H100 control (Stage II with lambda_sdf = lambda_skel = lambda_area = 0) and the
    continuation method train the same mask path: same epochs, schedule, batches and selection."""
    cfg = tiny_cfg(epochs_stage2=2)
    cont = _train(tiny, "continuation", cfg, stage1_state)
    zero = _train(tiny, "geodistill", {**cfg, "lambda_sdf": 0.0, "lambda_skel": 0.0, "lambda_area": 0.0}, stage1_state)
    full = _train(tiny, "geodistill", cfg, stage1_state)
    assert cont.selected_epoch == 2 and list(cont.log["epoch"]) == [0, 1, 2]
    assert cont.model.geometry_heads is None and zero.model.geometry_heads is not None  # L_raw only: no heads
    assert np.isnan(cont.log[["sdf", "skel", "area"]].to_numpy(float)).all()
    mask_cont, mask_zero = cont.model.mask_path_state_dict(), zero.model.mask_path_state_dict()
    for k in mask_cont:
        torch.testing.assert_close(mask_cont[k], mask_zero[k], rtol=1e-5, atol=1e-6, msg=k)
    # ... and the geometry terms do change the weights (the control is not a no-op comparison)
    diff = max(float((full.model.mask_path_state_dict()[k].float() - mask_cont[k].float()).abs().max())
               for k in mask_cont)
    assert diff > 1e-6


# ---- 2b: the supervised ceiling and the reference-mask boundary -----------------------------------
def test_only_the_ceiling_may_train_on_reference_masks(tiny):
    from pipeline.training.inputs import ceiling_training_data, require_supervised_ceiling, training_data

    ceiling = get_method(SUPERVISED_CEILING)
    assert not ceiling.annotation_free and [m for m in METHODS if not METHODS[m].annotation_free] == [SUPERVISED_CEILING]
    # the table's guard: any other method asking for reference targets is refused at import time
    rogue = Method("plain_on_reference", 1, "scratch", ("epochs_stage1",), "lr_stage1", data="reference")
    with pytest.raises(ValueError, match="plain_on_reference"):
        check_reference_boundary({**METHODS, rogue.name: rogue})
    with pytest.raises(ValueError, match="reference masks enter a loss only"):
        require_supervised_ceiling(get_method("plain"))
    inputs = {n: open_artifact(tiny / f, n) for n, f in [("manifest", "manifest.parquet"), ("images", "images.zarr")]}
    reference = open_artifact(tiny / "reference.zarr", "reference")
    with pytest.raises(ValueError, match="reference masks enter a loss only"):
        ceiling_training_data(get_method("plain"), inputs, reference)
    # and the pseudo-target path refuses the ceiling
    with pytest.raises(ValueError, match="ceiling_training_data"):
        training_data(ceiling, tiny_cfg(), inputs)
    # the ceiling's targets ARE the training split's reference masks (and nothing of the teacher)
    data = ceiling_training_data(ceiling, inputs, reference)
    split = inputs["manifest"].df["split"].to_numpy()
    np.testing.assert_array_equal(data.mask, reference.numpy("mask")[split == "train"])
    assert np.all(data.gate == 1.0) and len(data) == int((split == "train").sum())


def test_ceiling_weights_follow_the_reference_masks_of_training_rows(tmp_path):
    """Contrast with test_training's boundary test for plain: here corrupting the training rows'
    reference masks DOES change the weights -- the ceiling is the one place they enter a loss."""
    a = build_tiny_artifacts(tmp_path / "a")
    b = build_tiny_artifacts(tmp_path / "b")
    ref = open_artifact(b / "reference.zarr")
    masks = ref.numpy("mask")
    split = open_artifact(b / "manifest.parquet").df["split"].to_numpy()
    masks[split == "train"] = ~masks[split == "train"]
    write_zarr(b / "reference.zarr", {"mask": masks, "has_mask": ref.numpy("has_mask")}, ref.meta,
               {"image_ids": ref.attrs["image_ids"]})
    cfg = tiny_cfg(epochs_stage1=1)
    wa = _train(a, SUPERVISED_CEILING, cfg, art=a).model.state_dict()
    wb = _train(b, SUPERVISED_CEILING, cfg, art=b).model.state_dict()
    assert any(not torch.equal(wa[k], wb[k]) for k in wa)
    # plain on the same two artifact sets: identical (its loss never sees reference masks)
    pa = _train(a, "plain", cfg, art=a).model.state_dict()
    pb = _train(b, "plain", cfg, art=b).model.state_dict()
    assert all(torch.equal(pa[k], pb[k]) for k in pa)


def test_ceiling_needs_the_explicit_flag(tiny, tmp_path):
    from pipeline.params import validate
    from pipeline.profiles import profile_params

    raw = profile_params("demo")
    raw["protocol"]["runs"][SUPERVISED_CEILING] = [42]
    with pytest.raises(InputError, match="protocol.supervised_ceiling: true"):
        validate(raw)
    raw["protocol"]["supervised_ceiling"] = True
    assert validate(raw)["protocol"]["runs"][SUPERVISED_CEILING] == [42]
    assert validate(profile_params("demo"))["protocol"]["supervised_ceiling"] is False   # off by default
    assert validate(profile_params("paper"))["protocol"]["runs"][SUPERVISED_CEILING] == [42, 3407, 2026]
    # the train stage refuses the ceiling without the flag (one line, exit 2) ...
    params = train_params_file(tmp_path)
    common = ["--params", str(params), "--artifacts", str(tiny), "--device", "cpu", "--resume-dir",
              str(tmp_path / "cache"), "--stage", "1", "--method", SUPERVISED_CEILING, "--seed", "42"]
    r = train_cli(*common, "--out", str(tmp_path / "no"), cwd=tmp_path)
    assert r.returncode == 2 and "protocol.supervised_ceiling" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "no").exists()
    # ... and trains with it; its lineage names reference.zarr once, and no teacher output
    r = train_cli(*common, "--set", "protocol.supervised_ceiling=true", "--out", str(tmp_path / "yes"), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    schemas = [i["schema"] for i in open_artifact(tmp_path / "yes", "checkpoint").meta.inputs]
    assert sorted(schemas) == ["images", "manifest", "reference"]


# ---- item 3: per-epoch validation IoU at 0.5 and at the calibrated tau ----------------------------
def test_log_has_val_iou_at_half_and_at_the_epoch_calibrated_tau(tiny):
    from pipeline.training import loop as training
    from pipeline.evaluation.inference import predict_probs
    from pipeline.thresholds import EPOCH_TAU_GRID, calibrate_threshold

    cfg = tiny_cfg(epochs_stage1=1)
    res = _train(tiny, "plain", cfg)
    row = res.log.iloc[-1]
    assert {"val_iou_cal", "val_tau_cal"} <= set(res.log.columns) and list(res.log.columns) == list(training.LOG_COLUMNS)
    assert row["val_tau_cal"] in EPOCH_TAU_GRID and row["val_iou_cal"] >= row["val_iou"] - 1e-12  # 0.5 is on the grid
    _, val = load_arrays(tiny, "plain", cfg)
    probs = predict_probs(res.model, val.images, precision="fp32")
    tau, curve = calibrate_threshold(probs, val.masks, EPOCH_TAU_GRID)
    assert row["val_tau_cal"] == tau and row["val_iou_cal"] == pytest.approx(curve.max())


# ---- evaluate and report with the controls --------------------------------------------------------
@pytest.fixture(scope="module")
def reported(tmp_path_factory):
    from tests.builders.evaluation import build_tiny_artifacts as build_eval, run_result_stages, write_params

    root = tmp_path_factory.mktemp("controls")
    art = build_eval(root / "artifacts", methods=("plain", "geodistill", "continuation", SUPERVISED_CEILING))
    run_result_stages(root, art, write_params(root / "params.yaml"), root / "report")
    return art, root / "report"


def test_evaluate_compares_with_plain_and_continuation_never_the_ceiling(reported):
    from pipeline.stats import method_gains

    art, _ = reported
    m = open_artifact(art / "metrics.parquet").df
    s = open_artifact(art / "summary.parquet").df.set_index(["group", "method", "threshold_mode"])
    # the ceiling has means but no gain or CI against anything
    ceil = s.xs(SUPERVISED_CEILING, level="method")
    assert np.isfinite(ceil["iou_mean"]).all()
    assert ceil[[c for c in s.columns if c.startswith("gain_")]].isna().all().all()
    # geodistill vs the continuation: the gain interval of the two methods alone
    pair = m[m["method"].isin(["geodistill", "continuation"])]
    want = method_gains(pair, ["iou"], control="continuation", by=["dataset", "group", "threshold_mode"],
                        n_resamples=200, ci=0.95, seed=0).set_index(["group", "method", "threshold_mode"])
    got = s.loc[("KCP", "geodistill", "calibrated")]
    ref = want.loc[("KCP", "geodistill", "calibrated")]
    assert got["gain_iou_vs_continuation"] == pytest.approx(ref["gain_iou"])
    assert got["gain_iou_vs_continuation_lo"] == pytest.approx(ref["gain_iou_lo"])
    assert np.isnan(s.loc[("KCP", "plain", "calibrated"), "gain_iou_vs_continuation"])   # plain is cold-started
    # the size split and the area-vs-reference columns
    assert set(m["target_size"]) <= {"tiny", "regular", "empty"}
    np.testing.assert_allclose(m["area_vs_reference"], m["area_ratio"] / m["target_fraction"])
    # calibrate: reliability diagram, ECE and area curve per run
    thr = open_artifact(art / "thresholds.parquet").df
    assert thr["ece"].between(0, 1).all() and all(len(c) == 10 for c in thr["rel_count"])
    assert all(len(a) == len(g) for a, g in zip(thr["area_curve"], thr["grid"]))


def test_report_labels_the_ceiling_and_keeps_it_out_of_comparisons(reported):
    _, out = reported
    md = (out / "report.md").read_text()
    label = "Supervised ceiling (uses reference masks; not annotation-free)"
    from pipeline.report.glossary import TERMS

    html = (out / "report.html").read_text()
    for key in ("tab:controls", "tab:reference-points", "tab:calibration", "tab:epoch-swings", "tab:size-split"):
        assert f'<table data-key="{key}">' in html, key
    # every table that shows the ceiling names it with the full label; the main results and the controls never show it
    lines = md.splitlines()
    glossary = {f"| {t} | {m} |" for t, m in TERMS}  # the word's definition, not a row of results
    ceiling_lines = [ln for ln in lines if "eiling" in ln and ln.startswith("|") and ln not in glossary]
    assert ceiling_lines and all(label in ln for ln in ceiling_lines)

    def table(key):  # the rows of the tables with this key (the page's data-key; keys are never shown)
        bodies = re.findall(rf'<table data-key="{key}">(.*?)</table>', html, re.S)
        return [re.sub(r"<[^>]+>", " ", r) for b in bodies for r in re.findall(r"<tr>(.*?)</tr>", b, re.S)]

    for key in ("tab:spacesense-results", "tab:controls", "tab:diagnostics"):
        assert not any("eiling" in r for r in table(key)), key
    assert any(label in r for r in table("tab:reference-points"))
    assert any("Teacher vote" in r for r in table("tab:reference-points"))
    assert any("Budget-matched continuation" in r for r in table("tab:controls"))
    # findings are stated in words, with numbers
    assert "**Calibrated threshold.**" in md and "**Budget-matched continuation (calibrated tau).**" in md
    assert f"**{label}** minus Plain Student" in md and "**Teacher vote as a predictor**" in md
    assert "**Target size**" in md and "**Per-epoch validation IoU.**" in md
    for f in ("reliability.png", "area_vs_tau.png", "training_curves_calibrated.png"):
        assert (out / "figures" / f).is_file(), f
