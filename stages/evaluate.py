"""Stage evaluate: per-image metrics of every student on every test group at the calibrated and the fixed
tau, seed summaries with the gains' intervals, and the DVC metrics and plot tables; reference masks only score."""

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
