"""The ``geodistill`` console script: the DAG's stage commands and the user tools.

The commands are imported lazily, so that ``geodistill --help`` starts no torch.
"""

from __future__ import annotations

import importlib
import importlib.util

import click

from pipeline import __version__
from pipeline.artifacts.lineage import PROGRAM
from pipeline.orchestration.dag import stage_modules
from pipeline.cli.conventions import one_line_errors

__all__ = ["main"]


def command_name(stage: str) -> str:
    """Name the ``geodistill`` command of a DVC stage: its name with "-" for "_" (dvc.yaml keeps the stage's)."""
    return stage.replace("_", "-")


#: subcommand -> module exposing a click command ``main`` (or ``module:command``)
COMMANDS = {
    **{command_name(stage): module for stage, module in stage_modules().items()},
    "segment": "pipeline.cli.segment",
    "dag": "pipeline.cli.generate:dag_main",
    "profile": "pipeline.cli.generate:profile_main",
    "run": "pipeline.cli.run_on_ray",
    "label": "pipeline.cli.label",
    "review": "pipeline.cli.review",
    "distill": "pipeline.cli.distill",
    "plots": "pipeline.cli.plots",
    "reproduce-check": "pipeline.cli.reproduce_check",
}


#: old spellings still accepted (not listed in --help): a DVC stage's own name with "_"
ALIASES = {stage: command_name(stage) for stage in stage_modules() if command_name(stage) != stage}


class LazyGroup(click.Group):
    """The command group that imports a subcommand's module only when that subcommand is asked for."""

    def list_commands(self, ctx):
        """List the subcommands whose module can be found (an optional extra's may not be installed)."""
        return sorted(n for n, m in COMMANDS.items() if importlib.util.find_spec(m.split(":")[0]) is not None)

    def get_command(self, ctx, name):
        """Import and return subcommand ``name`` (an alias resolved), or None when it is unknown or not installed."""
        name = ALIASES.get(name, name)
        if name not in COMMANDS:
            return None
        mod, _, attr = COMMANDS[name].partition(":")
        if importlib.util.find_spec(mod) is None:
            return None
        return getattr(importlib.import_module(mod), attr or "main")

    def invoke(self, ctx):
        """Run every subcommand under :func:`pipeline.cli.conventions.one_line_errors`: one line, no traceback."""
        args = [*getattr(ctx, "_protected_args", []), *ctx.args] or [""]
        with one_line_errors(args[0] or PROGRAM):
            return super().invoke(ctx)


def _print_version(ctx, _param, value):
    if not value or ctx.resilient_parsing:
        return
    click.echo(f"geodistill {__version__}")
    ctx.exit()


USER_HELP = """GeoDistill-Refine: annotation-free spacecraft segmentation.


Your own images:
  geodistill label IMAGES --checkpoint SAM3_DIR --out LABELS      pseudo-masks (PNG, COCO, YOLO)
  geodistill distill IMAGES --checkpoint SAM3_DIR --out RUN       a trained, exported student
  geodistill segment --checkpoint RUN/artifacts/deploy --input PHOTOS --output MASKS


The pipeline (dvc.yaml): `geodistill run` (or `dvc repro`) runs it; every stage is also a
command below. `geodistill COMMAND --help` explains one.
"""


@click.group(cls=LazyGroup, help=USER_HELP)
@click.option("--version", is_flag=True, expose_value=False, is_eager=True, callback=_print_version,
              help="Show the version and exit.")
def main():
    pass


if __name__ == "__main__":
    main()
