"""``geodistill distill INPUT --out DIR``: a folder in, a student, deploy bundle and report out."""

from __future__ import annotations

import click

from pipeline.api import distill_params
from pipeline.runtime.errors import LABELS
from pipeline.profiles import load_params_or_profile
from pipeline.orchestration.standalone import (efficiency_line, project_outputs, run_project, time_budget_params, training_line,
                                 write_project)
from pipeline.runtime.progress import quiet_bars
from pipeline.cli.conventions import (bit_depth_option, max_pixels_option, overwrite_option, quiet_option,
                                      skip_bad_option, stage_command, teacher_choice_options)

__all__ = ["main"]


@stage_command("distill", default_profile="distill", profile_loader=load_params_or_profile)
@click.argument("input_dir", metavar="INPUT", type=click.Path())
@click.option("--out", required=True, type=click.Path(file_okay=False),
              help="project folder (created; rerun the same command to resume)")
@click.option("--val-masks", default=None, type=click.Path(),
              help="masks named like some of the images: those images become validation/test images "
                   "(threshold, checkpoint choice, report scores); without: tau 0.5, last epoch")
@teacher_choice_options("; a SIMULATOR is refused (it needs masks of every training image)")
@click.option(LABELS.flag, LABELS.keyword, default=None, type=click.Path(), metavar="LABEL_DIR",
              help="an unmodified `geodistill label` output of the same images: train from its pseudo-labels "
                   "(its teacher, resolution, vote and gate) and its teacher cache, so the teacher computes "
                   "nothing again; no --checkpoint needed")
@click.option("--time", "time_budget", default=None, metavar="DURATION",
              help="bound Stage I's training, e.g. 20m or 1h30m: converted once on this host into "
                   "train.step_budget in the project's params (a rerun with the same --time does nothing; a "
                   "longer one continues the saved run); a time that allows the whole run at more epochs "
                   "raises the epochs cap, up to train.time_cap_factor times; the teacher, Stage II and export "
                   "come on top")
@click.option("--no-run", is_flag=True, help="only write the DVC project (run it later with `dvc repro` in --out)")
@click.option("--no-benchmark", is_flag=True, help="leave out the efficiency benchmark of the deploy bundle "
              "(time it later: `geodistill benchmark --deploy artifacts/deploy` in --out)")
@skip_bad_option
@max_pixels_option
@bit_depth_option
@overwrite_option
@quiet_option
def main(params, device, input_dir, out, val_masks, backend, labels, time_budget, no_run, no_benchmark, skip_bad,
         max_pixels, bit_depth, overwrite, quiet, **folders):
    """Train a deployable student on a folder of images.

    SAM 3 pseudo-labels, Stage I, Stage II, threshold, export, report.  --out becomes a DVC project running the
    pipeline's own DAG, so a rerun resumes; a file of yours where a project file goes is refused by name
    (docs/own-data.md).  --labels LABEL_DIR reuses an unmodified `geodistill label` output's teacher answers.
    """
    params = distill_params(params, input_dir, labels, backend, folders, skip_bad, max_pixels, bit_depth)
    params = time_budget_params(params, time_budget, out, device, input_dir, val_masks)
    project = write_project(input_dir, out, params, val_masks=val_masks, overwrite=overwrite, labels=labels,
                            benchmark=not no_benchmark)
    if no_run:
        click.echo(f"distill: wrote the DVC project {project}; run `dvc repro` there", err=True)
        return
    with quiet_bars(quiet):
        run_project(project, device, quiet=quiet)
    res = project_outputs(project)
    click.echo(f"distill: deploy bundle {res['deploy']}\ndistill: report {res['report']}", err=True)
    if (line := training_line(project)) is not None:
        click.echo(f"distill: {line}", err=True)
    if (line := efficiency_line(project)) is not None:
        click.echo(f"distill: {line}", err=True)


if __name__ == "__main__":
    main()
