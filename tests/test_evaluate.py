"""calibrate / evaluate / analyze_teacher stages end to end on tiny artifacts built here.

``build_tiny_artifacts`` writes every input artifact these stages (and the report) read -- a small
manifest with train/val and two test groups, 32x32 images with one bright shape each, reference
masks, a six-prompt teacher, consensus, geometry, gates -- and random TinyUNet checkpoints saved
with ``pipeline.inference.save_checkpoint``.  No other helper's stage is run.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml
from click.testing import CliRunner

from pipeline.artifacts import make_meta, open_artifact, write_parquet, write_zarr

SIZE = 32
PROMPTS = ["spacecraft", "satellite", "space probe", "space vehicle",
           "spacecraft with rigid body and appendages", "artificial object in space with panels and antennas"]
PARAMS = {
    "calibrate": {"grid_start": 0.05, "grid_stop": 0.95, "grid_step": 0.05, "fixed_tau": 0.5},
    "evaluate": {"bf1_tolerance": 2, "small_region_max_fraction": 0.05, "bootstrap_resamples": 200,
                 "bootstrap_seed": 0, "ci": 0.95},
    "report": {"qualitative_images": 2, "pseudo_target_images": 2},
}


def _meta(schema, **kw):
    return make_meta(schema, "fixture", "test", {}, [], **kw)


def _shape(rng):
    """A filled ellipse plus a thin boom (a small component for small-region IoU)."""
    m = np.zeros((SIZE, SIZE), np.uint8)
    c = tuple(int(v) for v in rng.integers(10, 22, 2))
    ax = tuple(int(v) for v in rng.integers(4, 9, 2))
    cv2.ellipse(m, c, ax, float(rng.integers(0, 180)), 0, 360, 1, -1)
    x = int(rng.integers(2, 28))
    m[1:4, x:x + 3] = 1
    return m.astype(bool)


def build_tiny_artifacts(root: Path, methods=("plain", "geodistill"), seeds=(1, 2), teacher_backend="simulated",
                         with_parts=True) -> Path:
    """Write a complete tiny artifacts directory under ``root`` and return it."""
    import torch

    from pipeline.inference import save_checkpoint
    from pipeline.methods import METHODS
    from pipeline.model import TinyUNet

    art = Path(root)
    rng = np.random.default_rng(0)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny tensors: threading only adds contention on shared CPUs
    layout = [("train", "train", 3, 3), ("val", "val", 2, 2), ("test", "KCP", 3, 2), ("test", "CVI", 2, 2)]
    rows = []
    for split, group, n_sc, views in layout:
        for s in range(n_sc):
            for v in range(views):
                iid = f"{group}_s{s}_v{v}"
                rows.append(dict(image_id=iid, dataset="synthetic", domain="synthetic", split=split, group=group,
                                 spacecraft=f"{group}-sc{s}", image_path=f"{iid}.png", mask_path=None, part_path=None,
                                 width=SIZE, height=SIZE, sha256="0" * 64))
    mdf = pd.DataFrame(rows)
    n = len(mdf)
    ids = mdf["image_id"].tolist()
    masks = np.stack([_shape(rng) for _ in range(n)])
    noise = rng.integers(0, 40, (n, SIZE, SIZE, 3))
    images = np.clip(noise + masks[..., None] * np.array([180, 170, 150]), 0, 255).astype(np.uint8)
    write_parquet(art / "manifest.parquet", mdf, _meta("manifest"))
    write_zarr(art / "images.zarr", {"image": images}, _meta("images"), {"image_ids": ids})
    ref = {"mask": masks, "has_mask": np.ones(n, bool)}
    if with_parts:
        ref["parts"] = masks.astype(np.uint8)
    write_zarr(art / "reference.zarr", ref, _meta("reference"), {"image_ids": ids})

    k = len(PROMPTS)
    tmasks = np.zeros((n, k, SIZE, SIZE), bool)
    kernel = np.ones((3, 3), np.uint8)
    for i in range(n):
        m8 = masks[i].astype(np.uint8)
        variants = [masks[i], cv2.dilate(m8, kernel).astype(bool), cv2.erode(m8, kernel).astype(bool),
                    np.roll(masks[i], 2, axis=1), masks[i] & (rng.random((SIZE, SIZE)) > 0.2),
                    np.zeros_like(masks[i]) if i % 3 == 0 else masks[i]]
        tmasks[i] = np.stack(variants)
    scores = rng.uniform(0.3, 0.95, (n, k)).astype(np.float32)
    write_zarr(art / "teacher.zarr", {"masks": tmasks, "scores": scores},
               _meta("teacher"), {"prompts": PROMPTS, "image_ids": ids, "backend": teacher_backend})
    agreement = tmasks.mean(axis=1).astype(np.float32)
    voted = agreement >= 0.5
    train_rows = np.flatnonzero(mdf["split"] == "train")
    write_zarr(art / "consensus.zarr", {"agreement": agreement, "voted": voted,
                                        "n_valid": np.full(n, k, np.int16)}, _meta("consensus"), {"image_ids": ids})
    sdf = rng.uniform(-1, 1, (n, SIZE, SIZE)).astype(np.float32)
    write_zarr(art / "geometry.zarr", {"sdf": sdf, "skeleton": masks & (rng.random(masks.shape) > 0.9)},
               _meta("geometry"), {"image_ids": ids})
    g = np.where(np.arange(n) % 4 == 0, 0.0, rng.uniform(0.2, 1.0, n))
    write_parquet(art / "gates.parquet", pd.DataFrame({
        "image_id": ids, "split": mdf["split"], "c": rng.random(n), "v": np.ones(n), "a": rng.random(n) * 0.3,
        "a0": np.full(n, 0.1), "g_conf": rng.random(n), "g_valid": np.ones(n), "g_area": rng.random(n), "g": g,
        "n_valid": np.full(n, k)}), _meta("gates"))

    for mi, method in enumerate(methods):
        for seed in seeds:
            torch.manual_seed(1000 * mi + seed)
            model = TinyUNet(channels=(4, 8, 8))
            # a few optimiser steps on the teacher's voted masks of the training split, so that the
            # students are distinct and non-degenerate (more steps for later methods)
            opt = torch.optim.Adam(model.parameters(), lr=0.02)
            x = torch.from_numpy(images[train_rows]).permute(0, 3, 1, 2).float() / 255
            y = torch.from_numpy(voted[train_rows]).float()[:, None]
            model.train()
            for _ in range(5 + 6 * mi + 2 * seed):
                opt.zero_grad()
                torch.nn.functional.binary_cross_entropy_with_logits(model(x), y).backward()
                opt.step()
            model.eval()
            val_iou = rng.uniform(0.2, 0.6, 3)
            log = pd.DataFrame({"epoch": np.arange(1, 4), "stage": [METHODS[method].stage] * 3,
                                "loss": [0.9, 0.7, 0.6], "val_iou": val_iou,
                                "val_bf1": rng.uniform(0.2, 0.6, 3), "val_iou_cal": val_iou + 0.05,
                                "val_tau_cal": [0.5, 0.6, 0.7], "lr": [1e-3] * 3})
            save_checkpoint(art / "checkpoints" / method / str(seed), model, _meta("checkpoint"), log,
                            method=method, seed=seed, stage=METHODS[method].stage, selected_epoch=3)
    torch.set_num_threads(threads)
    return art


def write_params(path: Path, **over) -> Path:
    params = json.loads(json.dumps(PARAMS))
    for sec, vals in over.items():
        params[sec].update(vals)
    path.write_text(yaml.safe_dump(params))
    return path


def invoke(main, args):
    res = CliRunner().invoke(main, [*args, "--device", "cpu"], catch_exceptions=False)
    return res


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval")
    art = build_tiny_artifacts(root / "artifacts")
    params = write_params(root / "params.yaml")
    from stages.calibrate import main as calibrate

    res = invoke(calibrate, ["--params", str(params), "--artifacts", str(art),
                             "--checkpoints", str(art / "checkpoints"), "--out", str(art / "thresholds.parquet")])
    assert res.exit_code == 0, res.output
    return root, art, params


def test_calibration_picks_the_best_grid_point(tiny):
    from pipeline.inference import load_student, predict_probs
    from pipeline.metrics import image_iou
    from pipeline.thresholds import threshold_grid

    root, art, _ = tiny
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


def test_evaluate_end_to_end(tiny):
    from pipeline.inference import load_student, predict_probs
    from pipeline.metrics import boundary_f1, image_iou
    from stages.evaluate import main as evaluate

    root, art, params = tiny
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


def test_analyze_teacher_end_to_end(tiny):
    from pipeline.metrics import image_iou
    from stages.analyze_teacher import main as analyze

    root, art, params = tiny
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


def test_stage_errors_are_one_line(tmp_path, tiny):
    from stages.calibrate import main as calibrate
    from stages.evaluate import main as evaluate

    root, art, params = tiny
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
