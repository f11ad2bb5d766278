"""``geodistill plots``: DVC's plots of this project as a page that works offline.

    geodistill plots                       # dvc plots show: every plot of dvc.yaml -> geodistill_plots/index.html (dvc plots show alone writes dvc_plots/)
    geodistill plots --rev HEAD~1          # dvc plots diff HEAD~1: the workspace against a commit
    geodistill plots training_curves -o out --open

It runs DVC's own ``dvc plots show`` (``dvc plots diff`` with ``--rev``) with ``--html-template`` set
to a page that inlines the chart library from an installed package (pipeline.report.offline_plots), so the
page renders without network; DVC's default page loads it from a CDN and stays blank offline.  It
first writes ``.dvc/plots/method_lines.json`` (the template of dvc.yaml's plots: one line per method)
when the project lacks it.  Plain ``dvc plots show`` works too, online.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

import click

from pipeline.artifacts.atomic import write_text_if_changed
from pipeline.runtime.errors import InputError
from pipeline.report.offline_plots import dvc_plots_command, offline_page, template_path, template_text, vega_scripts

#: the page folder of `geodistill plots`: not `dvc plots show`'s own dvc_plots/, so neither replaces the other
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
    try:
        scripts = vega_scripts()
    except InputError as e:
        click.echo(f"geodistill plots: error: {e}", err=True)
        sys.exit(2)
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
