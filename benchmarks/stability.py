"""Do the demo's published numbers (docs/stability.md) hold under numerical perturbations -- 1 thread, the other
precision -- compared with the seed-to-seed spread?  Per (recipe, perturbation, seed) it trains ``plain``, then
``geodistill`` and ``continuation`` warm-started from it, on the profile's synthetic benchmark, scores every group
at the tau of each rule, and prints each number's perturbation and seed spreads and whether the target holds;
``--noise-floor`` records the first recipe's spreads for the report.

    python -m benchmarks.stability --profile reduced --recipes paper --seeds 42 3407 2026 --noise-floor reports/noise_floor.json
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from pipeline.artifacts.atomic import write_json
from benchmarks import study_recipe as sr
from benchmarks.common import parser, resumed_runs, run_jobs
from pipeline.runtime.device import autocast_dtype
from pipeline.artifacts.provenance import cpu
from pipeline.runtime.errors import InputError
from pipeline.evaluation.inference import predict_probs
from pipeline.methods import BASELINE, CONTINUATION, PROPOSED, STAGE_ONE, get_method
from pipeline.metrics import iou_curve, per_image_metrics
from pipeline.params import RECIPES, validate_section
from pipeline.profiles import FIVE_SEEDS, load_profile
from pipeline.report.analysis import noise_floor_key, noise_floor_records
from pipeline.reproducibility import TOLERANCE
from pipeline.stats import ONE_SIDED_95_Z
from pipeline.thresholds import TAU_RULES, mask_from_probs, tau_by_rule, threshold_grid
from pipeline.training.checkpointing import NoCheckpointer

#: the RECIPES key of the paper's own recipe: the reference of every other recipe's "no worse" condition
PAPER_RECIPE = "paper"
#: the demo's runs, in training order: Stage I first (the others warm-start from it)
METHODS = tuple(dict.fromkeys((STAGE_ONE, BASELINE, PROPOSED, CONTINUATION)))
#: (treatment, control) pairs whose gains the demo publishes
GAINS = ((PROPOSED, BASELINE), (PROPOSED, CONTINUATION))
#: perturbation -> train overrides (``precision`` is resolved per recipe: the other precision)
PERTURBATIONS = {"default": {"num_threads": 2}, "threads1": {"num_threads": 1}, "precision": {"num_threads": 2}}
#: screening candidates: recipe parts on top of ``train.recipe: paper`` (or of the recipe the candidate names)
CANDIDATES: dict[str, dict] = {
    "fp32": {"precision": "fp32"},
    "fp32_avg5": {"precision": "fp32", "average_last": 5},
    "fp32_warmup1": {"precision": "fp32", "warmup_epochs": 1},
    "fp32_precise_bn": {"precision": "fp32", "precise_bn": True},
    "fp32_pos_weight_10": {"precision": "fp32", "pos_weight_max": 10.0},
    "avg5": {"average_last": 5},
    "stable_warmup1": {"recipe": "stable", "warmup_epochs": 1},
    "stable_pos_weight_10": {"recipe": "stable", "pos_weight_max": 10.0},
}
METRICS = ("iou", "bf1")


def recipe_train(name: str, base: Mapping[str, Any]) -> dict:
    """The train section of a :data:`pipeline.params.RECIPES` or :data:`CANDIDATES` name over ``base``."""
    parts = {"recipe": name} if name in RECIPES else {"recipe": PAPER_RECIPE, **CANDIDATES[name]}
    return validate_section("train", {**base, **{k: None for k in RECIPES[PAPER_RECIPE]["train"]}, **parts})


def perturbed(cfg: Mapping[str, Any], perturbation: str) -> dict:
    """``cfg`` under a perturbation: thread count, or the other precision of this host."""
    import torch

    out = {**cfg, **PERTURBATIONS[perturbation]}
    if perturbation == "precision":
        out["precision"] = "bf16" if autocast_dtype(torch.device("cpu"), cfg["precision"]) is None else "fp32"
    return out


def score(model, data: Mapping[str, Any], cal: Mapping[str, Any], tolerance: float) -> dict:
    """Per tau rule: the calibrated tau and the per-group test scores, the means of [P >= tau]
    (eq:inference-mask) per test group (predictions in fp32)."""
    grid = threshold_grid(cal)
    val = data["val"]
    curve = iou_curve(predict_probs(model, val.images), val.masks, grid).mean(axis=0)
    tp, groups = predict_probs(model, data["test_images"]), data["test_groups"]
    out = {}
    for rule in TAU_RULES:
        tau = tau_by_rule(grid, curve, rule, tolerance=cal["plateau_tolerance"], halfwidth=cal["smooth_halfwidth"])
        m = per_image_metrics(mask_from_probs(tp, tau), data["test_masks"], tolerance)
        out[rule] = {"tau": tau, "groups": {str(g): {k: float(np.mean(m[k][groups == g])) for k in METRICS}
                                            for g in dict.fromkeys(groups)}}
    return out


_DATA: dict = {}


def _init_worker(artifacts: str, cfg: dict, threads: int) -> None:
    _DATA.update(sr.load_study_data(Path(artifacts), cfg, methods=(STAGE_ONE, PROPOSED)))


def run_one(job: dict) -> dict:
    """Stage I, then the methods warm-started from it, for one (recipe, perturbation, seed)."""
    from pipeline.training import loop as training
    t0 = time.perf_counter()
    cfg, seed = job["cfg"], job["seed"]
    out = {k: job[k] for k in ("recipe", "perturbation", "seed", "variant", "method")}
    init = None
    for m in METHODS:
        data = _DATA[PROPOSED if m == PROPOSED else STAGE_ONE]  # the continuation reads Stage I's pseudo-masks
        res = training.train(get_method(m), cfg, data, _DATA["val"], seed, checkpointer=NoCheckpointer(),
                             init_state=init, show_progress=False)
        if m == STAGE_ONE:
            init = res.model.mask_path_state_dict()
        out[m] = {"selected_epoch": res.selected_epoch, "autocast": res.info["autocast"],
                  **score(res.model, _DATA, job["cal"], job["tolerance"])}
    out["seconds"] = time.perf_counter() - t0
    print(f"  done {out['recipe']:18s} {out['perturbation']:9s} s{seed} ({out['seconds']:.0f} s)", flush=True)
    return out


def published(run: Mapping[str, Any], rule: str) -> dict[str, float]:
    """One run's ``<method>/<group>/<metric>`` and gains ``<treatment>-<control>/<group>/<metric>`` under a tau rule."""
    out = {f"{m}/{g}/{k}": v[k] for m in METHODS for g, v in run[m][rule]["groups"].items() for k in METRICS}
    out.update({f"{t}-{c}/{g}/{k}": out[f"{t}/{g}/{k}"] - out[f"{c}/{g}/{k}"]
                for t, c in GAINS for g in run[t][rule]["groups"] for k in METRICS})
    return out


def spreads(runs: list[dict], rule: str) -> dict[str, dict]:
    """Per published number: ``mean`` and ``seed_sd`` over seeds (default perturbation), ``pert`` (the largest
    range over one seed's perturbations), ``pert_mean`` (the range of the seed-means over perturbations) and
    ``move_<p>`` (|seed-mean under p - under the default|, the seeds run under every perturbation)."""
    seeds = sorted({r["seed"] for r in runs})
    perts = [p for p in PERTURBATIONS if any(r["perturbation"] == p for r in runs)]
    val = {(r["perturbation"], r["seed"]): published(r, rule) for r in runs}
    full = [s for s in seeds if all((p, s) in val for p in perts)]  # seeds run under every perturbation
    out = {}
    for k in next(iter(val.values())):
        d = [val[("default", s)][k] for s in seeds if ("default", s) in val]
        per_seed = [np.ptp([val[(p, s)][k] for p in perts if (p, s) in val]) for s in seeds
                    if sum((p, s) in val for p in perts) > 1]
        means = {p: np.mean([val[(p, s)][k] for s in full]) for p in perts} if full else {}
        out[k] = {"mean": float(np.mean(d)) if d else float("nan"),
                  "seed_sd": float(np.std(d, ddof=1)) if len(d) > 1 else float("nan"),
                  "pert": float(max(per_seed)) if per_seed else float("nan"),
                  "pert_mean": float(np.ptp(list(means.values()))) if len(means) > 1 else float("nan"),
                  "n_seeds": len(d), "n_pert_seeds": len(full),
                  **{f"move_{p}": float(abs(means[p] - means["default"])) for p in perts
                     if p != "default" and "default" in means}}
    return out


def exposed(cfg: Mapping[str, Any]) -> list[str]:
    """The perturbations a recipe is exposed to between hosts: threads always, the precision when ``auto``."""
    return ["threads1"] + (["precision"] if cfg["precision"] == "auto" else [])


#: one-sided 95 % normal quantile of the non-inferiority check (:func:`no_worse_than`)
NON_INFERIORITY_Z = ONE_SIDED_95_Z


def no_worse_than(sp: Mapping[str, dict], reference: Mapping[str, dict] | None, metric: str = "iou") -> bool | None:
    """Non-inferiority of every student seed-mean ``metric`` to the ``reference`` recipe's: the one-sided 95 %
    lower bound of the difference, standard error sqrt(sd^2/n + sd_ref^2/n_ref), above -TOLERANCE[metric];
    None without a reference."""
    pairs = [(v, reference[k]) for k, v in _numbers(sp, metric).items() if k in reference] if reference else []
    se = [np.sqrt(v["seed_sd"] ** 2 / v.get("n_seeds", 1) + r["seed_sd"] ** 2 / r.get("n_seeds", 1)) for v, r in pairs]
    if not pairs or not np.all(np.isfinite(se)):
        return None
    return all(v["mean"] - r["mean"] - NON_INFERIORITY_Z * e > -TOLERANCE[metric] for (v, r), e in zip(pairs, se))


def target_met(sp: Mapping[str, dict], perturbations=("threads1", "precision"),
               reference: Mapping[str, dict] | None = None, check_reference: bool = False) -> tuple[bool, float, float]:
    """(met, worst IoU move, worst BF1 move): every student seed-mean moves by at most
    :data:`pipeline.reproducibility.TOLERANCE` under each of ``perturbations`` and, with ``check_reference``,
    is :func:`no_worse_than` the ``reference`` recipe's."""
    worst = {k: max((_worst(sp, f"move_{p}", k) for p in perturbations), default=float("nan")) for k in METRICS}
    met = all(worst[k] <= TOLERANCE[k] for k in METRICS)
    return met and (not check_reference or no_worse_than(sp, reference) is True), worst["iou"], worst["bf1"]


def print_summary(recipe: str, rule: str, sp: Mapping[str, dict], perturbations=("threads1", "precision")) -> None:
    met, wi, wb = target_met(sp, perturbations)
    print(f"\n== recipe {recipe}, tau rule {rule}: target {'MET' if met else 'NOT met'} under {list(perturbations)} "
          f"(worst move of a seed-mean: IoU {wi:.4f}, BF1 {wb:.4f})")
    moves = [k for k in next(iter(sp.values())) if k.startswith("move_")]
    print(f"{'number':34s} {'mean':>7s} {'seed sd':>7s} {'pert1':>7s} " + " ".join(f"{m:>14s}" for m in moves))
    for k, v in sp.items():
        print(f"{k:34s} {v['mean']:+7.3f} {v['seed_sd']:7.3f} {v['pert']:7.3f} "
              + " ".join(f"{v[m]:14.4f}" for m in moves))


def _numbers(sp: Mapping[str, dict], metric: str, gains: bool = False) -> dict[str, dict]:
    """The published numbers of ``metric``: the gains', else the methods' own."""
    return {n: v for n, v in sp.items() if ("-" in n.split("/")[0]) == gains and n.endswith("/" + metric)}


def _worst(sp, key: str, metric: str, gains: bool = False) -> float:
    return max((v.get(key, float("nan")) for v in _numbers(sp, metric, gains).values()), default=float("nan"))


def recipe_table(summary: Mapping[str, Mapping[str, dict]], exposure: Mapping[str, list] | None = None) -> list[dict]:
    """One row per (recipe, rule): the methods' mean IoU and BF1, the worst moves, the median seed sd, and
    whether the target holds under the recipe's ``exposure`` (default: every perturbation)."""
    rows = []
    for key, sp in summary.items():
        recipe, rule = key.split("|")
        perts = (exposure or {}).get(recipe, ("threads1", "precision"))
        reference = summary.get(f"{PAPER_RECIPE}|{rule}")
        met, wi, wb = target_met(sp, perts, reference, check_reference=recipe != PAPER_RECIPE)
        row = {"recipe": recipe, "rule": rule, "target": met, "exposed": list(perts), "pert_iou": wi, "pert_bf1": wb,
               "no_worse": no_worse_than(sp, reference) if recipe != PAPER_RECIPE else True}
        for k in METRICS:
            row.update({f"move_{p}_{k}": _worst(sp, f"move_{p}", k) for p in ("threads1", "precision")})
            row[f"pert1_{k}"] = _worst(sp, "pert", k)
            row[f"gain_pert1_{k}"] = _worst(sp, "pert", k, gains=True)
            row.update({f"{m}_{k}": float(np.mean([v["mean"] for n, v in _numbers(sp, k).items()
                                                   if n.startswith(m + "/")])) for m in METHODS})
            row[f"seed_sd_{k}"] = float(np.median([v["seed_sd"] for v in _numbers(sp, k).values()]))
        rows.append(row)
    return rows


#: the printed recipe table's columns: (header, row key)
TABLE = (("plainIoU", "plain_iou"), ("geoIoU", "geodistill_iou"), ("contIoU", "continuation_iou"),
         ("plainBF1", "plain_bf1"), ("geoBF1", "geodistill_bf1"), ("thrIoU", "move_threads1_iou"),
         ("thrBF1", "move_threads1_bf1"), ("prcIoU", "move_precision_iou"), ("prcBF1", "move_precision_bf1"),
         ("1sIoU", "pert1_iou"), ("1sBF1", "pert1_bf1"), ("sdIoU", "seed_sd_iou"), ("sdBF1", "seed_sd_bf1"))


def print_recipe_table(rows: list[dict]) -> None:
    print(f"\n{'recipe':18s} {'rule':8s} " + " ".join(f"{h:>{max(6, len(h))}s}" for h, _ in TABLE) + " target")
    for r in rows:
        print(f"{r['recipe']:18s} {r['rule']:8s} " + " ".join(f"{r[k]:{max(6, len(h))}.3f}" for h, k in TABLE)
              + f" {'yes' if r['target'] else 'no'} ({'+'.join(r['exposed'])})")


def noise_floor_record(sp: Mapping[str, dict], info: Mapping[str, Any], perturbations) -> dict:
    """The record the report reads (:func:`pipeline.report.analysis.gain_noise_floor`): per published number,
    ``floor`` (its largest seed-mean move under ``perturbations``), ``pert`` and ``seed_sd``."""
    nums = {k: {"floor": max((v.get(f"move_{p}", float("nan")) for p in perturbations), default=float("nan")),
                "pert": v["pert"], "seed_sd": v["seed_sd"]} for k, v in sp.items()}
    return {"info": {**dict(info), "perturbations": list(perturbations)}, "numbers": nums}


def write_noise_floor(path: str | Path, key: str, record: dict) -> dict:
    """Put ``record`` into the noise-floor file under ``key`` (one per configuration,
    :func:`pipeline.report.analysis.noise_floor_key`), keeping the others; returns the whole document."""
    path = Path(path)
    old = json.loads(path.read_text()) if path.is_file() else {}
    doc = {"recipes": {**noise_floor_records(old), key: record}}
    write_json(path, doc)  # its folder made if missing
    return doc


def main(argv=None) -> dict:
    ap = parser(__doc__, workdir="bench_stability", resolution=None, epochs=None, seeds=FIVE_SEEDS, jobs=2,
                out="bench_stability.json")
    ap.add_argument("--profile", default="demo", choices=["demo", "reduced", "paper"],
                    help="whose data sizes and epochs (e.g. reduced: 270/60/3x60 images, 20 + 10 epochs)")
    ap.add_argument("--epochs-stage2", type=int, default=None, help="train.epochs_stage2 (default: the profile's)")
    ap.add_argument("--pert-seeds", type=int, default=None,
                    help="run the perturbations for the first N seeds only (default: all)")
    ap.add_argument("--perturbations", nargs="+", default=list(PERTURBATIONS), choices=list(PERTURBATIONS),
                    help="default is always run; e.g. --perturbations default threads1 for pinned-precision recipes")
    ap.add_argument("--recipes", nargs="+", default=list(RECIPES),
                    help="train.recipe names and/or screening candidates: " + ", ".join(CANDIDATES))
    ap.add_argument("--noise-floor", default=None,
                    help="put the first recipe's spreads into this file as its record (reports/noise_floor.json)")
    args = ap.parse_args(argv)
    # idle OpenMP threads sleep instead of spinning: on a shared 2-core machine a spinning thread of a
    # 2-thread run stalls the other; no effect on the numbers
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

    bad = [r for r in args.recipes if r not in RECIPES and r not in CANDIDATES]
    if bad:
        raise InputError(f"--recipes {bad}: expected one of {', '.join([*RECIPES, *CANDIDATES])}")
    if args.resolution is None:
        args.resolution = int(load_profile(args.profile)["data"]["resolution"])
    sets = [f"data.resolution={args.resolution}"]
    params = load_profile(args.profile, sets)
    artifacts = sr.build_artifacts(Path(args.workdir).resolve(), args.profile, sets, "cpu", geometry=True)
    epochs = {k: v for k, v in (("epochs_stage1", args.epochs), ("epochs_stage2", args.epochs_stage2)) if v is not None}
    base = {**params["train"], **epochs}
    cfgs = {r: {**recipe_train(r, base), **epochs} for r in args.recipes}  # the epochs are recipe parts: set after
    pert_seeds = args.seeds[:args.pert_seeds] if args.pert_seeds else args.seeds
    # a run's (variant, method) of the resumable jobs are its (recipe, perturbation)
    jobs = [{"recipe": rname, "perturbation": p, "seed": s, "variant": rname, "method": p,
             "cfg": perturbed(cfgs[rname], p),
             "cal": params["calibrate"], "tolerance": params["evaluate"]["bf1_tolerance"]}
            for rname in args.recipes for s in args.seeds for p in dict.fromkeys(["default", *args.perturbations])
            if p == "default" or s in pert_seeds]
    info = {"artifacts": str(artifacts), "device": "cpu", "resolution": args.resolution, "profile": args.profile,
            "epochs": {r: [c["epochs_stage1"], c["epochs_stage2"]] for r, c in cfgs.items()}, "n_train": None}
    t0 = time.perf_counter()
    results = resumed_runs(args.out, info, jobs, lambda todo: run_jobs(
        todo, str(artifacts), base, args.jobs, 1, _init_worker, run_one))
    summary = {}
    exposure = {r: exposed(recipe_train(r, base)) for r in args.recipes}
    for rname in args.recipes:
        runs = [results[(rname, j["perturbation"], j["seed"])] for j in jobs if j["recipe"] == rname]
        for rule in TAU_RULES:
            summary[f"{rname}|{rule}"] = sp = spreads(runs, rule)
            print_summary(rname, rule, sp, exposure[rname])
    rows = recipe_table(summary, exposure)
    print(f"\nseeds {args.seeds} (perturbations on {pert_seeds}), {args.resolution}^2, the {args.profile} profile's sizes, "
          f"epochs {info['epochs']}; means over seeds and groups; thr/prc = worst move of a student seed-mean "
          f"(method x group) under 1 thread / the other precision; 1s = worst range over perturbations of one "
          f"seed; sd = median seed sd; target judged on the perturbations the recipe is exposed to")
    print_recipe_table(rows)
    info["wall_seconds"] = time.perf_counter() - t0
    out = {"info": {**info, "seeds": args.seeds, "pert_seeds": pert_seeds, "recipes": args.recipes},
           "table": rows, "summary": summary}
    Path(args.out).write_text(json.dumps(out, indent=1))
    if args.noise_floor:
        first = args.recipes[0]  # its recipe's tau rule (a screening candidate: that of the recipe it extends)
        base_recipe = first if first in RECIPES else CANDIDATES[first].get("recipe", PAPER_RECIPE)
        rule = RECIPES[base_recipe]["calibrate"]["tau_rule"]
        keep = {k: v for k, v in out["info"].items() if k not in ("artifacts", "wall_seconds", "n_train")}
        host = cpu()  # where the floor was measured: the report names it (another CPU has other kernels)
        keep.update(recipe=first, tau_rule=rule, cpu=host["model"], cpu_flags=host["flags"])
        key = noise_floor_key(first, args.profile, args.resolution)
        write_noise_floor(args.noise_floor, key, noise_floor_record(summary[f"{first}|{rule}"], keep, exposure[first]))
        print(f"wrote {args.noise_floor} (record {key})")
    print(f"wrote {args.out}")
    return out


if __name__ == "__main__":
    main()
