"""calibrate / evaluate / analyze_teacher stages end to end on the tiny artifacts of tests/builders/evaluation.py
(a small manifest with train/val and two test groups, a six-prompt teacher, random TinyUNet checkpoints).
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from pipeline.artifacts.store import open_artifact, write_parquet
from tests.builders.evaluation import PARAMS, calibrated_artifacts, invoke, write_params


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval")
    art, params = calibrated_artifacts(root)
    return root, art, params


def test_calibration_picks_the_best_grid_point(calibrated):
    from pipeline.evaluation.inference import load_student, predict_probs
    from pipeline.metrics import image_iou
    from pipeline.thresholds import threshold_grid

    root, art, _ = calibrated
    thr = open_artifact(art / "thresholds.parquet", "thresholds").df
    assert sorted(zip(thr["method"], thr["seed"])) == [("geodistill", 1), ("geodistill", 2), ("plain", 1), ("plain", 2)]
    grid = threshold_grid(PARAMS["calibrate"])
    assert grid[0] == 0.05 and grid[-1] == 0.95 and 0.5 in grid
    mdf = open_artifact(art / "manifest.parquet").df
    val = np.flatnonzero(mdf["split"] == "val")
    images = open_artifact(art / "images.zarr").numpy("image")[val]
    gts = open_artifact(art / "reference.zarr").numpy("mask")[val]
    for _, row in thr.iterrows():
        model, _ = load_student(art / "checkpoints" / row["method"] / str(row["seed"]))
        probs = predict_probs(model, images)
        # brute force: mean validation Image IoU at every grid point, with the single-image metric
        curve = np.array([np.mean([image_iou(p >= t, g) for p, g in zip(probs, gts)]) for t in grid])
        np.testing.assert_allclose(row["curve"], curve, atol=1e-12)
        assert row["val_iou"] == pytest.approx(curve.max())
        assert curve[np.flatnonzero(np.isclose(grid, row["tau"]))[0]] == pytest.approx(curve.max())
        assert row["fixed_val_iou"] == pytest.approx(curve[np.flatnonzero(np.isclose(grid, 0.5))[0]])


def test_evaluate_end_to_end(calibrated):
    from pipeline.evaluation.inference import load_student, predict_probs
    from pipeline.metrics import boundary_f1, image_iou
    from stages.evaluate import main as evaluate

    root, art, params = calibrated
    out = art / "metrics.parquet"
    res = invoke(evaluate, ["--params", str(params), "--artifacts", str(art), "--checkpoints", str(art / "checkpoints"),
                            "--thresholds", str(art / "thresholds.parquet"), "--out", str(out),
                            "--summary", str(art / "summary.parquet"),
                            "--metrics-dir", str(root / "metrics" / "students")])
    assert res.exit_code == 0, res.output
    m = open_artifact(out, "metrics").df
    thr = open_artifact(art / "thresholds.parquet").df
    # 10 test images x 4 runs x 2 threshold modes
    assert len(m) == 10 * 4 * 2 and set(m["method"]) == {"plain", "geodistill"}
    assert set(m["group"]) == {"KCP", "CVI"} and set(m["threshold_mode"]) == {"calibrated", "fixed"}
    # tau applied unchanged: calibrated rows carry the run's calibrated tau, fixed rows 0.5
    for (method, seed, mode), part in m.groupby(["method", "seed", "threshold_mode"]):
        want = thr[(thr.method == method) & (thr.seed == seed)]["tau"].item() if mode == "calibrated" else 0.5
        assert (part["tau"] == want).all()
    # spot-check one row against the single-image metrics
    row = m[(m.method == "geodistill") & (m.seed == 2) & (m.threshold_mode == "calibrated")].iloc[3]
    mdf = open_artifact(art / "manifest.parquet").df
    i = int(np.flatnonzero(mdf["image_id"] == row["image_id"])[0])
    model, _ = load_student(art / "checkpoints" / "geodistill" / "2")
    prob = predict_probs(model, open_artifact(art / "images.zarr").numpy("image")[i:i + 1])[0]
    gt = open_artifact(art / "reference.zarr").numpy("mask")[i]
    assert row["iou"] == pytest.approx(image_iou(prob >= row["tau"], gt))
    assert row["bf1"] == pytest.approx(boundary_f1(prob >= row["tau"], gt, 2))

    s = open_artifact(art / "summary.parquet", "summary").df
    assert len(s) == 2 * 2 * 2   # groups x methods x modes
    r = s[(s.group == "KCP") & (s.method == "geodistill") & (s.threshold_mode == "calibrated")].iloc[0]
    part = m[(m.group == "KCP") & (m.method == "geodistill") & (m.threshold_mode == "calibrated")]
    per_seed = part.groupby("seed")["iou"].mean()
    assert r["n_seeds"] == 2 and r["n_images"] == 6
    assert r["iou_mean"] == pytest.approx(per_seed.mean()) and r["iou_std"] == pytest.approx(per_seed.std(ddof=1))
    ctrl = m[(m.group == "KCP") & (m.method == "plain") & (m.threshold_mode == "calibrated")]
    assert r["gain_iou"] == pytest.approx(part["iou"].mean() - ctrl["iou"].mean())
    assert r["gain_iou_lo"] <= r["gain_iou"] <= r["gain_iou_hi"]
    assert np.isnan(s[(s.method == "plain")]["gain_iou"]).all()
    js = json.loads((root / "metrics" / "students" / "KCP" / "geodistill.json").read_text())
    assert js["iou"] == pytest.approx(round(r["iou_mean"], 4))
    # deterministic: same inputs and params -> same fingerprint and the same table
    out2 = root / "metrics2.parquet"
    invoke(evaluate, ["--params", str(params), "--artifacts", str(art), "--checkpoints", str(art / "checkpoints"),
                      "--thresholds", str(art / "thresholds.parquet"), "--out", str(out2),
                      "--summary", str(root / "summary2.parquet"), "--metrics-dir", str(root / "s2"),
                      "--training-curves", str(root / "t2.csv"), "--threshold-curves", str(root / "c2.csv")])
    assert open_artifact(out2).fingerprint == open_artifact(out).fingerprint
    pd.testing.assert_frame_equal(open_artifact(root / "summary2.parquet").df, s)


def test_analyze_teacher_end_to_end(calibrated):
    from pipeline.metrics import image_iou
    from stages.analyze_teacher import main as analyze

    root, art, params = calibrated
    out = art / "teacher_metrics.parquet"
    res = invoke(analyze, ["--params", str(params), "--artifacts", str(art), "--out", str(out),
                           "--metrics-dir", str(root / "metrics" / "teacher")])
    assert res.exit_code == 0, res.output
    assert "SIMULATOR" in res.output
    t = open_artifact(out, "teacher_metrics")
    tm = t.df
    # val + test images (4 + 10), 6 prompts + vote + val_selected
    assert set(tm["source"]) == {f"prompt_{k}" for k in range(6)} | {"vote", "val_selected"}
    assert len(tm[tm.source == "vote"]) == 14
    # the selected prompt is the best on the validation split; prompt_0 is the exact GT copy here
    assert t.meta.extra["selected_source"] == "prompt_0" and t.meta.extra["simulator"] is True
    # spot-check: prompt_3 (shifted by 2 px) IoU for one image
    mdf = open_artifact(art / "manifest.parquet").df
    iid = mdf[mdf.group == "KCP"]["image_id"].iloc[0]
    i = int(np.flatnonzero(mdf["image_id"] == iid)[0])
    teach = open_artifact(art / "teacher.zarr").numpy("masks")[i, 3]
    gt = open_artifact(art / "reference.zarr").numpy("mask")[i]
    got = tm[(tm.image_id == iid) & (tm.source == "prompt_3")]["iou"].item()
    assert got == pytest.approx(image_iou(teach, gt))
    assert sorted(p.name for p in (root / "metrics" / "teacher").iterdir()) == ["CVI.json", "KCP.json"]
    js = json.loads((root / "metrics" / "teacher" / "KCP.json").read_text())
    assert 0 < js["gate_share"] < 1  # the fixture zeroes every fourth image's gate


def test_stage_errors_are_one_line(tmp_path, calibrated):
    from stages.calibrate import main as calibrate
    from stages.evaluate import main as evaluate

    root, art, params = calibrated
    res = CliRunner().invoke(calibrate, ["--params", str(params), "--artifacts", str(tmp_path / "nope"),
                                         "--device", "cpu"])
    assert res.exit_code == 2 and "manifest.parquet" in res.output and "Traceback" not in res.output
    bad = write_params(tmp_path / "bad.yaml", calibrate={"grid_step": -1})
    res = CliRunner().invoke(calibrate, ["--params", str(bad), "--artifacts", str(art), "--device", "cpu",
                                         "--out", str(tmp_path / "t.parquet")])
    assert res.exit_code == 2 and "calibrate.grid_step" in res.output
    # thresholds that lack a run -> one line naming the run
    thr = open_artifact(art / "thresholds.parquet")
    write_parquet(tmp_path / "thr.parquet", thr.df[thr.df.method == "plain"], thr.meta)
    res = CliRunner().invoke(evaluate, ["--params", str(params), "--artifacts", str(art),
                                        "--checkpoints", str(art / "checkpoints"), "--thresholds",
                                        str(tmp_path / "thr.parquet"), "--out", str(tmp_path / "m.parquet"),
                                        "--device", "cpu"])
    assert res.exit_code == 2 and "geodistill/1" in res.output
