"""Figures drawn with matplotlib on the Agg canvas (PNG for the page, SVG for papers), byte-identical across renders.

Image panels (paper Fig. qualitative-results, eq:sdf-target) are numpy/OpenCV RGB tiles.
"""

from __future__ import annotations

import contextlib
import io
from typing import Iterator, Mapping, Sequence

import cv2
import matplotlib
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure as Chart
from matplotlib.textpath import TextPath
from matplotlib.ticker import MaxNLocator

from pipeline.methods import METHODS

__all__ = ["GT_CONTOUR", "PALETTE", "UNKNOWN_METHOD", "REFERENCE_LINE", "CHART_FONT", "PNG_DPI", "Tile",
           "MAX_TILE_INCHES", "method_style", "png_bytes", "svg_bytes", "error_overlay", "qualitative_row",
           "pseudo_target_row", "caption_inches", "wrap_caption", "image_grid", "line_plot", "histogram"]

#: the error overlay's colours (:func:`error_overlay`): true positive, false positive, false negative
TP = (40, 200, 60)
FP = (230, 40, 40)
FN = (40, 90, 240)
GT_CONTOUR = (255, 230, 0)
PALETTE = [(31, 119, 180), (214, 39, 40), (44, 160, 44), (255, 127, 14), (148, 103, 189),
           (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)]
UNKNOWN_METHOD = {"color": "#5a5a5a", "style": "solid", "symbol": "."}
REFERENCE_LINE = (170, 170, 170)  # diagonals and "ratio = 1" lines
CHART_FONT = {"font.size": 10, "axes.titlesize": 11, "axes.labelsize": 10, "xtick.labelsize": 9,
              "ytick.labelsize": 9, "legend.fontsize": 8.5}
SVG_RC = {"svg.hashsalt": "geodistill-refine", "svg.fonttype": "path"}
PNG_DPI = 120


def method_style(method: str) -> dict:
    """Return a method's series style from the method table.

    Parameters
    ----------
    method : str
        A method name; another name (e.g. the teacher vote) gets :data:`UNKNOWN_METHOD`'s grey dots.

    Returns
    -------
    dict
        ``color``, ``style``, ``symbol`` and, for a method of the table, ``key``: the keys :func:`line_plot`
        reads of a series.
    """
    m = METHODS.get(method)
    if m is None:
        return dict(UNKNOWN_METHOD)
    return {"color": m.color, "style": m.dash, "symbol": m.symbol, "key": m.name}


def png_bytes(fig: Chart) -> bytes:
    """Render ``fig`` as PNG at :data:`PNG_DPI`, byte-identical across renders.

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        The figure.

    Returns
    -------
    bytes
        The PNG file, without a timestamp or software tag.
    """
    return _save(fig, "png")


def _resize(arr: np.ndarray, size: int, nearest: bool) -> np.ndarray:
    if arr.shape[:2] == (size, size):
        return arr
    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_AREA
    return cv2.resize(arr, (size, size), interpolation=interp)


def to_rgb(image: np.ndarray) -> np.ndarray:
    """Return ``image`` (grey or RGB(A)) as a contiguous uint8 RGB array."""
    img = np.asarray(image)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    return np.ascontiguousarray(img[..., :3].astype(np.uint8))


def mask_tile(mask: np.ndarray, size: int) -> np.ndarray:
    """Return a binary mask as a white-on-black RGB tile of ``size`` px (nearest-neighbour)."""
    m = _resize(np.asarray(mask, dtype=np.uint8) * 255, size, nearest=True)
    return np.repeat(m[..., None], 3, axis=2)


def draw_contour(rgb: np.ndarray, mask: np.ndarray, color=GT_CONTOUR, thickness: int = 1) -> np.ndarray:
    """Draw the outer and hole contours of a binary mask (at ``rgb``'s size) in place."""
    contours, _ = cv2.findContours(np.asarray(mask, dtype=np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(rgb, contours, -1, color, thickness, lineType=cv2.LINE_8)
    return rgb


def error_overlay(image: np.ndarray, pred: np.ndarray, gt: np.ndarray, size: int, alpha: float = 0.55,
                  contour: bool = True) -> np.ndarray:
    """Draw a prediction's errors over its image: :data:`TP` green, :data:`FP` red, :data:`FN` blue.

    Each marked pixel becomes (1 - ``alpha``) image + ``alpha`` colour; the ground truth's contour is drawn in
    :data:`GT_CONTOUR` on top.

    Parameters
    ----------
    image : numpy.ndarray
        The image, grey or RGB.
    pred, gt : numpy.ndarray
        The predicted and the reference binary masks.
    size : int
        The side of the square tile in pixels (the masks resized nearest-neighbour).
    alpha : float
        The opacity of the error colours.
    contour : bool
        Whether to draw the ground truth's contour.

    Returns
    -------
    numpy.ndarray
        The RGB uint8 tile, ``size`` x ``size``.
    """
    img = _resize(to_rgb(image), size, nearest=False).astype(np.float32)
    p = _resize(np.asarray(pred, dtype=np.uint8), size, nearest=True).astype(bool)
    g = _resize(np.asarray(gt, dtype=np.uint8), size, nearest=True).astype(bool)
    for sel, col in ((p & g, TP), (p & ~g, FP), (~p & g, FN)):
        img[sel] = (1 - alpha) * img[sel] + alpha * np.array(col, np.float32)
    out = np.clip(img, 0, 255).astype(np.uint8)
    if contour:
        draw_contour(out, g)
    return out


def colorize(values: np.ndarray, size: int, vmin: float, vmax: float, kind: str = "viridis") -> np.ndarray:
    """Colour a float array as RGB: ``viridis`` or ``diverging`` (blue-white-red around 0).

    Parameters
    ----------
    values : numpy.ndarray
        The 2-D values.
    size : int
        The side of the square tile in pixels.
    vmin, vmax : float
        The values mapped to the two ends of the colour map (clipped outside).
    kind : str
        ``viridis`` or ``diverging``.

    Returns
    -------
    numpy.ndarray
        The RGB uint8 tile, ``size`` x ``size``.

    Raises
    ------
    ValueError
        ``kind`` is neither colour map.
    """
    v = np.asarray(values, dtype=np.float32)
    t = np.clip((v - vmin) / max(vmax - vmin, 1e-12), 0.0, 1.0)
    t = _resize(t, size, nearest=False)
    if kind == "viridis":
        bgr = cv2.applyColorMap((t * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    if kind == "diverging":
        blue, white, red = (np.array(c, np.float32) for c in ((33, 102, 172), (247, 247, 247), (178, 24, 43)))
        lo = t[..., None] < 0.5
        a = np.where(lo, t[..., None] * 2, (t[..., None] - 0.5) * 2)
        rgb = np.where(lo, blue + (white - blue) * a, white + (red - white) * a)
        return rgb.astype(np.uint8)
    raise ValueError(f"unknown colour map {kind!r}")


def skeleton_overlay(image: np.ndarray, mask: np.ndarray, skeleton: np.ndarray, size: int) -> np.ndarray:
    """Return ``image`` dimmed outside ``mask`` with the ``skeleton`` pixels dotted in magenta, ``size`` px."""
    img = _resize(to_rgb(image), size, nearest=False).astype(np.float32)
    m = _resize(np.asarray(mask, dtype=np.uint8), size, nearest=True).astype(bool)
    img[~m] *= 0.35
    out = img.astype(np.uint8)
    sk = np.asarray(skeleton, dtype=np.uint8)
    scale = size / sk.shape[0]
    ys, xs = np.nonzero(sk)
    for y, x in zip((ys * scale).astype(int), (xs * scale).astype(int)):
        cv2.circle(out, (int(x), int(y)), max(1, int(round(scale / 2))), (255, 0, 255), -1)
    return out


#: one tile of :func:`image_grid`: an RGB uint8 image and its caption lines
Tile = tuple[np.ndarray, Sequence[str]]


def qualitative_row(image: np.ndarray, gt: np.ndarray, preds: Mapping[str, np.ndarray],
                    scores: Mapping[str, str], title: str, size: int = 160,
                    reference: Sequence[str] = ("ground truth", "(yellow contour)")) -> list[Tile]:
    """Build one row of :func:`image_grid`: image | reference contour | a TP/FP/FN overlay per method.

    Parameters
    ----------
    image : numpy.ndarray
        The image, grey or RGB.
    gt : numpy.ndarray
        The reference binary mask.
    preds : Mapping
        Method name -> its binary mask, in column order (:func:`error_overlay`).
    scores : Mapping
        Method name -> the score line under its name ("" where missing).
    title : str
        The first tile's caption.
    size : int
        The side of each tile in pixels.
    reference : sequence of str
        The caption of the reference tile.

    Returns
    -------
    list of Tile
        The row's tiles with their captions.
    """
    img = _resize(to_rgb(image), size, nearest=False)
    gt_view = draw_contour(img.copy(), _resize(np.asarray(gt, np.uint8), size, nearest=True))
    return [(img, [title]), (gt_view, list(reference)),
            *((error_overlay(image, pred, gt, size), [name, scores.get(name, "")]) for name, pred in preds.items())]


def pseudo_target_row(image: np.ndarray, prompt_masks: np.ndarray, prompt_labels: Sequence[str],
                      agreement: np.ndarray, voted: np.ndarray, sdf: np.ndarray, skeleton: np.ndarray,
                      gate_text: Sequence[str], title: str, size: int = 128) -> list[Tile]:
    """Build one row of :func:`image_grid` (paper Fig. pseudo-geometry): image, prompt masks, A, M, D and K.

    Parameters
    ----------
    image : numpy.ndarray
        The image, grey or RGB.
    prompt_masks : numpy.ndarray
        The teacher's mask of each prompt, stacked.
    prompt_labels : sequence of str
        The caption of each prompt mask.
    agreement : numpy.ndarray
        A, the per-pixel agreement of the prompts in [0, 1].
    voted : numpy.ndarray
        M, the voted mask.
    sdf : numpy.ndarray
        D, the signed distance target (eq:sdf-target), positive inside; drawn over [-1, 1].
    skeleton : numpy.ndarray
        K, the skeleton of M.
    gate_text : sequence of str
        The gate's caption lines under ``title``.
    title : str
        The first tile's caption.
    size : int
        The side of each tile in pixels.

    Returns
    -------
    list of Tile
        The row's tiles with their captions.
    """
    return [(_resize(to_rgb(image), size, nearest=False), [title, *gate_text]),
            *((mask_tile(m, size), [lab]) for m, lab in zip(prompt_masks, prompt_labels)),
            (colorize(agreement, size, 0.0, 1.0, "viridis"), ["agreement A"]),
            (mask_tile(voted, size), ["voted M (A>=0.5)"]),
            (colorize(sdf, size, -1.0, 1.0, "diverging"), ["SDF D (in>0>out)"]),
            (skeleton_overlay(image, voted, skeleton, size), ["skeleton K"])]


#: image panels: least inches per tile, caption points and the widest a tile grows before a caption wraps
TILE_INCHES = 1.45
CAPTION_FONT = 8.5
MAX_TILE_INCHES = 2.4


def caption_inches(line: str) -> float:
    """Measure the width of a caption line at :data:`CAPTION_FONT`.

    Parameters
    ----------
    line : str
        One caption line.

    Returns
    -------
    float
        Its width in inches; 0 for a blank line.
    """
    return TextPath((0, 0), line, size=CAPTION_FONT).get_extents().width / 72.0 if line.strip() else 0.0


def wrap_caption(line: str, width: float = MAX_TILE_INCHES) -> list[str]:
    """Wrap ``line`` to ``width`` inches at the caption font, inside a word only where it is wider than a line.

    Parameters
    ----------
    line : str
        One caption line.
    width : float
        The widest a line may be, in inches.

    Returns
    -------
    list of str
        The lines, none wider than ``width`` unless it holds a single character: no caption is cut.
    """
    lines = [""]
    for word in line.split(" "):
        joined = f"{lines[-1]} {word}" if lines[-1] else word
        if caption_inches(joined) <= width:
            lines[-1] = joined
            continue
        if caption_inches(word) <= width:
            lines.append(word)
            continue
        while caption_inches(joined) > width:  # a word wider than a line fills this one, then lines of its own
            k = max(k for k in range(1, len(joined)) if k == 1 or caption_inches(joined[:k]) <= width)
            lines[-1], joined = joined[:k].rstrip(), joined[k:].lstrip()
            lines.append("")
        lines[-1] = joined
    return lines


def image_grid(rows: Sequence[Sequence[Tile]], tile_inches: float = TILE_INCHES) -> Chart:
    """Draw rows of image tiles as one figure, each tile pixel for pixel with its caption above.

    Tiles widen (up to :data:`MAX_TILE_INCHES`, then captions wrap) so no caption is cut or runs into the next.

    Parameters
    ----------
    rows : sequence of sequence of Tile
        The rows (:func:`qualitative_row`, :func:`pseudo_target_row`); a short row leaves its last cells blank.
    tile_inches : float
        The least side of a tile in inches.

    Returns
    -------
    matplotlib.figure.Figure
        The figure (:func:`png_bytes`, :func:`svg_bytes`).
    """
    rows = [[(tile, [part for line in cap for part in wrap_caption(line)]) for tile, cap in row] for row in rows]
    nrows = len(rows)
    ncols = max((len(r) for r in rows), default=1)
    lines = max((len(cap) for r in rows for _, cap in r), default=1)
    widest = max((caption_inches(line) for r in rows for _, cap in r for line in cap), default=0.0)
    tile_inches = max(tile_inches, widest + 0.04)
    cap_inches = lines * CAPTION_FONT * 1.25 / 72.0
    gap = 0.08                                                   # inches between tiles
    width = ncols * tile_inches + (ncols - 1) * gap
    height = nrows * (tile_inches + cap_inches)
    with matplotlib.rc_context(CHART_FONT):
        fig = Chart(figsize=(width, height), dpi=100)
        FigureCanvasAgg(fig)
        # every cell exactly tile_inches square: no margins, the captions in the vertical gaps
        axes = fig.subplots(nrows, ncols, squeeze=False,
                            gridspec_kw={"left": 0.0, "right": 1.0, "bottom": 0.0, "top": 1.0 - cap_inches / height,
                                         "wspace": gap / tile_inches, "hspace": cap_inches / tile_inches})
        for r, row in enumerate(rows):
            for c in range(ncols):
                ax = axes[r][c]
                ax.set_axis_off()
                if c < len(row):
                    tile, caption = row[c]
                    ax.imshow(tile, interpolation="nearest")
                    ax.set_title("\n".join(caption), fontsize=CAPTION_FONT, loc="left", pad=2)
    return fig


def svg_bytes(fig: Chart) -> bytes:
    """Render ``fig`` as SVG, byte-identical across renders (fixed hash salt, text as paths, no date).

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        The figure.

    Returns
    -------
    bytes
        The SVG file.
    """
    return _save(fig, "svg")


def _save(fig: Chart, fmt: str) -> bytes:
    """``fig`` in ``fmt`` (png | svg | pdf) without any timestamp or random id."""
    metadata = {"png": {"Software": None}, "svg": {"Date": None}, "pdf": {"CreationDate": None}}[fmt]
    buf = io.BytesIO()
    with matplotlib.rc_context({**CHART_FONT, **SVG_RC}):
        fig.savefig(buf, format=fmt, dpi=PNG_DPI, metadata=metadata, bbox_inches="tight", pad_inches=0.05)
    return buf.getvalue()


def _mpl_color(color) -> str | tuple:
    return color if isinstance(color, str) else tuple(float(c) / 255.0 for c in color)


@contextlib.contextmanager
def _chart(width: int, height: int, title: str, xlabel: str, ylabel: str, **grid) -> Iterator[tuple[Chart, object]]:
    """(figure, axes) of ``width`` x ``height`` px axes, titled and gridded after the body draws."""
    with matplotlib.rc_context(CHART_FONT):
        fig = Chart(figsize=(width / 100.0, height / 100.0), dpi=100)
        FigureCanvasAgg(fig)
        ax = fig.add_subplot()
        yield fig, ax
        ax.set_title(title)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(True, color="#dddddd", linewidth=0.6, **grid)
        ax.set_axisbelow(True)


def line_plot(series: Sequence[dict], title: str, xlabel: str, ylabel: str, width: int = 640,
              height: int = 380, ylim: tuple[float, float] | None = None) -> Chart:
    """Draw a line chart of ``series`` with the legend at the right.

    Earlier series are drawn wider and under later ones, so coinciding curves both show; non-finite points are
    left out, and whole-number x values get whole-number ticks.

    Parameters
    ----------
    series : sequence of dict
        Each with ``x``, ``y``, ``label`` and optionally ``marker`` (an x to dot), ``color``, ``style``,
        ``symbol`` and ``key`` (SVG id ``series-<key>``); :func:`method_style` gives a method's.
    title, xlabel, ylabel : str
        The chart's title and axis labels.
    width, height : int
        The axes' size in pixels.
    ylim : tuple of float or None
        The y range; None: matplotlib's.

    Returns
    -------
    matplotlib.figure.Figure
        The figure (:func:`png_bytes`, :func:`svg_bytes`).
    """
    with _chart(width, height, title, xlabel, ylabel) as (fig, ax):
        n = len(series)
        for i, s in enumerate(series):
            _draw_series(ax, s, i, n)
        if ylim is not None:
            ax.set_ylim(*ylim)
        if series and all(_integral(s["x"]) for s in series):      # epochs: whole-number ticks
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        if n:
            ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0, frameon=False,
                      handlelength=3.0)
    return fig


def histogram(values, bins, title: str, xlabel: str, ylabel: str, width: int = 640, height: int = 300) -> Chart:
    """Draw a histogram of ``values`` over the bin edges ``bins``, whole-number counts on the y axis.

    Parameters
    ----------
    values : array_like
        The values counted.
    bins : array_like
        The bin edges, increasing.
    title, xlabel, ylabel : str
        The chart's title and axis labels.
    width, height : int
        The axes' size in pixels.

    Returns
    -------
    matplotlib.figure.Figure
        The figure (:func:`png_bytes`, :func:`svg_bytes`).
    """
    counts, edges = np.histogram(np.asarray(values, float), bins=np.asarray(bins, float))
    with _chart(width, height, title, xlabel, ylabel, axis="y") as (fig, ax):
        ax.bar(edges[:-1], counts, width=np.diff(edges), align="edge", color=_mpl_color(PALETTE[0]),
               edgecolor="white", linewidth=0.6, gid="histogram")
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_xlim(float(edges[0]), float(edges[-1]))
    return fig


def _integral(values) -> bool:
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    return bool(v.size) and bool(np.all(v == np.round(v)))


def _draw_series(ax, s: dict, i: int, n: int) -> None:
    color = _mpl_color(s.get("color", PALETTE[i % len(PALETTE)]))
    x = np.asarray(s["x"], float)
    y = np.asarray(s["y"], float)
    ok = np.isfinite(x) & np.isfinite(y)
    every = max(1, int(ok.sum()) // 8)
    width = 1.5 + 1.3 * (n - 1 - i) / max(n - 1, 1)        # earlier = wider, so it shows under later ones
    symbol = s.get("symbol")
    ax.plot(x[ok], y[ok], color=color, linestyle=s.get("style", "solid"), linewidth=width, alpha=0.85,
            marker=symbol, markevery=(i % every, every) if symbol else None, markersize=5,
            markerfacecolor="none" if symbol in ("o", "s", "D", "^", "v", "<", ">", "p", "h", "d") else color,
            label=str(s.get("label", "")), zorder=2 + i, gid=f"series-{s.get('key', i)}")
    if s.get("marker") is not None and ok.any():
        mx = float(s["marker"])
        my = float(np.interp(mx, x[ok], y[ok]))
        ax.plot([mx], [my], marker="o", markersize=7 + 4 * (n - 1 - i) / max(n - 1, 1), color=color,
                markeredgecolor="black", linestyle="none", zorder=3 + n + i)
