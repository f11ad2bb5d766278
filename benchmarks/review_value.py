"""What a person's corrections buy: the reference masks of the k top-ranked training images replace their votes
(``review.mode: replace``; NOT annotation-free); the Stage-I student's test Image IoU for the shipped ranking, the
lowest gate first and random selections, each one's seed-aware gain over k = 0 and the ranking minus random (the
simulated teacher builds its bad masks from the gate's factors: a gate-based ranking wins partly by construction).

    python -m benchmarks.review_value --resolution 64 --seeds 42 43 44 [--runs seed42.json ... --figure curve.png]
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipeline import catalog
from pipeline.artifacts.store import open_artifact
from benchmarks.common import parser
from benchmarks.study_recipe import build_artifacts, score_run
from pipeline.evaluation.inference import load_student, open_labelled_split, predict_probs
from pipeline.methods import STAGE_ONE, get_method
from pipeline.metrics import image_ious
from pipeline.params import load_params, section
from pipeline.consensus import agreement_entropy
from pipeline.review.ranking import DEFAULT_RANKING, scores
from pipeline.stats import paired_seed_image_t
from pipeline.thresholds import mask_from_probs
from pipeline.training.inputs import read_rows, load_inputs, replace_targets
from pipeline.training.checkpointing import NoCheckpointer

CAVEAT = ("on this benchmark the simulated teacher builds its bad masks from the gate's own factors "
          "(pipeline/teachers/simulated.py): a gate-based ranking (gate, and combined through g) wins partly by "
          "construction")
SELECTIONS = (DEFAULT_RANKING, "gate", "random")


def training_table(artifacts: Path, train_ids: list[str]):
    """The training images' ``image_id, g, h`` (the columns the rankings read), in ``train_ids`` order."""
    import pandas as pd

    manifest = open_artifact(catalog.path("manifest", artifacts), "manifest")
    gates = open_artifact(catalog.path("gates", artifacts), "gates").df.set_index("image_id")
    consensus = open_artifact(catalog.path("consensus", artifacts), "consensus")
    row = {iid: i for i, iid in enumerate(manifest.df["image_id"].astype(str))}
    h = agreement_entropy(np.asarray(consensus["agreement"])[[row[i] for i in train_ids]])
    return pd.DataFrame({"image_id": train_ids, "g": gates.loc[train_ids, "g"].to_numpy(np.float64), "h": h})


def select(table, how: str, k: int, rng: np.random.Generator) -> list[str]:
    """The ``k`` training images a person corrects under selection ``how`` (:data:`SELECTIONS`)."""
    if k == 0:
        return []
    if how == "random":
        return list(rng.choice(table["image_id"].to_numpy(), size=k, replace=False))
    order = np.lexsort((table["image_id"].to_numpy(), -scores(table, how)))  # rank(): score desc, then id
    return list(table["image_id"].to_numpy()[order[:k]])


def run_study(artifacts: Path, cfg: dict, ks, seeds, draws: int, device: str = "cpu", selections=SELECTIONS,
              done=lambda runs: None, k0_checkpoints: Path | None = None) -> list[dict]:
    """Every (selection, k, seed[, draw]) run: its test IoUs per image (Stage I on replaced targets).

    ``done(runs)`` is called after each run, so a long study can keep what it has finished.
    ``k0_checkpoints``: score k = 0 from the Plain Student checkpoints ``<dir>/<seed>`` (a DAG run on the same
    data and params: the same training) instead of training it again.
    """
    from pipeline.training import loop as training

    method = get_method(STAGE_ONE)
    data, val, _ = load_inputs(artifacts, method, cfg)
    manifest, images, reference, test = open_labelled_split(artifacts, "test", "nothing to score", allow_empty=True)
    row = {iid: i for i, iid in enumerate(manifest.df["image_id"].astype(str))}
    test_images, test_masks = read_rows(images, "image", test), read_rows(reference, "mask", test).astype(bool)
    table = training_table(artifacts, list(data.image_ids))
    groups = manifest.df["spacecraft"].astype(str).to_numpy()[test]
    plan = [(seed, k, how, d) for seed in seeds for k in ks for how in (selections if k else ("none",))
            for d in range(draws if how == "random" else 1)]
    runs = []
    for seed, k, how, d in plan:
        chosen = select(table, how, k, np.random.default_rng([seed, k, d]))
        truth = {i: read_rows(reference, "mask", np.array([row[i]]))[0].astype(bool) for i in chosen}
        if not chosen and k0_checkpoints is not None:
            model = load_student(Path(k0_checkpoints) / str(seed), device)[0]
        else:
            model = training.train(method, cfg, replace_targets(data, truth) if chosen else data, val, seed,
                                   checkpointer=NoCheckpointer(), device=device, show_progress=False).model
        tau = score_run(model, val, test_images, test_masks, device)["tau_cal"]
        ious = image_ious(mask_from_probs(predict_probs(model, test_images, device=device, precision="fp32"), tau),
                          test_masks)
        runs.append({"selection": how, "k": k, "seed": seed, "draw": d, "iou": float(ious.mean()),
                     "ious": [float(v) for v in ious], "groups": list(groups)})
        print(f"  {how:9s} k={k:3d} seed {seed} draw {d}: test IoU {ious.mean():.4f}", flush=True)
        done(runs)
    return runs


def selected_label_quality(artifacts: Path, cfg: dict, ks, seeds, draws: int, selections=SELECTIONS) -> list[dict]:
    """Mean voted-mask Image IoU against the reference: the whole training set, then each (selection, k > 0)'s picks."""
    data, _, _ = load_inputs(artifacts, get_method(STAGE_ONE), cfg)
    ids = list(data.image_ids)
    manifest = open_artifact(catalog.path("manifest", artifacts), "manifest")
    consensus = open_artifact(catalog.path("consensus", artifacts), "consensus")
    reference = open_artifact(catalog.path("reference", artifacts), "reference")
    row = {iid: i for i, iid in enumerate(manifest.df["image_id"].astype(str))}
    rows = np.array([row[i] for i in ids])
    iou = dict(zip(ids, image_ious(read_rows(consensus, "voted", rows).astype(bool),
                                   read_rows(reference, "mask", rows).astype(bool))))
    table = training_table(artifacts, ids)
    out = [{"selection": "all", "k": len(ids), "voted_iou": float(np.mean(list(iou.values())))}]
    for k in (k for k in ks if k):
        for how in selections:
            picks = [select(table, how, k, np.random.default_rng([seed, k, d]))
                     for seed in seeds for d in range(draws if how == "random" else 1)]
            out.append({"selection": how, "k": k, "voted_iou": float(np.mean([[iou[i] for i in p] for p in picks]))})
    return out


def summarize(runs: list[dict], ks, seeds, selections=SELECTIONS) -> list[dict]:
    """Per (selection, k): mean test IoU over seeds and draws, the gain over k = 0 with its seed-aware interval,
    and for the rankings their difference from random."""
    def per_image(how, k):
        return np.asarray([np.mean([r["ious"] for r in runs if r["selection"] == how and r["k"] == k
                                    and r["seed"] == s], axis=0) for s in seeds])

    base = per_image("none", ks[0]) if ks and ks[0] == 0 else None
    groups = np.asarray(runs[0]["groups"])
    rows = []
    for k in ks:
        for how in (selections if k else ("none",)):
            x = per_image(how, k)
            row = {"selection": how, "k": k, "iou": float(x.mean())}
            if base is not None and k:
                row.update(_interval(paired_seed_image_t(x, base, groups), "gain", "low", "high"))
                if how != "random" and "random" in selections:
                    row.update(_interval(paired_seed_image_t(x, per_image("random", k), groups), "vs_random",
                                         "vs_random_low", "vs_random_high"))
            rows.append(row)
    return rows


def _interval(t, *names: str) -> dict[str, float]:
    return {n: float(np.ravel(v)[0]) for n, v in zip(names, (t.estimate, t.low, t.high))}


def print_table(rows: list[dict]) -> None:
    print(f"{'selection':10s} {'k':>4s} {'test IoU':>9s} {'gain vs k=0 [95% CI]':>28s} {'minus random [95% CI]':>28s}")
    for r in rows:
        gain = f"{r['gain']:+.4f} [{r['low']:+.4f}, {r['high']:+.4f}]" if "gain" in r else ""
        vs = f"{r['vs_random']:+.4f} [{r['vs_random_low']:+.4f}, {r['vs_random_high']:+.4f}]" if "vs_random" in r else ""
        print(f"{r['selection']:10s} {r['k']:4d} {r['iou']:9.4f} {gain:>28s} {vs:>28s}")
    print(f"NOTE: {CAVEAT}.  Corrected students are NOT annotation-free (human masks in the loss).")


#: what the figure calls each selection
SELECTION_TEXT = {DEFAULT_RANKING: f"shipped ranking ({DEFAULT_RANKING})", "gate": "lowest gate g first",
                  "random": "random"}


def curve_figure(rows: list[dict], title: str):
    """Test Image IoU against the images corrected, a line per selection, its gain's 95 % interval as a band."""
    from pipeline.report import figures as F  # matplotlib: figures only

    base = next(r["iou"] for r in rows if r["k"] == 0)
    series, bands = [], []
    for how, color in zip(SELECTIONS, F.PALETTE):
        part = [r for r in rows if r["selection"] == how]
        if not part:  # a selection the study did not train (--selections)
            continue
        x = [0] + [r["k"] for r in part]
        series.append({"x": x, "y": [base] + [r["iou"] for r in part], "label": SELECTION_TEXT[how], "color": color,
                       "key": how, "symbol": "o"})
        bands.append((x, [base] + [base + r["low"] for r in part], [base] + [base + r["high"] for r in part], color))
    fig = F.line_plot(series, title, "training images corrected (k)", "test Image IoU (Stage I)")
    ax = fig.axes[0]
    for x, lo, hi, color in bands:
        ax.fill_between(x, lo, hi, color=tuple(c / 255 for c in color), alpha=0.12, linewidth=0)
    ax.set_xticks(sorted({r["k"] for r in rows}))
    return fig


def main(argv=None) -> list[dict]:
    ap = parser(__doc__, profile="paper", resolution=64, seeds=[42, 43, 44], epochs=None, set=[], device="cpu")
    ap.add_argument("--workdir", type=Path, default=Path(".cache/review_value"))
    ap.add_argument("--ks", type=int, nargs="+", default=[0, 10, 25, 50])
    ap.add_argument("--draws", type=int, default=3, help="random selections per (k, seed)")
    ap.add_argument("--selections", nargs="+", choices=SELECTIONS, default=list(SELECTIONS),
                    help="the selections to train (each k > 0 trains one run per selection, seed and draw)")
    ap.add_argument("--out", type=Path, default=None, help="write the runs and the table as JSON")
    ap.add_argument("--runs", type=Path, nargs="+", default=None, metavar="JSON",
                    help="summarize the runs of earlier --out files (e.g. one per seed) instead of training "
                         "(--workdir and the data options must be theirs)")
    ap.add_argument("--figure", type=Path, default=None, help="write the curve as a PNG")
    ap.add_argument("--k0-checkpoints", type=Path, default=None, metavar="DIR",
                    help="score k = 0 from the Plain Student checkpoints DIR/<seed> (e.g. a DAG run's "
                         "artifacts/checkpoints/plain on the same data and params) instead of training it")
    args = ap.parse_args(argv)
    sets = [f"data.resolution={args.resolution}", *args.sets]
    art = args.workdir / "artifacts"
    if not args.runs:  # the runs of --runs need no data; their label quality reads it where it is
        art = build_artifacts(args.workdir, args.profile, sets, args.device, geometry=True)
    cfg = section(load_params(args.workdir / "params.yaml", sets), "train") if art.is_dir() else None
    if cfg is not None and args.epochs is not None:
        cfg["epochs_stage1"] = args.epochs
    if args.runs:
        runs = [r for f in args.runs for r in json.loads(f.read_text())["runs"]]
        ks, seeds = sorted({r["k"] for r in runs}), sorted({r["seed"] for r in runs})
        draws = 1 + max(r["draw"] for r in runs)
        selections = tuple(h for h in SELECTIONS if any(r["selection"] == h for r in runs))
    else:
        ks, seeds, draws, selections = sorted(set(args.ks)), args.seeds, args.draws, tuple(args.selections)
        partial = (lambda done: args.out.write_text(json.dumps({"runs": done, "partial": True}, indent=1))
                   ) if args.out is not None else (lambda done: None)
        runs = run_study(art, cfg, ks, seeds, draws, args.device, selections, partial, args.k0_checkpoints)
    rows = summarize(runs, ks, seeds, selections)
    print_table(rows)
    quality = selected_label_quality(art, cfg, ks, seeds, draws, selections) if cfg is not None else []
    if quality:
        print("voted-mask Image IoU (against the reference) of the images each selection corrects:")
    for q in quality:
        print(f"  {q['selection']:9s} k={q['k']:3d}: {q['voted_iou']:.4f}")
    if args.out is not None:
        args.out.write_text(json.dumps({"runs": runs, "table": rows, "label_quality": quality, "caveat": CAVEAT},
                                       indent=1))
    if args.figure is not None:
        from pipeline.report import figures as F

        args.figure.write_bytes(F.png_bytes(curve_figure(
            rows, f"Plain Student after k corrections ({len(seeds)} seeds; bands: 95 % CI of the gain)")))
    return rows


if __name__ == "__main__":
    main()
