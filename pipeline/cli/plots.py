"""``geodistill plots``: DVC's own ``dvc plots show|diff``, with a page that renders without network.

The page template inlines the chart library (DVC's default page loads it from a CDN).
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

import click

from pipeline.artifacts.atomic import write_text_if_changed
from pipeline.report.offline_plots import dvc_plots_command, offline_page, template_path, template_text, vega_scripts
from pipeline.cli.conventions import one_line_errors

__all__ = ["main"]

#: not `dvc plots show`'s own dvc_plots/, so neither replaces the other
OFFLINE_PLOTS_DIR = "geodistill_plots"


@click.command(name="plots")
@click.argument("targets", nargs=-1)
@click.option("--rev", "revs", multiple=True, metavar="REV",
              help="compare with this git revision (dvc plots diff; repeatable)")
@click.option("-o", "--out", default=OFFLINE_PLOTS_DIR, show_default=True, type=click.Path(file_okay=False),
              help="folder of the page (index.html)")
@click.option("--open", "open_browser", is_flag=True, help="open the page in a browser")
def main(targets, revs, out, open_browser):
    """Render DVC's plots (one line per method) as a page that needs no network."""
    with one_line_errors("plots"):
        scripts = vega_scripts()
    template = template_path(".")
    if not template.is_file() and write_text_if_changed(template, template_text()):
        click.echo(f"plots: wrote {template}", err=True)
    with tempfile.TemporaryDirectory() as td:
        page = Path(td) / "page.html"
        page.write_text(offline_page(scripts), encoding="utf-8")
        cmd = [sys.executable, "-m", "dvc", *dvc_plots_command(page, out, revs, targets, open_browser)]
        rc = subprocess.run(cmd).returncode
    if rc != 0:
        sys.exit(rc)


if __name__ == "__main__":
    main()
