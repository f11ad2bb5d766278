"""DVC plots that draw one line per method and render without network.

:data:`METHOD_LINES` is the Vega-Lite template dvc.yaml's ``plots:`` name; :func:`offline_page` inlines the chart
library DVC's own page loads from a CDN.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path
from typing import Sequence

from pipeline.catalog import PLOT_TEMPLATE
from pipeline.runtime.errors import InputError

__all__ = ["VEGA_PACKAGE", "VEGA_FILES", "METHOD_LINES", "template_text", "template_path", "vega_scripts",
           "offline_page", "dvc_plots_command"]

#: the installed package whose files are the chart library (vega 5, vega-lite 5, vega-embed 6), in load order
VEGA_PACKAGE = "js_lib_vega_embed"
VEGA_FILES = ("vega5.js", "vega-lite5.js", "vega-embed6.js")

#: Vega's tableau20, saturated colours first (the scheme alternates dark/light pairs: two methods, two blues)
COLOURS = ("#4c78a8", "#f58518", "#54a24b", "#b79a20", "#439894", "#e45756", "#79706e", "#d67195", "#b279a2",
           "#9e765f", "#9ecae9", "#ffbf79", "#88d27a", "#f2cf5b", "#83bcb6", "#ff9d98", "#bab0ac", "#fcbfd2",
           "#d6a5c9", "#d8b5a5")

#: the Vega-Lite template: one line per method (colour), one dash per revision, the mean over seeds
METHOD_LINES = {
    "$schema": "https://vega.github.io/schema/vega-lite/v5.json",
    "data": {"values": "<DVC_METRIC_DATA>"},
    "title": "<DVC_METRIC_TITLE>",
    "width": 420,
    "height": 280,
    "mark": {"type": "line", "strokeWidth": 2},
    "encoding": {
        "x": {"field": "<DVC_METRIC_X>", "type": "quantitative", "title": "<DVC_METRIC_X_LABEL>"},
        "y": {"field": "<DVC_METRIC_Y>", "type": "quantitative", "aggregate": "mean",
              "title": "<DVC_METRIC_Y_LABEL>", "scale": {"zero": False}},
        "color": {"field": "method", "type": "nominal", "title": "method", "scale": {"range": list(COLOURS)}},
        "strokeDash": {"field": "rev", "type": "nominal", "title": "revision"},
    },
    "usermeta": {"embedOptions": {"renderer": "svg"}},
}


def template_text() -> str:
    """Render the plot template's file content.

    Returns
    -------
    str
        The committed ``.dvc/plots/<PLOT_TEMPLATE>.json``: :data:`METHOD_LINES` as JSON.
    """
    return json.dumps(METHOD_LINES, indent=1) + "\n"


def template_path(repo_root: str | Path) -> Path:
    """Locate the plot template in a repository.

    Parameters
    ----------
    repo_root : str or Path
        The repository (its ``.dvc`` folder).

    Returns
    -------
    Path
        ``<repo_root>/.dvc/plots/<PLOT_TEMPLATE>.json``.
    """
    return Path(repo_root) / ".dvc" / "plots" / f"{PLOT_TEMPLATE}.json"


def vega_scripts() -> list[tuple[str, str]]:
    """Read the chart library's scripts from the installed package.

    Returns
    -------
    list of tuple
        ``(file name, JavaScript)`` of each of :data:`VEGA_FILES`, in load order.

    Raises
    ------
    InputError
        :data:`VEGA_PACKAGE` is not installed, or a file of it is missing.
    """
    spec = importlib.util.find_spec(VEGA_PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        raise InputError(f"{VEGA_PACKAGE}: not installed (pip install django-js-lib-vega-embed); "
                         "it provides the chart library of the offline plots page")
    folder = Path(list(spec.submodule_search_locations)[0]) / "static" / VEGA_PACKAGE
    out = []
    for name in VEGA_FILES:
        f = folder / name
        if not f.is_file():
            raise InputError(f"{f}: missing from the installed {VEGA_PACKAGE}; reinstall it")
        out.append((name, f.read_text(encoding="utf-8")))
    return out


def _inline(code: str) -> str:
    # the same string to JavaScript, but it cannot end the element early
    return code.replace("</script", "<\\/script")


def offline_page(scripts: Sequence[tuple[str, str]], title: str = "GeoDistill-Refine plots") -> str:
    """Build a ``dvc plots show --html-template`` page with the chart library inlined.

    The page has no ``{scripts}`` placeholder, so DVC adds no CDN tag.

    Parameters
    ----------
    scripts : Sequence of tuple
        ``(file name, JavaScript)`` pairs (:func:`vega_scripts`).
    title : str
        The page's title.

    Returns
    -------
    str
        The HTML template, with DVC's ``{plot_divs}`` placeholder.
    """
    blocks = "\n".join(f"<script>/* {name} */\n{_inline(code)}\n</script>" for name, code in scripts)
    return ("<!DOCTYPE html>\n<html>\n<head>\n<meta charset=\"utf-8\">\n"
            f"<title>{title}</title>\n{blocks}\n"
            "<style>body { font-family: sans-serif; } .vega-embed { margin: 1em; }</style>\n"
            "</head>\n<body>\n{plot_divs}\n</body>\n</html>\n")


def dvc_plots_command(page: str | Path, out: str | Path, revs: Sequence[str] = (),
                      targets: Sequence[str] = (), open_browser: bool = False) -> list[str]:
    """Build the DVC arguments that render the plots into ``out`` with the offline page.

    Parameters
    ----------
    page : str or Path
        The HTML template (:func:`offline_page`).
    out : str or Path
        The output folder.
    revs : Sequence of str
        Revisions to compare (``dvc plots diff``); none: ``dvc plots show``.
    targets : Sequence of str
        Plot targets; none: every plot of dvc.yaml.
    open_browser : bool
        Open the page when rendered.

    Returns
    -------
    list of str
        The arguments after ``dvc``.
    """
    cmd = ["plots", "diff", *revs] if revs else ["plots", "show"]
    if targets:
        cmd += ["--targets", *targets] if revs else list(targets)
    cmd += ["--html-template", str(page), "-o", str(out)]
    return cmd + (["--open"] if open_browser else [])
