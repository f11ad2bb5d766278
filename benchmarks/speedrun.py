"""Speedrun: the training cost (images x (resolution / 128)^2) at which a candidate recipe reaches the
validation Image IoU V of a converged baseline (``strong``, 400 epochs).  Each candidate trains the Plain
Student from scratch on the reduced profile's data; V is the seed mean at the calibrated tau of the final
weights.  Pass: V >= the baseline's at <= 1/4 of its cost.  ``--out`` keeps every finished run.
``--score-test`` scores the test images too (once, for the winner's confirmation on fresh seeds).

    python -m benchmarks.speedrun --resolution 64 --seeds 42 3407 2026 --jobs 2 --out reports/speedrun/speedrun-64.json
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from benchmarks.common import parser, read_json, run_jobs
from benchmarks.study_recipe import build_artifacts, load_study_data, score_run
from pipeline.methods import STAGE_ONE, get_method
from pipeline.params import RECIPES
from pipeline.profiles import load_profile
from pipeline.training import loop as training
from pipeline.training import schedule
from pipeline.training.checkpointing import NoCheckpointer

#: the resolution the cost is counted at
COST_RESOLUTION = 128
#: a candidate passes at no more than this share of the baseline's cost
PASS_COST_SHARE = 0.25
BASELINE = "baseline"
#: candidate -> (``train.*`` changes of ``strong``, what it tests); ``soft_targets`` departs from eq:raw-loss
CANDIDATES: dict[str, tuple[dict, str]] = {
    BASELINE: ({"epochs_stage1": 400}, "strong's schedule from scratch, 400 epochs"),
    "strong_100": ({"epochs_stage1": 100}, "strong at a quarter of the baseline's epochs (rate x1)"),
    "lr2": ({"epochs_stage1": 100, "lr_scale": 2}, "peak rate x2"),
    "lr4": ({"epochs_stage1": 100, "lr_scale": 4, "warmup_epochs": 5}, "peak rate x4, 5 warm-up epochs"),
    "lr8": ({"epochs_stage1": 100, "lr_scale": 8, "warmup_epochs": 5}, "peak rate x8, 5 warm-up epochs"),
    "b32_lr4": ({"epochs_stage1": 100, "batch_size": 32, "lr_scale": 4, "warmup_epochs": 5},
                "batch 32 at 4x the rate (linear scaling from batch 8)"),
    "ema_lr4": ({"epochs_stage1": 100, "lr_scale": 4, "warmup_epochs": 5, "ema_decay": 0.999, "average_last": 0},
                "peak rate x4 + a moving average of the weights instead of the mean of the last 4 epochs"),
    "half_res_first": ({k: RECIPES["progressive"]["train"][k] for k in ("epochs_stage1", "low_res_fraction")},
                       "a resolution schedule: the first 160 of 220 epochs at half the side (a quarter of the cost)"),
    "soft_lr4": ({"epochs_stage1": 100, "lr_scale": 4, "warmup_epochs": 5, "soft_targets": True},
                 "peak rate x4 + soft targets (the agreement map; departs from eq:raw-loss)"),
}


def run_cost(epochs: int, n_train: int, resolution: int, low_res_epochs: int = 0) -> float:
    """Training images x (side / 128)^2 of a run of ``epochs`` over ``n_train`` images at ``resolution``, its first
    ``low_res_epochs`` at 1 / LOW_RES_FACTOR of the side (``train.low_res_fraction``)."""
    full = float(epochs - low_res_epochs) + float(low_res_epochs) / schedule.LOW_RES_FACTOR ** 2
    return full * int(n_train) * (int(resolution) / COST_RESOLUTION) ** 2


def candidate_cfg(base: Mapping[str, Any], name: str) -> dict:
    """``strong``'s train section with candidate ``name``'s changes (``average_last`` 1 when it averages nothing)."""
    cfg = {**base, **CANDIDATES[name][0]}
    if not cfg.get("ema_decay") and not cfg.get("average_last"):
        cfg["average_last"] = 1
    return cfg


_DATA: dict = {}


def _init(artifacts: str, cfg: dict, threads: int) -> None:
    import torch

    torch.set_num_threads(threads)
    _DATA.clear()
    _DATA.update(load_study_data(Path(artifacts), cfg, methods=(STAGE_ONE,)))
    if cfg.get("soft"):  # the soft-target candidates read the agreement map
        _DATA["soft"] = load_study_data(Path(artifacts), {**cfg, "soft_targets": True}, methods=(STAGE_ONE,))[STAGE_ONE]


def run_one(job: dict) -> dict:
    """Train one (candidate, seed) and score V."""
    cfg = job["cfg"]
    data = _DATA["soft"] if cfg.get("soft_targets") else _DATA[STAGE_ONE]
    t0 = time.perf_counter()
    res = training.train(get_method(STAGE_ONE), cfg, data, None, job["seed"], checkpointer=NoCheckpointer(),
                         device=job["device"], show_progress=False)
    seconds = time.perf_counter() - t0
    scores = training.validation_scores(res.model, _DATA["val"], job["device"], precision="fp32",
                                        channels_last=False, tolerance=float(cfg["val_bf1_tolerance"]))
    out = {"candidate": job["candidate"], "seed": job["seed"], "V": scores["val_iou_cal"],
           "tau": scores["val_tau_cal"], "V_05": scores["val_iou"],
           "cost": run_cost(cfg["epochs_stage1"], len(data), job["resolution"], res.info["low_res_epochs"]),
           "seconds": seconds}
    if job.get("score_test"):  # test IoU at the tau calibrated on validation, and at 0.5
        test = score_run(res.model, _DATA["val"], _DATA["test_images"], _DATA["test_masks"], job["device"])
        out.update(test_iou=test["iou_cal"], test_iou_05=test["iou_05"])
    print(f"  {out['candidate']:10s} s{out['seed']}: V {out['V']:.3f} (tau {out['tau']:.2f}), at 0.5 "
          f"{out['V_05']:.3f}, cost {out['cost']:.0f}, {seconds:.0f} s", flush=True)
    return out


def summarize(runs: list[dict]) -> list[dict]:
    """Per candidate: V's seed mean and std, V at 0.5, the cost and its ratio to the baseline's, and the verdict."""
    by: dict[str, list[dict]] = {}
    for r in runs:
        by.setdefault(r["candidate"], []).append(r)
    base = by.get(BASELINE)
    base_v = float(np.mean([r["V"] for r in base])) if base else None
    base_cost = float(np.mean([r["cost"] for r in base])) if base else None
    rows = []
    for name, rs in by.items():
        v = np.array([r["V"] for r in rs])
        cost = float(np.mean([r["cost"] for r in rs]))
        ratio = cost / base_cost if base_cost else None
        rows.append({"candidate": name, "seeds": sorted(r["seed"] for r in rs), "V": float(v.mean()),
                     "V_std": float(v.std(ddof=1)) if len(v) > 1 else None,
                     "V_05": float(np.mean([r["V_05"] for r in rs])), "cost": cost, "cost_ratio": ratio,
                     "passes": (None if base_v is None or name == BASELINE
                                else bool(v.mean() >= base_v and ratio <= PASS_COST_SHARE)),
                     "what": CANDIDATES[name][1] if name in CANDIDATES else "",
                     "test_iou": (float(np.mean([r["test_iou"] for r in rs])) if all("test_iou" in r for r in rs)
                                  else None)})
    return sorted(rows, key=lambda r: (r["candidate"] != BASELINE, r["cost"], -r["V"]))


def table(rows: list[dict]) -> str:
    """The summary as a Markdown table."""
    out = ["| candidate | seeds | V (calibrated tau) | V at 0.5 | cost | cost / baseline | passes | test IoU |",
           "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        v = f"{r['V']:.3f}" + (f" ± {r['V_std']:.3f}" if r["V_std"] is not None else "")
        ratio = f"{r['cost_ratio']:.2f}" if r["cost_ratio"] is not None else "n/a"
        out.append(f"| {r['candidate']} | {len(r['seeds'])} | {v} | {r['V_05']:.3f} | {r['cost']:,.0f} | {ratio} "
                   f"| {'n/a' if r['passes'] is None else ('yes' if r['passes'] else 'no')} "
                   f"| {'not scored' if r.get('test_iou') is None else format(r['test_iou'], '.3f')} |")
    return "\n".join(out)


def main(argv=None) -> dict:
    ap = parser(__doc__, workdir="speedrun", artifacts=None, profile="reduced", resolution=128, set=[],
                seeds=[42, 3407, 2026], jobs=1, threads=1, device="cpu", out="speedrun.json")
    ap.add_argument("--candidates", nargs="+", default=list(CANDIDATES), choices=list(CANDIDATES))
    ap.add_argument("--score-test", action="store_true", help="score the test images too (the confirmation)")
    args = ap.parse_args(argv)

    sets = [f"data.resolution={args.resolution}", *args.sets]
    params = load_profile(args.profile, ["train.recipe=strong", *sets])
    artifacts = Path(args.artifacts) if args.artifacts else \
        build_artifacts(Path(args.workdir).resolve(), args.profile, sets, args.device)
    base = {**params["train"], "num_threads": args.threads}
    out = Path(args.out)
    info = {"profile": args.profile, "resolution": args.resolution, "sets": sets, "device": args.device,
            "threads": args.threads, "artifacts": str(artifacts.resolve())}
    doc = read_json(out, {"info": info, "runs": []})
    if not isinstance(doc, dict) or doc.get("info") != info:
        ap.error(f"--out {out}: exists and is not a speedrun with these settings; give another --out")
    done = {(r["candidate"], r["seed"]) for r in doc["runs"]}
    jobs = [{"candidate": c, "seed": s, "cfg": candidate_cfg(base, c), "device": args.device,
             "resolution": args.resolution, "score_test": args.score_test} for c in args.candidates for s in args.seeds if (c, s) not in done]
    jobs.sort(key=lambda j: -j["cfg"]["epochs_stage1"])  # the longest first: the pool ends together
    init_cfg = {**base, "soft": any(j["cfg"].get("soft_targets") for j in jobs)}
    for r in run_jobs(jobs, str(artifacts), init_cfg, args.jobs, args.threads, _init, run_one):
        doc["runs"].append(r)
        doc["summary"] = summarize(doc["runs"])
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(doc, indent=1))  # finished runs survive an interruption
    doc["summary"] = summarize(doc["runs"])
    print(table(doc["summary"]), flush=True)
    return doc


if __name__ == "__main__":
    main()
