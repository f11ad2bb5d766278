"""Contact sheet: a grid of sampled images with their ground-truth contours, so a user can see the data."""

from __future__ import annotations

import cv2
import numpy as np
import pandas as pd

__all__ = ["sample_for_sheet", "tile", "contact_sheet"]

CONTOUR_RGB = (0, 255, 0)


def sample_for_sheet(rows: pd.DataFrame, n: int, seed: int) -> np.ndarray:
    """Pick the rows a contact sheet shows: round-robin over (split, group), seeded within a group.

    Parameters
    ----------
    rows : pandas.DataFrame
        Manifest rows (``split`` and ``group`` columns).
    n : int
        How many to pick (``data.contact_sheet_images``); fewer when there are fewer rows.
    seed : int
        The shuffle's seed within each group (``data.seed``).

    Returns
    -------
    numpy.ndarray
        int64 row indices, every group shown before any shows twice.
    """
    rng = np.random.default_rng(seed)
    groups = [rng.permutation(idx.to_numpy()) for _, idx in rows.groupby(["split", "group"], sort=True).groups.items()]
    out: list[int] = []
    k = 0
    while len(out) < min(n, len(rows)):
        for g in groups:
            if k < len(g) and len(out) < n:
                out.append(int(g[k]))
        k += 1
    return np.asarray(out, np.int64)


def tile(image: np.ndarray, mask: np.ndarray | None, label: str, size: int) -> np.ndarray:
    """Draw one tile: the image upscaled (nearest) to ``size``, its reference contour in green, a caption.

    Parameters
    ----------
    image : numpy.ndarray
        RGB uint8 [R, R, 3].
    mask : numpy.ndarray or None
        Bool [R, R] reference mask (None or empty: no contour).
    label : str
        The caption, wrapped so it is never cut (:func:`caption_lines`).
    size : int
        The tile's side in pixels.

    Returns
    -------
    numpy.ndarray
        RGB uint8 [size, size, 3].
    """
    t = cv2.resize(image, (size, size), interpolation=cv2.INTER_NEAREST) if image.shape[0] != size else image.copy()
    if mask is not None and mask.any():
        m = cv2.resize(mask.astype(np.uint8), (size, size), interpolation=cv2.INTER_NEAREST)
        contours, _ = cv2.findContours(m, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(t, contours, -1, CONTOUR_RGB, 1)
    lines, scale = caption_lines(label, size - 6, max(size / 400.0, 0.3))
    height = cv2.getTextSize("Ag", cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][1]
    for i, line in enumerate(lines):
        cv2.putText(t, line, (3, (height + 3) * (i + 1)), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1,
                    cv2.LINE_AA)
    return t


def caption_lines(label: str, width: int, scale: float, min_scale: float = 0.25) -> tuple[list[str], float]:
    """Wrap ``label`` at spaces and ``/`` into lines of at most ``width`` pixels at font ``scale``.

    The scale shrinks (down to ``min_scale``) while a single word is wider, then a word is broken inside, so
    that a caption is never cut: ``(lines, scale)``.
    """
    def fits(text: str, sc: float) -> bool:
        return cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, sc, 1)[0][0] <= width

    words = [w for w in label.replace("/", "/ ").split(" ") if w]
    while scale > min_scale and not all(fits(w, scale) for w in words):
        scale = max(min_scale, scale * 0.9)
    pieces = []
    for w in words:  # still too wide at the smallest scale: broken into pieces that fit
        while not fits(w, scale) and len(w) > 1:
            k = max(k for k in range(1, len(w) + 1) if k == 1 or fits(w[:k], scale))
            pieces.append(w[:k])
            w = w[k:]
        pieces.append(w)
    lines: list[str] = []
    for w in pieces:
        joined = f"{lines[-1]}{'' if lines[-1].endswith('/') else ' '}{w}" if lines else w
        if lines and fits(joined, scale):
            lines[-1] = joined
        else:
            lines.append(w)
    return lines, scale


def contact_sheet(tiles: list[np.ndarray], columns: int = 4, pad: int = 2) -> np.ndarray:
    """Lay equally sized RGB tiles out in a grid (row-major), separated by ``pad`` grey pixels.

    Parameters
    ----------
    tiles : list of numpy.ndarray
        RGB uint8 [s, s, 3] each.
    columns : int
        Tiles per row (fewer when there are fewer tiles).
    pad : int
        Grey pixels between and around the tiles.

    Returns
    -------
    numpy.ndarray
        The sheet, RGB uint8; an 8 x 8 black image when there are no tiles.
    """
    if not tiles:
        return np.zeros((8, 8, 3), np.uint8)
    s = tiles[0].shape[0]
    cols = min(columns, len(tiles))
    rows = -(-len(tiles) // cols)
    sheet = np.full((rows * (s + pad) + pad, cols * (s + pad) + pad, 3), 64, np.uint8)
    for k, t in enumerate(tiles):
        r, c = divmod(k, cols)
        sheet[pad + r * (s + pad): pad + r * (s + pad) + s, pad + c * (s + pad): pad + c * (s + pad) + s] = t
    return sheet
