"""A tiny document model (sections of text, tables, figures, "missing input" notes) and its two renderings.

The model renders to Markdown and to ONE self-contained HTML page (CSS inline, figures as base64 PNG data URIs,
no scripts, no external requests).
"""

from __future__ import annotations

import base64
import dataclasses
import html
import re
from typing import Union

__all__ = ["Text", "Table", "Figure", "Missing", "Section", "Report", "render_markdown", "render_html"]


@dataclasses.dataclass
class Text:
    """A paragraph; supports `code` and **bold** inline markup.

    Attributes
    ----------
    text : str
        The paragraph, Markdown inline markup allowed.
    """

    text: str


@dataclasses.dataclass
class Table:
    """A table of preformatted cells with a title and notes under it.

    Attributes
    ----------
    key : str
        An id for tests and the HTML's ``data-key`` (e.g. ``"tab:spacesense-results"``), never shown.
    title : str
        The caption above the table.
    header : list of str
        The column headings.
    rows : list of list of str
        The cells, row by row, already formatted.
    notes : list of str
        Notes printed under the table, one paragraph each.
    """

    key: str
    title: str
    header: list[str]
    rows: list[list[str]]
    notes: list[str] = dataclasses.field(default_factory=list)


@dataclasses.dataclass
class Figure:
    """A figure: a PNG (embedded in the HTML, linked from the Markdown) and optionally its SVG.

    Attributes
    ----------
    key : str
        An id for tests and the HTML's ``data-key``, never shown.
    title : str
        The figure's title (also the image's alt text).
    caption : str
        The caption under it.
    png : bytes
        The encoded PNG.
    filename : str
        The PNG's file name, written under ``figures/``.
    svg : bytes or None
        The vector form of the figure (text as paths), written beside the PNG as ``<stem>.svg``; None: none.
    """

    key: str
    title: str
    caption: str
    png: bytes
    filename: str
    svg: bytes | None = None

    @property
    def svg_filename(self) -> str:
        """``filename`` with the ``.svg`` suffix (the vector file beside the PNG)."""
        return self.filename.rsplit(".", 1)[0] + ".svg"


@dataclasses.dataclass
class Missing:
    """An input that was not there: the report says so instead of failing.

    Attributes
    ----------
    what : str
        What is missing (shown in bold).
    detail : str
        Why, and how to produce it.
    """

    what: str
    detail: str


Block = Union[Text, Table, Figure, Missing]


@dataclasses.dataclass
class Section:
    """A titled section of the report.

    Attributes
    ----------
    title : str
        The heading.
    blocks : list of Text, Table, Figure or Missing
        Its content, in order.
    """

    title: str
    blocks: list[Block] = dataclasses.field(default_factory=list)


@dataclasses.dataclass
class Report:
    """A whole report: a title and its sections.

    Attributes
    ----------
    title : str
        The report's title (the page's heading).
    sections : list of Section
        The sections, in order.
    """

    title: str
    sections: list[Section]

    def figures(self) -> list[Figure]:
        """List the report's figures.

        Returns
        -------
        list of Figure
            Every :class:`Figure` block, in document order.
        """
        return [b for s in self.sections for b in s.blocks if isinstance(b, Figure)]

    def tables(self) -> list[Table]:
        """List the report's tables.

        Returns
        -------
        list of Table
            Every :class:`Table` block, in document order.
        """
        return [b for s in self.sections for b in s.blocks if isinstance(b, Table)]


def _md_row(cells) -> str:
    """Write one Markdown table row, ``|`` escaped and line breaks flattened."""
    return "| " + " | ".join(str(c).replace("|", "\\|").replace("\n", " ") for c in cells) + " |"


def render_markdown(report: Report, figure_dir: str = "figures") -> str:
    """Render ``report`` as Markdown, figures linked (not embedded).

    Parameters
    ----------
    report : Report
        The document.
    figure_dir : str
        The folder, relative to the Markdown file, that holds each figure's ``filename`` (and SVG).

    Returns
    -------
    str
        The Markdown text, ending with one newline.
    """
    out = [f"# {report.title}", ""]
    for sec in report.sections:
        out += [f"## {sec.title}", ""]
        for b in sec.blocks:
            if isinstance(b, Text):
                out += [b.text, ""]
            elif isinstance(b, Missing):
                out += [f"> **Missing: {b.what}.** {b.detail}", ""]
            elif isinstance(b, Table):
                out += [f"**{b.title}**", "", _md_row(b.header), "|" + "|".join("---" for _ in b.header) + "|",
                        *map(_md_row, b.rows), "", *(f"*{n}*" for n in b.notes), *([""] if b.notes else [])]
            elif isinstance(b, Figure):
                vector = f" Vector: [{b.svg_filename}]({figure_dir}/{b.svg_filename})." if b.svg else ""
                out += [f"**{b.title}**", "", f"![{b.title}]({figure_dir}/{b.filename})", "",
                        f"*{b.caption}*{vector}", ""]
    return "\n".join(out).rstrip() + "\n"


CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;max-width:1200px;margin:2em auto;
padding:0 1em;color:#222;line-height:1.45}
h1{font-size:1.7em;border-bottom:2px solid #333;padding-bottom:.2em}h2{font-size:1.3em;margin-top:2em;
border-bottom:1px solid #bbb}
table{border-collapse:collapse;margin:.6em 0 .3em 0;font-size:.9em}
th,td{border-top:1px solid #ccc;border-bottom:1px solid #ccc;padding:.25em .6em;text-align:center}
th{background:#f2f2f2}td:first-child,th:first-child{text-align:left}
caption{caption-side:top;text-align:left;font-weight:600;padding:.3em 0}
.note{font-size:.85em;color:#444;margin:.2em 0}
.missing{background:#fff4e5;border-left:4px solid #f0a030;padding:.5em .8em;margin:.6em 0}
figure{margin:1em 0}figure img{max-width:100%;border:1px solid #ddd}
figcaption{font-size:.88em;color:#333;margin-top:.3em}
code{background:#f4f4f4;padding:0 .2em}
"""


def _inline(text: str) -> str:
    """Escape ``text`` for HTML and turn its `code` and **bold** markup into tags."""
    s = html.escape(str(text))
    s = re.sub(r"`([^`]+)`", r"<code>\1</code>", s)
    s = re.sub(r"\*\*([^*]+)\*\*", r"<b>\1</b>", s)
    return s


def render_html(report: Report) -> str:
    """Render ``report`` as one self-contained HTML page: no external resource of any kind.

    The CSS is inline, the figures are base64 PNG data URIs, and there are no scripts.

    Parameters
    ----------
    report : Report
        The document.

    Returns
    -------
    str
        The HTML page, ending with one newline.
    """
    parts = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
             f"<title>{html.escape(report.title)}</title>", f"<style>{CSS}</style></head><body>",
             f"<h1>{html.escape(report.title)}</h1>"]
    for i, sec in enumerate(report.sections):
        parts.append(f'<section id="sec{i}"><h2>{html.escape(sec.title)}</h2>')
        for b in sec.blocks:
            if isinstance(b, Text):
                parts.append(f"<p>{_inline(b.text)}</p>")
            elif isinstance(b, Missing):
                parts.append(f'<div class="missing"><b>Missing: {html.escape(b.what)}.</b> {_inline(b.detail)}</div>')
            elif isinstance(b, Table):
                parts += [f'<table data-key="{html.escape(b.key)}"><caption>{_inline(b.title)}</caption>',
                          "<thead><tr>" + "".join(f"<th>{_inline(h)}</th>" for h in b.header) + "</tr></thead><tbody>",
                          *("<tr>" + "".join(f"<td>{_inline(c)}</td>" for c in r) + "</tr>" for r in b.rows),
                          "</tbody></table>", *(f'<p class="note">{_inline(n)}</p>' for n in b.notes)]
            elif isinstance(b, Figure):
                data = base64.b64encode(b.png).decode("ascii")
                parts.append(f'<figure data-key="{html.escape(b.key)}"><img alt="{html.escape(b.title)}" '
                             f'src="data:image/png;base64,{data}"><figcaption><b>{html.escape(b.title)}.</b> '
                             f"{_inline(b.caption)}</figcaption></figure>")
        parts.append("</section>")
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"
