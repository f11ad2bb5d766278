"""Stage ``train`` (``train_<method>@<seed>``, or ``train_<method>`` for a group of seeds): one or several
seeds of one method, one after another in a process (``--jobs`` processes side by side), each run exactly as
a process of its own would make it; per-epoch resume state under ``--resume-dir``/<fingerprint>.  Exit code 1
when training diverged."""

from __future__ import annotations

import sys

import click

from pipeline.catalog import ARTIFACTS_DIR
from pipeline.params import section
from pipeline.runtime.device import resolve_device
from pipeline.runtime.errors import TrainingDiverged
from pipeline.training.inputs import open_method
from pipeline.training.seeds import auto_jobs, run_in_processes, run_seeds, seed_options
from stages._common import stage_command, stage_context


@stage_command("train")
@click.option("--stage", type=click.IntRange(1, 2), required=True, help="1 (Stage-I methods) or 2")
@click.option("--method", required=True, help="plain, geodistill, ... (pipeline.methods.METHODS)")
@click.option("--seed", "seeds", type=int, multiple=True, required=True,
              help="a seed to train (repeatable: the seeds run one after another in this process)")
@click.option("--artifacts", default=ARTIFACTS_DIR, show_default=True, type=click.Path(file_okay=False))
@click.option("--init", "inits", multiple=True,
              help="Stage-I checkpoint dir, one per --seed (warm-started methods only; others ignore it)")
@click.option("--out", "outs", multiple=True, required=True, help="checkpoint directory to write, one per --seed")
@click.option("--resume-dir", default=".cache/train", show_default=True,
              help="per-epoch resume states (outside DVC outs)")
@click.option("--live-dir", "live_dirs", multiple=True,
              help="DVCLive log of the epoch rows, one per --seed (default: reports/dvclive/<method>/<seed> "
                   "beside the artifacts dir)")
@click.option("--jobs", type=click.IntRange(0), default=0, show_default=True,
              help="processes training the seeds side by side (the same bytes as one); 0 = the cores over "
                   "train.num_threads on a CPU, 1 on a GPU")
def main(params, device, stage, method, seeds, artifacts, inits, outs, resume_dir, live_dirs, jobs):
    """Train (method, seed) students on pseudo-targets; write checkpoint + training log per seed."""
    jobs = jobs or auto_jobs(section(params, "train"), str(resolve_device(device)), len(seeds))
    context = stage_context("train", __file__, params)
    if jobs > 1 and len(seeds) > 1:
        # bad options or inputs are refused here, in one line, not once in every process
        seed_options(seeds, inits, outs, live_dirs)
        open_method(params, stage, method, artifacts, context)
        sys.exit(run_in_processes("stages.train", sys.argv[1:], len(seeds), min(jobs, len(seeds))))
    try:
        run_seeds(params, device, stage, method, seeds, artifacts, inits, outs, resume_dir, live_dirs, context,
                  sys.argv[1:])
    except TrainingDiverged as e:
        click.echo(f"geodistill train: training diverged: {str(e).splitlines()[0]}", err=True)
        sys.exit(1)


if __name__ == "__main__":
    main()
