"""Recipe study: why is the supervised ceiling no better than pseudo-labels, and why does validation IoU swing
between epochs?  Trains Plain (voted pseudo-masks) and the supervised ceiling (reference masks; NOT
annotation-free) under the paper recipe and under each one-change variant (:data:`VARIANTS`), and prints the
test IoU at the calibrated tau and at 0.5, the largest epoch-to-epoch jump, area ratios and tiny-target IoU
(means over seeds, differences to the paper recipe).  Finished runs in ``<out>.runs.jsonl`` are skipped.

    python -m benchmarks.study_recipe --resolution 96 --seeds 42 --jobs 2

``--set train.recipe=plateau`` makes another recipe the base that variant ``paper`` (no override) names; with
``--train-spacecraft``/``--train-views`` and ``--variants paper`` it gives the data-scaling curve (docs/student.md).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from benchmarks.common import parser, resumed_runs, run_jobs
from pipeline import catalog
from pipeline.artifacts.atomic import write_text_if_changed
from pipeline.artifacts.store import open_artifact
from pipeline.orchestration.dag import render_params_yaml
from pipeline.runtime.device import resolve_device
from pipeline.evaluation.inference import predict_probs
from pipeline.methods import STAGE_ONE, SUPERVISED_CEILING, get_method
from pipeline.metrics import image_ious
from pipeline.profiles import load_profile
from pipeline.thresholds import EPOCH_TAU_GRID, calibrate_threshold, mask_from_probs
from pipeline.training.inputs import read_rows, load_inputs
from pipeline.training.checkpointing import NoCheckpointer

REPO = Path(__file__).resolve().parents[1]
#: the Stage-I (Plain Student) recipe and the same recipe on reference masks (the supervised ceiling)
METHODS = (STAGE_ONE, SUPERVISED_CEILING)
#: targets under this fraction of the frame count as "tiny"
TINY_FRACTION = 0.002
#: the split sizes of the synthetic data (data.synthetic.*) the command line may set
DATA_SIZES = ("train_spacecraft", "train_views", "val_spacecraft", "val_views", "test_spacecraft_per_group",
              "test_views")

#: variant name -> (``train.*`` overrides of the paper recipe, the candidate it tests).  One change each.
VARIANTS: dict[str, tuple[dict, str]] = {
    "paper": ({}, "the profile's recipe, paper unless --set train.recipe (bf16 autocast where supported, BN momentum 0.1, pi clip 500, lr 5e-4 cosine)"),
    "fp32": ({"precision": "fp32"}, "bf16 autocast vs fp32"),
    "bn_momentum_0.01": ({"bn_momentum": 0.01}, "BN running statistics: slower running average"),
    "precise_bn": ({"precise_bn": True}, "BN running statistics recomputed over the training set before validation"),
    "groupnorm": ({"norm": "group"}, "no batch statistics at all (GroupNorm)"),
    "pos_weight_max_10": ({"pos_weight_max": 10.0}, "positive-class weight clipped at 10 instead of 500"),
    "lr_2e-4": ({"lr_stage1": 2e-4}, "lower learning rate"),
    "lr_1e-3": ({"lr_stage1": 1e-3}, "higher learning rate"),
    "constant_lr": ({"schedule": "constant"}, "no cosine decay"),
}


def build_artifacts(workdir: Path, profile: str, sets: list[str], device: str, geometry: bool = False) -> Path:
    """prepare -> teacher -> consensus (-> geometry) by the stage commands on ``profile``'s params with ``sets``,
    into ``workdir/artifacts`` unless the last one's output is there; returns that directory."""
    art = workdir / "artifacts"
    if catalog.path("gates" if geometry else "consensus", art).exists():
        return art
    workdir.mkdir(parents=True, exist_ok=True)
    p = {n: str(catalog.path(n, art)) for n in ("manifest", "images", "reference", "teacher", "teacher_scores",
                                                 "consensus", "geometry", "gates")}
    params_file = workdir / "params.yaml"
    write_text_if_changed(params_file, render_params_yaml(profile))
    common = ["--params", str(params_file)] + [a for s in sets for a in ("--set", s)] + ["--device", device]
    cmds = [["stages.prepare", "--out-dir", str(art)],
            ["stages.teacher", "--manifest", p["manifest"], "--images", p["images"], "--reference",
             p["reference"], "--out", p["teacher"], "--scores", p["teacher_scores"]],
            ["stages.consensus", "--teacher", p["teacher"], "--out", p["consensus"]]]
    if geometry:
        cmds.append(["stages.geometry", "--consensus", p["consensus"], "--manifest", p["manifest"], "--out",
                     p["geometry"], "--gates", p["gates"]])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    for cmd in cmds:
        print("+", " ".join(cmd[:1]), flush=True)
        subprocess.run([sys.executable, "-m", *cmd, *common], cwd=workdir, env=env, check=True)
    return art


def scored_test_rows(artifacts: Path):
    """(the manifest, the rows of the test images with a reference mask): the images a study scores, in order."""
    manifest = open_artifact(catalog.path("manifest", artifacts), "manifest")
    reference = open_artifact(catalog.path("reference", artifacts), "reference")
    test = np.flatnonzero((manifest.df["split"] == "test").to_numpy())
    return manifest, test[read_rows(reference, "has_mask", test).astype(bool)]


def load_study_data(artifacts: Path, cfg: Mapping[str, Any], methods=METHODS) -> dict:
    """Training arrays per method (the training API), the validation data, test images, masks and groups."""
    out: dict[str, Any] = {}
    for m in methods:
        out[m], out["val"], _ = load_inputs(artifacts, get_method(m), cfg)
    manifest, test = scored_test_rows(artifacts)
    images = open_artifact(catalog.path("images", artifacts), "images")
    reference = open_artifact(catalog.path("reference", artifacts), "reference")
    out["test_images"] = read_rows(images, "image", test)
    out["test_masks"] = read_rows(reference, "mask", test).astype(bool)
    out["test_groups"] = manifest.df["group"].to_numpy()[test].astype(str)
    return out


def pos_weight_stats(mask: np.ndarray, batch_size: int, seed: int, epochs: int, max_weight: float) -> dict:
    """The positive-class weight pi (eq:positive-weight) over ``epochs`` epochs of the loop's seeded batches:
    median pi and the share of batches at the clip."""
    import torch

    from pipeline.losses import positive_weight

    n = len(mask)
    pis = []
    for epoch in range(1, epochs + 1):
        order = np.random.default_rng([seed, epoch]).permutation(n)
        for s in range(0, n, batch_size):
            pis.append(float(positive_weight(torch.from_numpy(mask[order[s:s + batch_size]]), None, max_weight)))
    pis = np.asarray(pis)
    frac = mask.reshape(n, -1).mean(1)
    return {"median_pi": float(np.median(pis)), "share_at_clip": float(np.mean(pis >= max_weight)),
            "share_tiny_targets": float(np.mean(frac < TINY_FRACTION)), "n_batches": int(len(pis))}


def max_adjacent_jump(val_iou: np.ndarray) -> float:
    """Largest |v[e] - v[e-1]| over adjacent logged epochs (NaN entries skipped); 0 for < 2 values."""
    v = np.asarray(val_iou, dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(np.max(np.abs(np.diff(v)))) if len(v) > 1 else 0.0


def area_ratios(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Per image predicted / reference foreground pixel count (images with a non-empty reference)."""
    p = pred.reshape(len(pred), -1).sum(1).astype(np.float64)
    g = gt.reshape(len(gt), -1).sum(1).astype(np.float64)
    keep = g > 0
    return p[keep] / g[keep]


def score_run(model, val, test_images, test_masks, device) -> dict:
    """Test scores at the tau calibrated on validation (the epoch grid) and at 0.5; predictions in fp32."""
    vp = predict_probs(model, val.images, device=device, precision="fp32")
    tau, _ = calibrate_threshold(vp, val.masks, EPOCH_TAU_GRID)
    tp = predict_probs(model, test_images, device=device, precision="fp32")
    tiny = test_masks.reshape(len(test_masks), -1).mean(1) < TINY_FRACTION
    out = {"tau_cal": float(tau)}
    for key, t in (("cal", tau), ("05", 0.5)):
        pred = mask_from_probs(tp, t)
        ious = image_ious(pred, test_masks)
        out[f"iou_{key}"] = float(ious.mean())
        out[f"area_{key}"] = float(np.median(area_ratios(pred, test_masks)))
        out[f"iou_{key}_tiny"] = float(ious[tiny].mean()) if tiny.any() else float("nan")
        out[f"iou_{key}_rest"] = float(ious[~tiny].mean()) if (~tiny).any() else float("nan")
    return out


_DATA: dict = {}


def _init_worker(artifacts: str, cfg: dict, threads: int) -> None:
    import torch

    torch.set_num_threads(threads)
    _DATA.update(load_study_data(Path(artifacts), cfg))


def run_one(job: dict) -> dict:
    """Train (variant, method, seed) and score it; the process's study data come from :func:`_init_worker`."""
    from pipeline.training import loop as training
    t0 = time.perf_counter()
    cfg = job["cfg"]
    res = training.train(get_method(job["method"]), cfg, _DATA[job["method"]], _DATA["val"], job["seed"],
                         checkpointer=NoCheckpointer(), device=job["device"], show_progress=False)
    log = res.log[res.log["epoch"] >= 1]
    out = {k: job[k] for k in ("variant", "method", "seed")}
    out.update(selected_epoch=res.selected_epoch, max_jump=max_adjacent_jump(log["val_iou"].to_numpy()),
               **{f"{c}_curve": [float(v) for v in log[c]] for c in ("val_iou", "val_iou_cal", "loss")},
               autocast=res.info["autocast"], stopped=res.info.get("stopped"), steps_run=res.info.get("steps_run"))
    out.update(score_run(res.model, _DATA["val"], _DATA["test_images"], _DATA["test_masks"], job["device"]))
    out["seconds"] = time.perf_counter() - t0
    print(f"  done {out['variant']:18s} {out['method']:18s} s{out['seed']}: iou_cal {out['iou_cal']:.3f} "
          f"iou_05 {out['iou_05']:.3f} jump {out['max_jump']:.3f} ({out['seconds']:.0f} s)", flush=True)
    return out


COLUMNS = ("iou_cal", "iou_05", "max_jump", "max_jump_cal", "area_cal", "area_05", "iou_cal_tiny", "tau_cal")


def summarize(results: list[dict]) -> list[dict]:
    """Means over seeds per (variant, method), with differences to the paper recipe of the same method; a run's
    ``max_jump_cal`` is the largest epoch-to-epoch change of its calibrated validation IoU."""
    rows = []
    results = [{**r, "max_jump_cal": max_adjacent_jump(r["val_iou_cal_curve"])} for r in results]
    for v in dict.fromkeys(r["variant"] for r in results):
        for m in METHODS:
            rs = [r for r in results if r["variant"] == v and r["method"] == m]
            if rs:
                rows.append({"variant": v, "method": m, "n_seeds": len(rs),
                             **{c: float(np.mean([r[c] for r in rs])) for c in COLUMNS}})
    base = {r["method"]: r for r in rows if r["variant"] == "paper"}
    for r in rows:
        b = base.get(r["method"])
        for c in ("iou_cal", "iou_05", "max_jump", "max_jump_cal"):
            r[f"d_{c}"] = r[c] - b[c] if b is not None else float("nan")
    return rows


def print_table(rows: list[dict], header: str) -> None:
    print(header)
    print(f"{'variant':18s} {'method':18s} {'IoU@cal':>7s} {'d':>7s} {'IoU@.5':>7s} {'d':>7s} {'maxjump':>7s} "
          f"{'d':>7s} {'jump@c':>6s} {'area@c':>6s} {'area@.5':>7s} {'tinyIoU':>7s} {'tau':>5s}")
    for r in rows:
        print(f"{r['variant']:18s} {r['method']:18s} {r['iou_cal']:7.3f} {r['d_iou_cal']:+7.3f} {r['iou_05']:7.3f} "
              f"{r['d_iou_05']:+7.3f} {r['max_jump']:7.3f} {r['d_max_jump']:+7.3f} {r['max_jump_cal']:6.3f} {r['area_cal']:6.2f} "
              f"{r['area_05']:7.2f} {r['iou_cal_tiny']:7.3f} {r['tau_cal']:5.2f}")


def add_data_size_options(ap) -> None:
    """``--train-spacecraft`` ... ``--test-views``: the data.synthetic sizes of :data:`DATA_SIZES`."""
    for key in DATA_SIZES:
        ap.add_argument("--" + key.replace("_", "-"), type=int, default=None, help=f"data.synthetic.{key}")


def data_size_sets(args) -> list[str]:
    """``--set`` items of the data sizes given on the command line (:func:`add_data_size_options`)."""
    return [f"data.synthetic.{k}={getattr(args, k)}" for k in DATA_SIZES if getattr(args, k) is not None]


def main(argv=None) -> dict:
    ap = parser(__doc__, artifacts=None, workdir="study_recipe", profile="paper", resolution=384, epochs=None,
                seeds=[42], device="cpu", jobs=1, threads=1, out="study_recipe.json", set=[])
    add_data_size_options(ap)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    args = ap.parse_args(argv)

    device = str(resolve_device(args.device))
    sets = [f"data.resolution={args.resolution}"] + data_size_sets(args) + args.sets
    params = load_profile(args.profile, sets)
    artifacts = (Path(args.artifacts) if args.artifacts
                 else build_artifacts(Path(args.workdir).resolve(), args.profile, sets, device))
    base = dict(params["train"])
    base["num_threads"] = args.threads
    base["validate_low_res"] = True  # the study reads the whole validation curve (max_jump), half-side epochs too
    if args.epochs is not None:
        base["epochs_stage1"] = args.epochs
    data = load_study_data(artifacts, base)
    info = {"artifacts": str(artifacts), "device": device, "resolution": args.resolution, "profile": args.profile,
            "n_train": {m: len(data[m]) for m in METHODS}, "n_val": len(data["val"]),
            "n_test": int(len(data["test_masks"])), "epochs": base["epochs_stage1"], "seeds": args.seeds,
            "threads": args.threads, "jobs": args.jobs,
            "pos_weight": {m: pos_weight_stats(np.asarray(data[m].mask), base["batch_size"], args.seeds[0], base["epochs_stage1"],
                                               base["pos_weight_max"]) for m in METHODS}}
    print(json.dumps(info))
    jobs = [{"variant": v, "method": m, "seed": s, "device": device, "cfg": {**base, **VARIANTS[v][0]}}
            for s in args.seeds for v in args.variants for m in args.methods]
    t0 = time.perf_counter()
    results_by_key = resumed_runs(args.out, info, jobs, lambda todo: run_jobs(
        todo, str(artifacts), base, args.jobs, args.threads, _init_worker, run_one))
    results = [results_by_key[(j["variant"], j["method"], j["seed"])] for j in jobs]
    info["wall_seconds"] = time.perf_counter() - t0
    rows = summarize(results)
    print_table(rows, f"\n{info['n_train']} train / {info['n_val']} val / {info['n_test']} test images at "
                      f"{args.resolution}^2, {base['epochs_stage1']} epochs, seeds {args.seeds}, device {device}, "
                      f"{args.jobs} x {args.threads} threads; means over seeds; d = variant - paper (same method)")
    out = {"info": info, "variants": {v: {"overrides": VARIANTS[v][0], "tests": VARIANTS[v][1]} for v in args.variants},
           "summary": rows, "runs": results}
    Path(args.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}")
    return out


if __name__ == "__main__":
    main()
