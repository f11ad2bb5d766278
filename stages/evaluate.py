"""Stage evaluate: per-image metrics of every student on every test group, seed summaries and gains.

* thresholds: the validation-calibrated tau of each (method, seed), applied unchanged, and the fixed
  tau (``calibrate.fixed_tau`` recorded in thresholds.parquet, 0.5) -- ``threshold_mode`` =
  calibrated | fixed;
* ``metrics.parquet``: one row per (group, method, seed, image, threshold_mode) with Image IoU,
  Boundary F1 (evaluate.bf1_tolerance px), precision, recall, predicted area ratio and small-region
  IoU (pipeline.metrics);
* per image also ``target_fraction`` (reference foreground / frame), ``target_size`` (``tiny`` under
  evaluate.tiny_target_max_fraction = 0.2 % of the frame, ``regular``, ``empty``;
  pipeline.diagnostics) and ``area_vs_reference`` (predicted / reference foreground area; NaN for an
  empty reference) -- the size split and the foreground-inflation diagnostics;
* ``summary.parquet``: mean and sample std over seeds of the per-seed means, plus the gain of each
  annotation-free method over ``plain`` with a paired hierarchical bootstrap CI (spacecraft, then
  images; evaluate.bootstrap_resamples, evaluate.ci, seeded by evaluate.bootstrap_seed), and of each
  warm-started Stage-II method over the budget-matched ``continuation`` (``gain_<m>_vs_continuation``
  columns; pipeline.methods.gain_treatments).  The supervised ceiling (NOT annotation-free) gets
  means only: it is never in a gain or its CI;
* DVC results (git-tracked; pipeline.dvc_results): ``reports/metrics/students/<group>/<method>.json`` (iou,
  bf1 at the calibrated tau: ``dvc metrics show``), ``reports/plots/training_curves.csv`` (every run's log) and
  ``reports/plots/threshold_curves.csv`` (calibrate's curves), drawn one line per method by ``dvc plots``.

Reference masks are used here only to score predictions.
"""

from __future__ import annotations


import click
import numpy as np
import pandas as pd

from pipeline.catalog import ARTIFACTS_DIR, dvc_path
from pipeline import catalog
from pipeline.params import section
from stages._common import stage_command, stage_context

GAIN_METRICS = ("iou", "bf1", "precision", "recall")
CHUNK = 64  # test images predicted and scored per batch (bounded memory for large test sets)
#: the reference masks' scoring geometry (pipeline.metrics.ScoringReference, ~5 bytes a pixel) is built
#: once and reused by every run while the test set has at most this many pixels, else once per run
REFERENCE_CACHE_PIXELS = 1 << 26


def run_thresholds(thresholds: pd.DataFrame, method: str, seed: int, path) -> tuple[float, float]:
    """(calibrated tau, fixed tau) of one run; ArtifactError when calibrate did not see the run."""
    from pipeline.errors import ArtifactError

    row = thresholds[(thresholds["method"] == method) & (thresholds["seed"] == seed)]
    if len(row) != 1:
        raise ArtifactError(f"{path}: no calibrated threshold for {method}/{seed} in thresholds.parquet; "
                            f"rerun calibrate")
    return float(row["tau"].iloc[0]), float(row["fixed_tau"].iloc[0])


def control_gains(metrics: pd.DataFrame, control: str, n_boot: int, ci: float, seed: int) -> pd.DataFrame:
    """Gains over ``control`` (pipeline.stats.method_gains, paired hierarchical bootstrap) of the
    methods :func:`pipeline.methods.gain_treatments` compares with it -- never the supervised ceiling."""
    from pipeline.methods import gain_treatments
    from pipeline.stats import method_gains

    keep = [*gain_treatments(control, metrics["method"].unique()), control]
    return method_gains(metrics[metrics["method"].isin(keep)], GAIN_METRICS, control=control,
                        by=["dataset", "group", "threshold_mode"], n_resamples=n_boot, ci=ci, seed=seed)


def vs_column(column: str, control: str) -> str:
    """Summary column name of a gain over a control other than plain: ``gain_iou_lo`` ->
    ``gain_iou_vs_continuation_lo``, ``gain_seeds`` -> ``gain_seeds_vs_continuation``."""
    for end in ("_lo", "_hi"):
        if column.endswith(end):
            return f"{column.removesuffix(end)}_vs_{control}{end}"
    return f"{column}_vs_{control}"


def write_dvc_results(metrics_dir, training_curves_csv, threshold_curves_csv, summary: pd.DataFrame,
                      thresholds: pd.DataFrame, runs) -> None:
    """The DVC metrics files and plot tables (pipeline.dvc_results) of this evaluation: ``runs`` are
    the evaluated (method, seed, checkpoint path) triples, whose training logs the curves show."""
    from pipeline.artifacts import open_artifact
    from pipeline.dvc_results import (student_metric_files, threshold_curves, training_curves, write_csv,
                                      write_metrics_dir)

    write_metrics_dir(metrics_dir, student_metric_files(summary))
    write_csv(training_curves_csv, training_curves(
        (m, s, open_artifact(p, "checkpoint").table("log.parquet")) for m, s, p in runs))
    write_csv(threshold_curves_csv, threshold_curves(thresholds))


@stage_command("evaluate")
@click.option("--artifacts", "art", default=ARTIFACTS_DIR, show_default=True, type=click.Path(file_okay=False))
@click.option("--checkpoints", default=dvc_path("checkpoints"), show_default=True, type=click.Path(file_okay=False))
@click.option("--thresholds", default=dvc_path("thresholds"), show_default=True, type=click.Path(dir_okay=False))
@click.option("--out", default=dvc_path("metrics"), show_default=True, type=click.Path(dir_okay=False))
@click.option("--summary", "summary_out", default=dvc_path("summary"), show_default=True,
              type=click.Path(dir_okay=False))
@click.option("--metrics-dir", default=None, type=click.Path(file_okay=False),
              help="DVC metrics <group>/<method>.json, replaced [default: reports/metrics/students beside --artifacts]")
@click.option("--training-curves", default=None, type=click.Path(dir_okay=False),
              help="DVC plot table of the runs' training logs [default: reports/plots/training_curves.csv beside --artifacts]")
@click.option("--threshold-curves", default=None, type=click.Path(dir_okay=False),
              help="DVC plot table of the calibration curves [default: reports/plots/threshold_curves.csv beside --artifacts]")
def main(params, device, art, checkpoints, thresholds, out, summary_out, metrics_dir, training_curves,
         threshold_curves):
    """Score every student on every test group; write per-image metrics, summaries with bootstrap CIs."""
    from pipeline.artifacts import open_artifact, read_chunk_rows, write_parquet
    from pipeline.diagnostics import target_fractions, target_size_class
    from pipeline.device import resolve_device
    from pipeline.inference import active_runs, load_student, open_labelled_split, predict_probs
    from pipeline.metrics import score_masks, scoring_reference
    from pipeline.progress import progress
    from pipeline.stats import seed_summary
    from pipeline.thresholds import mask_from_probs

    cfg = section(params, "evaluate")
    tol, small_frac = cfg["bf1_tolerance"], cfg["small_region_max_fraction"]
    tiny_frac = cfg["tiny_target_max_fraction"]
    n_boot, boot_seed, ci = cfg["bootstrap_resamples"], cfg["bootstrap_seed"], cfg["ci"]

    manifest, images, reference, test = open_labelled_split(art, "test", "nothing to evaluate")
    thr = open_artifact(thresholds, "thresholds")
    mdf = manifest.df
    runs = active_runs(checkpoints, "evaluate")

    dev = resolve_device(device)
    info = mdf.iloc[test][["image_id", "dataset", "domain", "group", "spacecraft"]].reset_index(drop=True)
    frames, inputs = [], [manifest, images, reference, thr]
    refs = {}  # chunk start -> (target fractions, ScoringReference) of its test masks

    def chunk_reference(s: int, idx):
        """The chunk's reference side: read and prepared once, reused by every run when it fits."""
        if s in refs:
            return refs[s]
        gts = read_chunk_rows(reference["mask"], idx).astype(bool)
        entry = target_fractions(gts), scoring_reference(gts, tol, max_fraction=small_frac)
        if test.size * gts[0].size <= REFERENCE_CACHE_PIXELS:
            refs[s] = entry
        return entry

    for method, seed, path in progress(runs, desc="evaluate"):
        tau_cal, tau_fixed = run_thresholds(thr.df, method, seed, path)
        model, _ = load_student(path, dev)
        inputs.append(open_artifact(path))
        for s in range(0, test.size, CHUNK):
            idx = test[s:s + CHUNK]
            probs = predict_probs(model, read_chunk_rows(images["image"], idx), device=dev)
            target, ref = chunk_reference(s, idx)
            for mode, tau in (("calibrated", tau_cal), ("fixed", tau_fixed)):
                scores = score_masks(mask_from_probs(probs, tau), ref)
                part = info.iloc[s:s + len(idx)].copy()
                part["method"], part["seed"], part["threshold_mode"], part["tau"] = method, int(seed), mode, tau
                for k, v in scores.items():
                    part[k] = v
                part["target_fraction"], part["target_size"] = target, target_size_class(target, tiny_frac)
                with np.errstate(invalid="ignore", divide="ignore"):
                    part["area_vs_reference"] = np.where(target > 0, scores["area_ratio"] / np.maximum(target, 1e-300),
                                                         np.nan)
                frames.append(part)
    metrics = pd.concat(frames, ignore_index=True)
    order = ["dataset", "domain", "group", "spacecraft", "method", "seed", "image_id", "threshold_mode", "tau"]
    metrics = metrics[order + [c for c in metrics.columns if c not in order]]

    by = ["dataset", "group", "method", "threshold_mode"]
    summary = seed_summary(metrics, by, ["iou", "bf1", "precision", "recall", "area_ratio", "small_iou",
                                         "area_vs_reference"])
    summary = summary.merge(control_gains(metrics, "plain", n_boot, ci, boot_seed), on=by, how="left")
    if "continuation" in set(metrics["method"]):
        vs = control_gains(metrics, "continuation", n_boot, ci, boot_seed)
        vs = vs.rename(columns={c: vs_column(c, "continuation") for c in vs.columns if c not in by})
        summary = summary.merge(vs, on=by, how="left")

    ctx = stage_context("evaluate", __file__, params)
    write_parquet(out, metrics, ctx.meta("metrics", inputs))
    mmeta = open_artifact(out, "metrics")
    write_parquet(summary_out, summary, ctx.meta("summary", [mmeta],
                                                 control="plain", ci=ci, bootstrap_resamples=n_boot))
    write_dvc_results(metrics_dir or catalog.path("metrics_students", art),
                      training_curves or catalog.path("plot_training_curves", art),
                      threshold_curves or catalog.path("plot_threshold_curves", art), summary, thr.df, runs)
    click.echo(f"evaluate: {len(runs)} runs x {test.size} test images -> {out}, {summary_out}", err=True)


if __name__ == "__main__":
    main()
