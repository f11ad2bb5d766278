"""Stage evaluate: per-image metrics of every student on every test group, seed summaries and gains.

* thresholds: the validation-calibrated tau of each (method, seed), applied unchanged, and the fixed
  tau (``calibrate.fixed_tau`` recorded in thresholds.parquet, 0.5) -- ``threshold_mode`` =
  calibrated | fixed;
* ``metrics.parquet``: one row per (group, method, seed, image, threshold_mode) with Image IoU,
  Boundary F1 (evaluate.bf1_tolerance px), precision, recall, predicted area ratio and small-region
  IoU (pipeline.metrics);
* per image also ``target_fraction`` (reference foreground / frame), ``target_size`` (``tiny`` under
  evaluate.tiny_target_max_fraction = 0.2 % of the frame, ``regular``, ``empty``;
  pipeline.evaluation.diagnostics) and ``area_vs_reference`` (predicted / reference foreground area; NaN for an
  empty reference) -- the size split and the foreground-inflation diagnostics;
* ``summary.parquet``: mean and sample std over seeds of the per-seed means, plus the gain of each
  annotation-free method over ``plain`` with a paired hierarchical bootstrap CI (spacecraft, then
  images; evaluate.bootstrap_resamples, evaluate.ci, seeded by evaluate.bootstrap_seed), and of each
  warm-started Stage-II method over the budget-matched ``continuation`` (``gain_<m>_vs_continuation``
  columns; pipeline.methods.gain_treatments).  The supervised ceiling (NOT annotation-free) gets
  means only: it is never in a gain or its CI (the rules: pipeline.evaluation.evaluate);
* DVC results (git-tracked; pipeline.report.dvc_results): ``reports/metrics/students/<group>/<method>.json`` (iou,
  bf1 at the calibrated tau: ``dvc metrics show``), ``reports/plots/training_curves.csv`` (every run's log) and
  ``reports/plots/threshold_curves.csv`` (calibrate's curves), drawn one line per method by ``dvc plots``.

Reference masks are used here only to score predictions.
"""

from __future__ import annotations

import click

from pipeline import catalog

from pipeline.report import dvc_results
from pipeline.artifacts.store import open_artifact, write_parquet
from pipeline.catalog import ARTIFACTS_DIR, dvc_path
from pipeline.runtime.device import resolve_device
from pipeline.evaluation.evaluate import score_runs, summarize
from pipeline.evaluation.inference import active_runs, open_labelled_split
from pipeline.methods import BASELINE
from pipeline.params import section
from stages._common import stage_command, stage_context


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
    cfg = section(params, "evaluate")
    n_boot, boot_seed, ci = cfg["bootstrap_resamples"], cfg["bootstrap_seed"], cfg["ci"]
    manifest, images, reference, test = open_labelled_split(art, "test", "nothing to evaluate")
    thr = open_artifact(thresholds, "thresholds")
    runs = active_runs(checkpoints, "evaluate")
    checkpoints_read = [open_artifact(path, "checkpoint") for _, _, path in runs]

    metrics = score_runs(runs, manifest.df, images, reference, test, thr.df, cfg, resolve_device(device))
    summary = summarize(metrics, n_boot, ci, boot_seed, cfg["interval"])

    ctx = stage_context("evaluate", __file__, params)
    write_parquet(out, metrics, ctx.meta("metrics", [manifest, images, reference, thr, *checkpoints_read]))
    write_parquet(summary_out, summary, ctx.meta("summary", [open_artifact(out, "metrics")],
                                                 control=BASELINE, ci=ci, bootstrap_resamples=n_boot,
                                                 interval=cfg["interval"]))
    # the DVC results (pipeline.report.dvc_results): metrics files and the plot tables of the runs' logs and curves
    dvc_results.write_metrics_dir(metrics_dir or catalog.path("metrics_students", art),
                                  dvc_results.student_metric_files(summary))
    dvc_results.write_csv(training_curves or catalog.path("plot_training_curves", art), dvc_results.training_curves(
        (m, s, ckpt.table(catalog.TRAINING_LOG_FILE)) for (m, s, _), ckpt in zip(runs, checkpoints_read)))
    dvc_results.write_csv(threshold_curves or catalog.path("plot_threshold_curves", art),
                          dvc_results.threshold_curves(thr.df))
    click.echo(f"evaluate: {len(runs)} runs x {test.size} test images -> {out}, {summary_out}", err=True)


if __name__ == "__main__":
    main()
