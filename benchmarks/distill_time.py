"""`distill` at the same wall time (issue 63 item 5): today's `distill` settings against the new ones, each given the
Stage-I step budget that ``--time`` converts on this host, paired over seeds.

The images are the synthetic benchmark's (``--profile`` at ``--resolution``), given to ``geodistill distill`` as a
user gives them: a folder of PNGs, the teacher's answers as ``--backend imported`` (the answers of the benchmark's
teacher SIMULATOR, exported from its ``teacher.zarr`` in the layout of docs/real-data.md) and the validation and
test images' reference masks as ``--val-masks`` (distill splits them into validation and test images itself).

1. ``export``: the folders above, from the profile's artifacts (built in ``--workdir`` unless given).
2. ``probe``: per setting, ``geodistill distill --time T --no-run``: the step budget that this host's probe converts
   (quiet cores, ``--threads`` threads: what a user's run gets).
3. ``run``: per setting and seed, ``geodistill distill`` with that step budget fixed (``--jobs`` at a time, one
   thread each: the steps, not the wall time, decide the result), and its wall seconds per stage.  A budget at or
   above Stage I's epoch cap never binds (:func:`cap_steps`): such a run is the same at every ``--time`` and is
   shared between them (:func:`project_name`).
4. The deployed student's test Image IoU per image (the report's ``metrics_per_image``), paired by seed and image:
   new - today with the seed-aware t interval (:func:`pipeline.stats.paired_seed_image_t`) and the signed verdict
   (:func:`pipeline.stats.claim_status`).

    python -m benchmarks.distill_time --time 10m --seeds 42 43 44 --workdir W --out reports/distill_time/x.json

Finished runs are kept in ``--workdir``: a rerun runs only what is missing (distill itself resumes a killed run).
"""

from __future__ import annotations

import datetime
import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import yaml

from benchmarks import bench_distill
from benchmarks.common import host_record, parser
from benchmarks.study_recipe import build_artifacts
from pipeline import catalog
from pipeline.artifacts.atomic import png_bytes, write_text_if_changed
from pipeline.artifacts.store import open_artifact
from pipeline.profiles import load_profile
from pipeline.stats import claim_status, paired_seed_image_t
from pipeline.training.budget import training_images
from pipeline.training.inputs import read_rows
from pipeline.training.schedule import steps_per_epoch

#: setting -> the ``--set`` items that make it, over the `distill` profile. ``today``: distill before issue 63
#: (fp32 with channels_last, the issue's "1.27x"; its epochs cap never moves); ``new``: the distill profile as it
#: ships (bf16 autocast where the CPU has bf16 units, channels_last; a ``--time`` that allows more raises the
#: epochs cap, :func:`pipeline.training.budget.raised_cap`)
SETTINGS: dict[str, list[str]] = {"today": ["train.precision=fp32", "train.time_cap_factor=1"], "new": []}
#: the deployed student, whose test Image IoU is compared
DEPLOYED = "geodistill"


# ----------------------------------------------------------------------------------------------- export


def export_inputs(artifacts: Path, dest: Path, prompts: Sequence[str]) -> dict[str, Path]:
    """Write ``images/``, ``masks/`` (the validation and test images' reference masks) and ``imported/`` (the teacher
    SIMULATOR's answers: ``scores.parquet`` and ``masks/<image_id>/<prompt_index>.png``, docs/real-data.md) under
    ``dest`` from the prepared arrays, unless ``dest/export.json`` says they are complete.  ``prompts`` are the
    teacher's, in the order of ``teacher.zarr``'s prompt axis."""
    import pandas as pd

    folders = {n: dest / n for n in ("images", "masks", "imported")}
    if (dest / "export.json").is_file():
        return folders
    manifest = open_artifact(catalog.path("manifest", artifacts), "manifest").df
    rows = np.arange(len(manifest))
    images = read_rows(open_artifact(catalog.path("images", artifacts), "images"), "image", rows)
    reference = open_artifact(catalog.path("reference", artifacts), "reference")
    gt, has_mask = read_rows(reference, "mask", rows), read_rows(reference, "has_mask", rows)
    teacher = open_artifact(catalog.path("teacher", artifacts), "teacher")
    masks, scores = read_rows(teacher, "masks", rows), read_rows(teacher, "scores", rows)  # [N, P, H, W], [N, P]
    if masks.shape[1] != len(prompts):
        raise SystemExit(f"distill_time: {masks.shape[1]} teacher prompts in the artifacts, {len(prompts)} in params")
    for f in folders.values():
        f.mkdir(parents=True, exist_ok=True)
    table = []
    for i, (iid, split) in enumerate(zip(manifest["image_id"], manifest["split"])):
        (folders["images"] / f"{iid}.png").write_bytes(png_bytes(images[i]))
        if split != "train" and has_mask[i]:  # never a training image's: distill would not train on it
            (folders["masks"] / f"{iid}.png").write_bytes(png_bytes(gt[i].astype(np.uint8) * 255))
        out = folders["imported"] / "masks" / iid
        out.mkdir(parents=True, exist_ok=True)
        for k, prompt in enumerate(prompts):
            (out / f"{k}.png").write_bytes(png_bytes(masks[i, k].astype(np.uint8) * 255))
            table.append({"image_id": iid, "prompt_index": k, "prompt": prompt, "score": float(scores[i, k])})
    pd.DataFrame(table).to_parquet(folders["imported"] / "scores.parquet", index=False)
    write_text_if_changed(dest / "export.json", json.dumps({"artifacts": str(artifacts), "images": len(rows)}))
    return folders


# ----------------------------------------------------------------------------------------------- distill


def distill_argv(folders: Mapping[str, Path], out: Path, sets: Sequence[str], extra: Sequence[str] = ()) -> list[str]:
    """The ``geodistill distill`` command of one run (:func:`benchmarks.bench_distill.distill_argv`)."""
    teacher = ["--val-masks", str(folders["masks"]), "--backend", "imported", "--imported-dir",
               str(folders["imported"]), "--device", "cpu", "--no-benchmark", "--quiet", *extra]
    return bench_distill.distill_argv(str(folders["images"]), out, teacher, sets)


def step_budget(project: Path) -> tuple[int, int]:
    """(``train.step_budget``, ``train.epochs_stage1``) that ``--time`` wrote into ``project``'s params.yaml (the
    epochs cap, raised where the time allows more)."""
    train = yaml.safe_load((project / catalog.PARAMS_FILE).read_text())["train"]
    return int(train["step_budget"]), int(train["epochs_stage1"])


def probe(folders: Mapping[str, Path], work: Path, setting: str, budget: str, sets: Sequence[str],
          threads: int) -> tuple[int, int]:
    """(step budget, epochs cap) that ``--time budget`` converts for ``setting`` (a ``--no-run`` project in
    ``work``)."""
    project = work / f"probe-{setting}-{budget}"
    if not (project / catalog.PARAMS_FILE).is_file():
        bench_distill.run_command(distill_argv(folders, project, [*sets, *SETTINGS[setting],
                                                              f"train.num_threads={threads}"], ["--time", budget, "--no-run"]))
    return step_budget(project)


def cap_steps(folders: Mapping[str, Path], setting: str, sets: Sequence[str], epochs: int | None = None) -> int:
    """Stage I's steps at its epoch cap (``epochs``, else ``train.epochs_stage1``, epochs of the training images):
    a step budget at or above it never binds, so the run is the same at every such ``--time``."""
    train = load_profile("distill", [*sets, *SETTINGS[setting]])["train"]
    n = training_images(folders["images"], folders["masks"], train["holdout_fraction"])
    return int(epochs or train["epochs_stage1"]) * steps_per_epoch(n, int(train["batch_size"]))


def project_name(setting: str, steps: int, cap: int, seed: int) -> str:
    """A run's folder: the setting, the steps its budget can bind (``cap`` when it cannot) and the seed, so that
    two ``--time`` values whose budgets both reach the cap share one run."""
    return f"{setting}-{min(steps, cap)}-s{seed}"


def run_sets(setting: str, seed: int, budget: str, steps: int, sets: Sequence[str], threads: int,
             epochs: int | None = None) -> list[str]:
    """The ``--set`` items of one run: the setting, its fixed step budget and epochs cap (what ``--time`` writes;
    ``epochs`` None: the profile's cap), the seed."""
    cap = [f"train.epochs_stage1={epochs}"] if epochs is not None else []
    return [*sets, *SETTINGS[setting], f"train.time_budget={budget}", f"train.step_budget={steps}", *cap,
            "train.until=plateau", f"train.num_threads={threads}", f"protocol.runs.plain=[{seed}]",
            f"protocol.runs.{DEPLOYED}=[{seed}]", f"deploy.export_seed={seed}"]


def run_record(project: Path, setting: str, seed: int, steps: int, wall: float | None) -> dict:
    """One finished run: per test image the deployed student's and Plain's Image IoU at the calibrated tau
    (``artifacts/metrics.parquet``), Stage I's steps and stop, and each stage's training seconds (the sum of its
    epochs' in the run's timings file)."""
    import pandas as pd

    art = project / catalog.ARTIFACTS_DIR
    m = pd.read_parquet(catalog.path("metrics", art))
    m = m[m["threshold_mode"] == "calibrated"].sort_values("image_id")
    ious = {meth: m[m["method"] == meth].set_index("image_id")["iou"] for meth in ("plain", DEPLOYED)}
    teacher = pd.read_parquet(catalog.path("teacher_metrics", art))
    vote = teacher[teacher["source"] == "vote"].set_index("image_id")["iou"]
    extra = json.loads((catalog.path("checkpoints", art) / "plain" / str(seed) / catalog.META_FILE).read_text())["extra"]

    def seconds(method: str) -> float:  # the run's epochs (the timings file: wall time stays out of the log)
        timings = json.loads(catalog.path("train_timings", art, method=method, seed=seed).read_text())
        return float(sum(e["seconds"] for e in timings["epochs"]))

    return {"setting": setting, "seed": seed, "step_budget": steps, "steps_run": int(extra["steps_run"]),
            "epochs": int(extra["epochs"]), "stopped": extra["stopped"], "autocast": extra.get("autocast"),
            "stage1_seconds": seconds("plain"), "stage2_seconds": seconds(DEPLOYED), "wall_seconds": wall,
            "image_ids": list(ious[DEPLOYED].index), "image_ious": ious[DEPLOYED].tolist(),
            "plain_image_ious": ious["plain"].reindex(ious[DEPLOYED].index).tolist(),
            "vote_image_ious": vote.reindex(ious[DEPLOYED].index).tolist()}


def comparison(runs: Sequence[Mapping[str, Any]], clusters: Mapping[str, str], groups: Mapping[str, str],
               key: str = "image_ious", ci: float = 0.95, control: tuple[str, str] | None = None) -> list[dict]:
    """new - today per test group and over every test image (``all``), paired by seed and image: the seed-aware t
    interval (:func:`pipeline.stats.paired_seed_image_t`, clusters = spacecraft) and the signed verdict (no noise
    floor exists for this configuration, so the interval alone decides).  ``control`` = (setting, key) compares
    ``key`` of the ``new`` runs with that instead (the vote: ``("new", "vote_image_ious")``)."""
    setting, ckey = control or ("today", key)
    by = {(r["setting"], r["seed"]): r for r in runs}
    seeds = sorted(s for (w, s) in by if w == "new" and (setting, s) in by)
    if not seeds:
        return []
    ids = by[("new", seeds[0])]["image_ids"]
    for s in seeds:
        if by[("new", s)]["image_ids"] != ids or by[(setting, s)]["image_ids"] != ids:
            raise SystemExit("distill_time: the runs scored different test images; they cannot be paired")
    g = np.array([groups[i] for i in ids])
    sc = np.array([clusters[i] for i in ids])
    out = []
    for name in [*dict.fromkeys(g.tolist()), "all"]:
        sel = np.ones(len(ids), bool) if name == "all" else g == name
        t = np.stack([np.asarray(by[("new", s)][key])[sel] for s in seeds])
        c = np.stack([np.asarray(by[(setting, s)][ckey])[sel] for s in seeds])
        iv = paired_seed_image_t(t, c, sc[sel], ci)
        gain = float(np.mean(t - c))
        out.append({"group": name, "seeds": seeds, "images": int(sel.sum()), "control": float(c.mean()),
                    "new": float(t.mean()), "ratio": float(t.mean() / c.mean()) if c.mean() > 0 else None,
                    "gain": gain, "low": float(iv.low), "high": float(iv.high),
                    "verdict": claim_status(gain, float(iv.low), float(iv.high), None, n_seeds=len(seeds))})
    return out


def table(doc: Mapping[str, Any]) -> str:
    """Markdown: the runs, then new - today per group for the deployed student and for Plain."""
    lines = ["| setting | seed | step budget | steps run | epochs | stopped | Stage I s | Stage II s | "
             f"{DEPLOYED} test IoU | Plain test IoU |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in doc["runs"]:
        lines.append(f"| {r['setting']} | {r['seed']} | {r['step_budget']:,} | {r['steps_run']:,} | {r['epochs']} | "
                     f"{r['stopped']} | {r['stage1_seconds']:.0f} | {r['stage2_seconds']:.0f} | "
                     f"{np.mean(r['image_ious']):.3f} | {np.mean(r['plain_image_ious']):.3f} |")
    for title, control, rows in (
            (f"new - today, the deployed student ({DEPLOYED})", "today", doc["gain"]),
            ("new - today, Plain (Stage I)", "today", doc["plain_gain"]),
            (f"the deployed student ({DEPLOYED}, new settings) - the teacher's vote", "vote", doc["vote_gain"]),
            ("Plain (new settings) - the teacher's vote", "vote", doc["plain_vote_gain"])):
        lines += ["", f"{title}:", "", f"| group | seeds | images | {control} | new | new / {control} | "
                  "gain [95 % CI] | verdict |", "|---|---|---|---|---|---|---|---|"]
        lines += [f"| {r['group']} | {len(r['seeds'])} | {r['images']} | {r['control']:.3f} | {r['new']:.3f} | "
                  f"{r['ratio']:.2f} | {r['gain']:+.3f} [{r['low']:+.3f}, {r['high']:+.3f}] | {r['verdict']} |"
                  for r in rows]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> dict:
    ap = parser(__doc__, artifacts=None, workdir="distill-time-work", profile="reduced", resolution=128, set=[],
                seeds=[42, 43, 44], jobs=2, threads=2, out="distill_time.json")
    ap.add_argument("--time", default="10m", help="the --time each setting's step budget is converted from")
    ap.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    args = ap.parse_args(argv)
    work = Path(args.workdir).resolve()
    sets = [f"data.resolution={args.resolution}", *args.sets]
    artifacts = Path(args.artifacts) if args.artifacts else build_artifacts(
        work / "data", args.profile, [f"data.resolution={args.resolution}"], "cpu")
    folders = export_inputs(artifacts, work / "inputs", load_profile("distill", sets)["teacher"]["prompts"])
    manifest = open_artifact(catalog.path("manifest", artifacts), "manifest").df
    clusters = dict(zip(manifest["image_id"], manifest["spacecraft"].astype(str)))
    groups = dict(zip(manifest["image_id"], manifest["group"].astype(str)))
    # the probes first, one at a time on the whole machine (``--threads``): the budgets a user's run gets
    probed = {s: probe(folders, work, s, args.time, sets, args.threads) for s in args.settings}
    budgets, epochs = {s: b for s, (b, _) in probed.items()}, {s: e for s, (_, e) in probed.items()}
    print("distill_time: step budgets for --time " + args.time + ": "
          + ", ".join(f"{s} {n:,} ({epochs[s]} epochs cap)" for s, n in budgets.items()), flush=True)
    caps = {s: cap_steps(folders, s, sets, epochs[s]) for s in args.settings}
    default_cap = {s: int(load_profile("distill", [*sets, *SETTINGS[s]])["train"]["epochs_stage1"])
                   for s in args.settings}
    jobs = [(s, seed) for seed in args.seeds for s in args.settings]
    walls: dict[tuple[str, int], float | None] = {}

    def one(job):
        s, seed = job
        project = work / project_name(s, budgets[s], caps[s], seed)
        done = (project / catalog.ARTIFACTS_DIR / "metrics.parquet").is_file()
        walls[job] = None if done else bench_distill.run_command(distill_argv(
            folders, project, run_sets(s, seed, args.time, budgets[s], sets, max(1, args.threads // args.jobs),
                                       epochs[s] if epochs[s] != default_cap[s] else None)))
        print(f"  done {s} s{seed} ({walls[job] or 0:.0f} s)", flush=True)

    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        list(pool.map(one, jobs))
    runs = [run_record(work / project_name(s, budgets[s], caps[s], seed), s, seed, budgets[s], walls[(s, seed)])
            for s, seed in jobs]
    doc = {"date": datetime.date.today().isoformat(), "host": host_record(),
           "time": args.time, "resolution": args.resolution, "profile": args.profile, "sets": sets,
           "settings": {s: SETTINGS[s] for s in args.settings}, "budgets": budgets, "epochs_caps": epochs,
           "cap_steps": caps, "runs": runs,
           "gain": comparison(runs, clusters, groups),
           "plain_gain": comparison(runs, clusters, groups, key="plain_image_ious"),
           "vote_gain": comparison(runs, clusters, groups, control=("new", "vote_image_ious")),
           "plain_vote_gain": comparison(runs, clusters, groups, key="plain_image_ious",
                                         control=("new", "vote_image_ious")),
           "teacher": "the synthetic benchmark's SIMULATOR (imported answers)"}
    out = Path(args.out)
    write_text_if_changed(out, json.dumps(doc, indent=1))
    write_text_if_changed(out.with_suffix(".md"), table(doc) + "\n")
    print(table(doc))
    return doc


if __name__ == "__main__":
    main()
