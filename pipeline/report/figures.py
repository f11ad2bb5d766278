"""Figures drawn with OpenCV and numpy only (no matplotlib dependency): error overlays, pseudo-target
panels, line plots.  Every function returns an RGB uint8 array; :func:`png_bytes` encodes one.

Colour conventions (paper Fig. qualitative-results / prompt-comparison):
  true positive green, false positive red, false negative blue (alpha-blended over the image),
  ground-truth contour yellow.  Agreement map: viridis in [0, 1].  SDF (eq:sdf-target, D = d_in - d_out
  normalised): red inside (positive) - white (boundary) - blue outside (negative), symmetric around 0.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import cv2
import numpy as np

TP = (40, 200, 60)
FP = (230, 40, 40)
FN = (40, 90, 240)
GT_CONTOUR = (255, 230, 0)
WHITE = (255, 255, 255)
BLACK = (0, 0, 0)
# distinct line colours (RGB) for plots of series that are not methods
PALETTE = [(31, 119, 180), (214, 39, 40), (44, 160, 44), (255, 127, 14), (148, 103, 189),
           (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)]
#: ONE colour per method (and the teacher vote), the same in every figure; no two alike.  Ablations
#: are also drawn dashed (:data:`DASHED_METHODS`), so that 16 series stay distinguishable.
METHOD_COLORS = {
    "plain": (31, 119, 180), "geodistill": (214, 39, 40), "continuation": (255, 127, 14),
    "confidence_filtered": (44, 160, 44), "afs_control": (148, 103, 189), "gabi": (140, 86, 75),
    "geodistill_adaptive": (227, 119, 194), "full_scratch_10": (188, 189, 34), "full_scratch_30": (23, 190, 207),
    "sdf_scratch": (0, 0, 128), "sdf_gated": (0, 128, 128), "sdf_skel_gated": (128, 0, 0),
    "sdf_area_gated": (240, 50, 230), "no_gate": (100, 100, 255), "supervised_ceiling": (0, 0, 0),
    "teacher_vote": (127, 127, 127),
}
DASHED_METHODS = frozenset({"full_scratch_10", "full_scratch_30", "sdf_scratch", "sdf_gated", "sdf_skel_gated",
                            "sdf_area_gated", "no_gate", "supervised_ceiling"})
REFERENCE_LINE = (170, 170, 170)  # diagonals and "ratio = 1" lines
FONT = cv2.FONT_HERSHEY_SIMPLEX
LEGEND_SCALE = 0.35
LEGEND_ROW = 16


def method_style(method: str) -> dict:
    """``{"color", "style"}`` of a method's series (:data:`METHOD_COLORS`; unknown names: grey)."""
    return {"color": METHOD_COLORS.get(method, (90, 90, 90)),
            "style": "dashed" if method in DASHED_METHODS else "solid"}


def png_bytes(rgb: np.ndarray) -> bytes:
    """Encode an RGB uint8 image as PNG bytes."""
    ok, buf = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def _resize(arr: np.ndarray, size: int, nearest: bool) -> np.ndarray:
    if arr.shape[0] == size and arr.shape[1] == size:
        return arr
    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_AREA
    return cv2.resize(arr, (size, size), interpolation=interp)


def to_rgb(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    return np.ascontiguousarray(img[..., :3].astype(np.uint8))


def mask_tile(mask: np.ndarray, size: int) -> np.ndarray:
    """A binary mask as a white-on-black tile."""
    m = _resize(np.asarray(mask, dtype=np.uint8) * 255, size, nearest=True)
    return np.repeat(m[..., None], 3, axis=2)


def draw_contour(rgb: np.ndarray, mask: np.ndarray, color=GT_CONTOUR, thickness: int = 1) -> np.ndarray:
    """Draw the outer and hole contours of a binary mask (already at ``rgb``'s size) in place."""
    contours, _ = cv2.findContours(np.asarray(mask, dtype=np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(rgb, contours, -1, color, thickness, lineType=cv2.LINE_8)
    return rgb


def error_overlay(image: np.ndarray, pred: np.ndarray, gt: np.ndarray, size: int, alpha: float = 0.55,
                  contour: bool = True) -> np.ndarray:
    """Image with TP green, FP red, FN blue blended in and the ground-truth contour in yellow."""
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
    """Map a float array to RGB: ``viridis`` (sequential) or ``diverging`` (blue-white-red around 0)."""
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
    """Image darkened outside the mask, with the skeleton drawn in magenta (dilated to stay visible)."""
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


def caption_tile(tile: np.ndarray, lines: Sequence[str], scale: float = 0.36, pad: int = 3) -> np.ndarray:
    """Add a white band with one or more text lines above a tile."""
    h_line = int(22 * scale) + 4
    band = np.full((pad * 2 + h_line * len(lines), tile.shape[1], 3), 255, np.uint8)
    for i, text in enumerate(lines):
        y = pad + h_line * (i + 1) - 4
        cv2.putText(band, text, (3, y), FONT, scale, BLACK, 1, cv2.LINE_AA)
    return np.concatenate([band, tile], axis=0)


def hstack(tiles: Sequence[np.ndarray], gap: int = 4) -> np.ndarray:
    """Place tiles side by side on white, top-aligned."""
    h = max(t.shape[0] for t in tiles)
    padded = []
    for i, t in enumerate(tiles):
        canvas = np.full((h, t.shape[1], 3), 255, np.uint8)
        canvas[:t.shape[0]] = t
        padded.append(canvas)
        if i < len(tiles) - 1:
            padded.append(np.full((h, gap, 3), 255, np.uint8))
    return np.concatenate(padded, axis=1)


def vstack(rows: Sequence[np.ndarray], gap: int = 8) -> np.ndarray:
    """Stack rows on white, left-aligned."""
    w = max(r.shape[1] for r in rows)
    out = []
    for i, r in enumerate(rows):
        canvas = np.full((r.shape[0], w, 3), 255, np.uint8)
        canvas[:, :r.shape[1]] = r
        out.append(canvas)
        if i < len(rows) - 1:
            out.append(np.full((gap, w, 3), 255, np.uint8))
    return np.concatenate(out, axis=0)


def title_band(img: np.ndarray, text: str, scale: float = 0.5) -> np.ndarray:
    band = np.full((int(30 * scale) + 12, img.shape[1], 3), 255, np.uint8)
    cv2.putText(band, text, (4, band.shape[0] - 8), FONT, scale, BLACK, 1, cv2.LINE_AA)
    return np.concatenate([band, img], axis=0)


# --------------------------------------------------------------------------------------------------
# Composite panels
# --------------------------------------------------------------------------------------------------
def qualitative_row(image: np.ndarray, gt: np.ndarray, preds: Mapping[str, np.ndarray],
                    scores: Mapping[str, str], title: str, size: int = 160) -> np.ndarray:
    """One row: image | image + GT contour | one TP/FP/FN overlay per method (caption: its metrics)."""
    img = _resize(to_rgb(image), size, nearest=False)
    gt_view = draw_contour(img.copy(), _resize(np.asarray(gt, np.uint8), size, nearest=True))
    tiles = [caption_tile(img, [title, ""]), caption_tile(gt_view, ["ground truth", "(yellow contour)"])]
    for name, pred in preds.items():
        tiles.append(caption_tile(error_overlay(image, pred, gt, size), [name, scores.get(name, "")]))
    return hstack(tiles)


def pseudo_target_row(image: np.ndarray, prompt_masks: np.ndarray, prompt_labels: Sequence[str],
                      agreement: np.ndarray, voted: np.ndarray, sdf: np.ndarray, skeleton: np.ndarray,
                      gate_text: Sequence[str], title: str, size: int = 128) -> np.ndarray:
    """Paper Fig. pseudo-geometry: image, K prompt masks, agreement A, voted M, SDF D, skeleton K
    over the image, and the gate's numbers (c, v, a, g) in the image tile's caption."""
    tiles = [caption_tile(_resize(to_rgb(image), size, nearest=False), [title, *gate_text])]
    for m, lab in zip(prompt_masks, prompt_labels):
        tiles.append(caption_tile(mask_tile(m, size), [lab]))
    tiles.append(caption_tile(colorize(agreement, size, 0.0, 1.0, "viridis"), ["agreement A"]))
    tiles.append(caption_tile(mask_tile(voted, size), ["voted M (A>=0.5)"]))
    tiles.append(caption_tile(colorize(sdf, size, -1.0, 1.0, "diverging"), ["SDF D (in>0>out)"]))
    tiles.append(caption_tile(skeleton_overlay(image, voted, skeleton, size), ["skeleton K"]))
    return hstack(tiles)


def _nice_ticks(lo: float, hi: float, n: int = 5) -> np.ndarray:
    if not np.isfinite(lo) or not np.isfinite(hi) or hi <= lo:
        hi = lo + 1.0
    raw = (hi - lo) / max(n, 1)
    mag = 10 ** np.floor(np.log10(raw))
    step = min((s * mag for s in (1, 2, 2.5, 5, 10) if s * mag >= raw), default=raw)
    start = np.ceil(lo / step) * step
    return np.arange(start, hi + step * 1e-6, step)


def _dashed_line(img: np.ndarray, p0, p1, color, dash: int = 7, gap: int = 5) -> None:
    """A dashed segment from ``p0`` to ``p1`` (dashes of ``dash`` px, gaps of ``gap`` px, in place)."""
    a, b = np.asarray(p0, float), np.asarray(p1, float)
    length = float(np.hypot(*(b - a)))
    if length == 0:
        return
    for t0 in np.arange(0.0, length, dash + gap):
        t1 = min(t0 + dash, length)
        q0, q1 = a + (b - a) * t0 / length, a + (b - a) * t1 / length
        cv2.line(img, tuple(int(round(v)) for v in q0), tuple(int(round(v)) for v in q1), color, 2, cv2.LINE_AA)


def line_plot(series: Sequence[dict], title: str, xlabel: str, ylabel: str, width: int = 640,
              height: int = 380, ylim: tuple[float, float] | None = None) -> np.ndarray:
    """A simple line plot.  ``series``: dicts with ``x``, ``y``, ``label`` and optional ``marker``
    (an x value to mark with a dot, e.g. the selected threshold), ``color`` and ``style``
    ("solid" | "dashed").  The plot area is ``width - 256`` by ``height - 90`` px; the image grows to
    the right and downwards until every legend label fits in full (labels are never cut)."""
    left, right, top, bottom = 56, 200, 46, 44
    pw, ph = width - left - right, height - top - bottom
    text_w = max((cv2.getTextSize(str(s.get("label", "")), FONT, LEGEND_SCALE, 1)[0][0] for s in series), default=0)
    right = max(right, 32 + text_w + 8)
    width = left + pw + right
    height = max(height, top + 12 + LEGEND_ROW * len(series) + 4)
    ph = height - top - bottom
    img = np.full((height, width, 3), 255, np.uint8)
    xs = np.concatenate([np.asarray(s["x"], float) for s in series]) if series else np.array([0.0, 1.0])
    ys = np.concatenate([np.asarray(s["y"], float) for s in series]) if series else np.array([0.0, 1.0])
    xs = xs[np.isfinite(xs)] if np.isfinite(xs).any() else np.array([0.0, 1.0])
    ys = ys[np.isfinite(ys)] if np.isfinite(ys).any() else np.array([0.0, 1.0])
    x0, x1 = float(np.min(xs)), float(np.max(xs))
    if x1 <= x0:
        x1 = x0 + 1
    y0, y1 = ylim if ylim is not None else (float(np.min(ys)), float(np.max(ys)))
    if y1 <= y0:
        y0, y1 = y0 - 0.05, y1 + 0.05
    pad = 0.05 * (y1 - y0)
    y0, y1 = (y0, y1) if ylim is not None else (y0 - pad, y1 + pad)

    def px(x, y):
        return (int(round(left + (x - x0) / (x1 - x0) * pw)), int(round(top + (1 - (y - y0) / (y1 - y0)) * ph)))

    grey = (220, 220, 220)
    for t in _nice_ticks(y0, y1):
        p = px(x0, t)
        cv2.line(img, (left, p[1]), (left + pw, p[1]), grey, 1)
        cv2.putText(img, f"{t:.2f}", (4, p[1] + 4), FONT, 0.35, BLACK, 1, cv2.LINE_AA)
    for t in _nice_ticks(x0, x1):
        p = px(t, y0)
        cv2.line(img, (p[0], top), (p[0], top + ph), grey, 1)
        lab = f"{t:g}"
        cv2.putText(img, lab, (p[0] - 4 * len(lab), top + ph + 14), FONT, 0.35, BLACK, 1, cv2.LINE_AA)
    cv2.rectangle(img, (left, top), (left + pw, top + ph), BLACK, 1)
    cv2.putText(img, title, (left, 20), FONT, 0.5, BLACK, 1, cv2.LINE_AA)
    cv2.putText(img, xlabel, (left + pw // 2 - 4 * len(xlabel), height - 8), FONT, 0.4, BLACK, 1, cv2.LINE_AA)
    cv2.putText(img, ylabel, (4, top - 10), FONT, 0.38, BLACK, 1, cv2.LINE_AA)
    for i, s in enumerate(series):
        col = s.get("color", PALETTE[i % len(PALETTE)])
        x = np.asarray(s["x"], float)
        y = np.asarray(s["y"], float)
        ok = np.isfinite(x) & np.isfinite(y)
        pts = [px(a, b) for a, b in zip(x[ok], y[ok])]
        dashed = s.get("style") == "dashed"
        for j in range(len(pts) - 1):
            if dashed:
                _dashed_line(img, pts[j], pts[j + 1], col)
            else:
                cv2.line(img, pts[j], pts[j + 1], col, 2, cv2.LINE_AA)
        if len(pts) == 1:
            cv2.circle(img, pts[0], 3, col, -1, cv2.LINE_AA)
        if s.get("marker") is not None and ok.any():
            mx = float(s["marker"])
            my = float(np.interp(mx, x[ok], y[ok]))
            cv2.circle(img, px(mx, my), 5, col, -1, cv2.LINE_AA)
            cv2.circle(img, px(mx, my), 5, BLACK, 1, cv2.LINE_AA)
        ly = top + 12 + LEGEND_ROW * i
        if dashed:
            for x in (left + pw + 10, left + pw + 22):
                cv2.line(img, (x, ly - 4), (x + 6, ly - 4), col, 2, cv2.LINE_AA)
        else:
            cv2.line(img, (left + pw + 10, ly - 4), (left + pw + 28, ly - 4), col, 2, cv2.LINE_AA)
        cv2.putText(img, str(s.get("label", "")), (left + pw + 32, ly), FONT, LEGEND_SCALE, BLACK, 1, cv2.LINE_AA)
    return img
