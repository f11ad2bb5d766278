"""``geodistill run``: the DVC pipeline on Ray, DVC staying the record (:mod:`pipeline.cluster.driver`)."""

from __future__ import annotations

import signal
import sys
from pathlib import Path

import click

from pipeline.cluster.driver import run_pipeline
from pipeline.cli.conventions import one_line_errors, setup_logging

__all__ = ["main"]


@click.command(name="run")
@click.argument("targets", nargs=-1)
@click.option("--address", default=None, metavar="ADDR",
              help="a Ray cluster to join (e.g. ray://head:10001 or auto) [default: $RAY_ADDRESS, else an "
                   "embedded local Ray]")
@click.option("--stage-cpus", type=click.FloatRange(min=1), default=None,
              help="cores a CPU stage takes (its OMP_NUM_THREADS) [default: half the largest node]")
@click.option("--train-gpu-fraction", type=click.FloatRange(min=0.01, max=1), default=0.25, show_default=True,
              help="the share of a GPU one training run takes (4 runs per GPU at 0.25)")
@click.option("--dry-run", is_flag=True, help="print the stages that would be checked, with their resources")
def main(targets, address, stage_cpus, train_gpu_fraction, dry_run):
    """Run the DVC pipeline (or TARGETS and their upstream stages) with the stale stages as Ray tasks.

    Each runs `dvc repro --single-item STAGE` once its upstream stages are done, so DVC records every
    stage as `dvc repro` would.  A failing stage's dependents do not run (exit code 1).  Logs and a
    timeline: artifacts/logs/run/.  Needs the `cluster` extra (Ray); docs/scaling.md.
    """
    setup_logging()
    # SIGTERM (scancel, kill) as Ctrl-C: Ray shuts down and the stage processes end with their workers
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    with one_line_errors("run"):
        result = run_pipeline(Path.cwd(), tuple(targets), address, stage_cpus, train_gpu_fraction, dry_run,
                              echo=click.echo)
    if result is None:
        return
    click.echo(f"geodistill run: {result.count('ran')} ran, {result.count('restored')} restored from DVC's run "
               f"cache, {result.count('up_to_date')} up to date, {result.count('failed')} failed, "
               f"{result.count('not_run')} not run; {result.wall_s:.1f} s wall")
    if not result.ok:
        failed = [n for n, r in result.results.items() if r["status"] == "failed"]
        not_run = [n for n, r in result.results.items() if r["status"] == "not_run"]
        click.echo(f"geodistill run: error: stage {failed[0]} failed: {result.results[failed[0]]['error']}"
                   + (f"; not run: {', '.join(not_run)}" if not_run else ""), err=True)
        sys.exit(1)


if __name__ == "__main__":
    main()
