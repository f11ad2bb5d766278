"""``geodistill profile NAME`` and ``geodistill dag``: generate params.yaml and dvc.yaml."""

from __future__ import annotations

import sys
from pathlib import Path

import click
import yaml

from pipeline.artifacts.atomic import write_text_if_changed
from pipeline.catalog import DVC_FILE, PARAMS_FILE
from pipeline.orchestration.dag import is_generated_params, project_dvc_yaml, render_params_yaml
from pipeline.artifacts.ownership import refuse_unowned
from pipeline.profiles import PROFILES
from pipeline.cli.conventions import one_line_errors

__all__ = ["dag_main", "profile_main"]


@click.command(name="dag")
@click.option("--check", is_flag=True, help="only check that dvc.yaml is up to date (exit 1 if not)")
@click.option("--out", default=DVC_FILE, show_default=True, type=click.Path(dir_okay=False))
def dag_main(check: bool, out: str) -> None:
    """Write dvc.yaml from pipeline/catalog.py, pipeline/methods.py, the stages' imports and params.yaml."""
    raw = yaml.safe_load(Path(PARAMS_FILE).read_text()) if Path(PARAMS_FILE).is_file() else None
    text = project_dvc_yaml(raw)
    path = Path(out)
    if check:
        if not path.is_file() or path.read_text() != text:
            click.echo(f"geodistill dag: {path} is out of date; run `geodistill dag`", err=True)
            sys.exit(1)
        click.echo(f"{path} is up to date")
        return
    click.echo(f"{'wrote' if write_text_if_changed(path, text) else 'unchanged'} {path}")


@click.command(name="profile")
@click.argument("name", type=click.Choice(list(PROFILES)))
@click.option("--out", default=PARAMS_FILE, show_default=True, type=click.Path(dir_okay=False))
@click.option("--overwrite", is_flag=True,
              help="accepted like the other commands' --overwrite; a params file that `geodistill profile` did "
                   "not write is never replaced (refused by name)")
def profile_main(name: str, out: str, overwrite: bool) -> None:
    """Write params.yaml with the effective values of profile NAME; a params file it did not write is refused."""
    with one_line_errors("profile"):
        text = render_params_yaml(name)
        path = Path(out)
        refuse_unowned([path], [path] if is_generated_params(path) else [], command="profile", option="--out",
                       where=out, why="it lacks the header a generated params file starts with", overwrite=overwrite)
        click.echo(f"{'wrote' if write_text_if_changed(out, text) else 'unchanged'} {out} (profile {name})")


if __name__ == "__main__":
    dag_main()
