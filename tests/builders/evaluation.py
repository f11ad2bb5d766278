"""Tiny artifacts for the result stages (calibrate, evaluate, analyze_teacher, report), shared by several
test modules (imported as ``tests.builders.evaluation``; see tests/conftest.py for the folder's rule).

``build_tiny_artifacts`` writes every input artifact these stages (and the report) read -- a small
manifest with train/val and two test groups, 32x32 images with one bright shape each, reference
masks, a six-prompt teacher, consensus, geometry, gates -- and random TinyUNet checkpoints saved
with ``pipeline.evaluation.inference.save_checkpoint``.  No other helper's stage is run.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import yaml
from click.testing import CliRunner

from pipeline.artifacts.lineage import make_meta
from pipeline.artifacts.store import write_parquet, write_zarr

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

    from pipeline.evaluation.inference import save_checkpoint
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


def calibrated_artifacts(root: Path, **build) -> tuple[Path, Path]:
    """(artifacts, params file) under ``root``: :func:`build_tiny_artifacts` (``build`` passed on),
    :func:`write_params` and the calibrate stage's ``thresholds.parquet``."""
    from stages.calibrate import main as calibrate

    art = build_tiny_artifacts(root / "artifacts", **build)
    params = write_params(root / "params.yaml")
    res = invoke(calibrate, ["--params", str(params), "--artifacts", str(art),
                             "--checkpoints", str(art / "checkpoints"), "--out", str(art / "thresholds.parquet")])
    assert res.exit_code == 0, res.output
    return art, params


def _other_outputs(main, given, root):
    """Every path option of a stage command not in ``given`` pointed under ``root`` (DVC metrics and
    plot files default to repository paths; the test must not write there)."""
    import click

    out = []
    for opt in main.params:
        if isinstance(opt, click.Option) and isinstance(opt.type, click.Path) and not set(opt.opts) & set(given):
            out += [opt.opts[0], str(root / opt.name)]
    return out


def run_result_stages(root: Path, art: Path, params: Path, report_out: Path | None = None) -> None:
    """calibrate, evaluate, analyze_teacher (and the report when ``report_out`` is given) on tiny
    artifacts through their click commands; DVC metrics/plot files go under ``root``/dvc, never into
    the repository."""
    from stages.analyze_teacher import main as analyze
    from stages.calibrate import main as calibrate
    from stages.evaluate import main as evaluate
    from stages.report import main as report

    common = ["--params", str(params), "--artifacts", str(art)]
    steps = [
        (calibrate, ["--checkpoints", str(art / "checkpoints"), "--out", str(art / "thresholds.parquet")]),
        (evaluate, ["--checkpoints", str(art / "checkpoints"), "--thresholds", str(art / "thresholds.parquet"),
                    "--out", str(art / "metrics.parquet"), "--summary", str(art / "summary.parquet")]),
        (analyze, ["--out", str(art / "teacher_metrics.parquet")]),
    ] + ([(report, ["--out", str(report_out)])] if report_out is not None else [])
    for main, extra in steps:
        res = invoke(main, common + extra + _other_outputs(main, common + extra, root / "dvc"))
        assert res.exit_code == 0, res.output
