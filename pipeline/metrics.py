"""Per-image segmentation metrics and threshold calibration (paper, "Metrics and Statistical Analysis").

Everything is computed on binary masks at the working resolution; ``pred`` and ``gt`` are bool [H,W]
(0/1 integers accepted).  Conventions, chosen so that per-image means are well defined:

* Image IoU = |P & G| / |P | G|; both masks empty -> 1.
* Foreground precision = |P & G| / |P|, recall = |P & G| / |G|.  A ratio 0/0 is 1 only when both masks
  are empty; when exactly one mask is empty, the undefined ratio is 0 (like the other one, which is
  0 by definition) -- an empty prediction of a non-empty target scores (0, 0), a non-empty
  prediction of an empty target scores (0, 0), two empty masks score (1, 1).
* Boundary F1 (tolerance t = 2 px at 384x384): the boundary of a mask is the mask minus its 3x3
  erosion -- the one-pixel-wide, 8-connected inner contour.  The image frame is NOT a contour: the
  erosion treats pixels outside the frame as foreground (OpenCV's default border for erosion), as
  the SDF targets treat the frame as "not background".  A boundary pixel of P is matched when its
  exact Euclidean distance (``cv2.distanceTransform``, DIST_MASK_PRECISE) to the nearest boundary
  pixel of G is <= t; BF-precision = matched P-boundary / |P-boundary|, BF-recall symmetric,
  BF1 = 2PR / (P + R) (0 when P + R = 0).  Both masks empty -> 1, exactly one empty -> 0; two
  full-frame masks (no contour at all) -> 1, exactly one contour-less -> 0.
* Predicted foreground area ratio = mean(P).
* Small-region IoU (``small_region_iou``): IoU restricted to the neighbourhood of small ground-truth
  objects -- see that function; NaN when the ground truth has no small component.
* Calibration (eq:inference-mask): :func:`iou_curve` gives the Image IoU of M = [P >= tau] at every tau
  of a grid; the selection rule lives in pipeline.thresholds (calibrate_threshold).
"""

from __future__ import annotations

import numpy as np

from pipeline.errors import InputError
from pipeline.params import PAPER
from pipeline.geometry import squared_distance

DEFAULT_TOLERANCE = PAPER.evaluate.bf1_tolerance  # the params schema holds the defaults
DEFAULT_SMALL_FRACTION = PAPER.evaluate.small_region_max_fraction
DEFAULT_SMALL_MARGIN = 3


def _cv2():
    import cv2

    return cv2


def _as_mask(x: np.ndarray, name: str) -> np.ndarray:
    x = np.asarray(x)
    if x.dtype != bool:
        if x.dtype.kind not in "biuf" or (x.size and not np.isin(x, (0, 1)).all()):
            raise InputError(f"{name}: mask must be binary (bool or 0/1)")
        x = x.astype(bool)
    return x


def _pair(pred, gt, ndim: int = 2) -> tuple[np.ndarray, np.ndarray]:
    pred = _as_mask(pred, "pred")
    gt = _as_mask(gt, "gt")
    if pred.shape != gt.shape:
        raise InputError(f"pred {pred.shape} and gt {gt.shape} shapes differ")
    if pred.ndim != ndim:
        raise InputError(f"expected {ndim}-D masks, got shape {pred.shape}")
    return pred, gt


# --------------------------------------------------------------------------------------------------
# Region metrics
# --------------------------------------------------------------------------------------------------
def _ratio(num: np.ndarray, den: np.ndarray, both_empty: np.ndarray) -> np.ndarray:
    """num / den, with 0/0 -> 1 where both masks are empty and 0 elsewhere."""
    num = np.asarray(num, dtype=np.float64)
    den = np.asarray(den, dtype=np.float64)
    out = np.divide(num, den, out=np.zeros(np.broadcast(num, den).shape), where=den > 0)
    return np.where(den > 0, out, np.where(both_empty, 1.0, 0.0))


def _region_counts(pred: np.ndarray, gt: np.ndarray):
    n, pixels = pred.shape[0], int(np.prod(pred.shape[1:]))  # (explicit size: -1 is ambiguous when n = 0)
    p = pred.reshape(n, pixels)
    g = gt.reshape(n, pixels)
    inter = np.count_nonzero(p & g, axis=1)
    np_ = np.count_nonzero(p, axis=1)
    ng = np.count_nonzero(g, axis=1)
    return inter, np_, ng


def image_iou(pred, gt) -> float:
    """Image IoU = |P & G| / |P | G| in [0, 1]; both masks empty -> 1."""
    pred, gt = _pair(pred, gt)
    inter, np_, ng = _region_counts(pred[None], gt[None])
    return float(_ratio(inter, np_ + ng - inter, (np_ == 0) & (ng == 0))[0])


def image_ious(preds, gts) -> np.ndarray:
    """:func:`image_iou` of every pair in batches [N,H,W] -> float64 [N], vectorised."""
    preds, gts = _pair(preds, gts, ndim=3)
    inter, np_, ng = _region_counts(preds, gts)
    return _ratio(inter, np_ + ng - inter, (np_ == 0) & (ng == 0))


def precision_recall(pred, gt) -> tuple[float, float]:
    """Foreground (precision, recall) = (|P & G| / |P|, |P & G| / |G|).

    Both masks empty -> (1, 1); exactly one empty -> (0, 0) (module docstring).
    """
    pred, gt = _pair(pred, gt)
    inter, np_, ng = _region_counts(pred[None], gt[None])
    both = (np_ == 0) & (ng == 0)
    return float(_ratio(inter, np_, both)[0]), float(_ratio(inter, ng, both)[0])


def area_fraction(pred) -> float:
    """Predicted foreground area ratio = (1/HW) sum_x P(x)."""
    pred = _as_mask(pred, "pred")
    return float(np.count_nonzero(pred)) / pred.size if pred.size else 0.0


# --------------------------------------------------------------------------------------------------
# Boundary F1
# --------------------------------------------------------------------------------------------------
_K3 = np.ones((3, 3), np.uint8)


def mask_boundary(mask) -> np.ndarray:
    """One-pixel-wide inner boundary: mask minus its 3x3 erosion (frame edge is not boundary)."""
    mask = _as_mask(mask, "mask")
    m8 = np.ascontiguousarray(mask, dtype=np.uint8)
    return mask & ~_cv2().erode(m8, _K3).astype(bool)


def _squared_distance_to(boundary: np.ndarray) -> np.ndarray:
    """Exact squared Euclidean distance of every pixel to the nearest True pixel of ``boundary``
    (integer-valued float32; compared with tolerance**2 so that d = t exactly is always matched)."""
    return squared_distance(~boundary)


def _boundary_f1_one(pred: np.ndarray, gt: np.ndarray, tolerance: float) -> float:
    p_any, g_any = pred.any(), gt.any()
    if not p_any and not g_any:
        return 1.0
    if p_any != g_any:
        return 0.0
    bp, bg = mask_boundary(pred), mask_boundary(gt)
    np_, ng = np.count_nonzero(bp), np.count_nonzero(bg)
    if np_ == 0 and ng == 0:  # two full-frame masks: no contour anywhere, identical masks
        return 1.0
    if np_ == 0 or ng == 0:
        return 0.0
    t2 = tolerance * tolerance
    precision = np.count_nonzero(_squared_distance_to(bg)[bp] <= t2) / np_
    recall = np.count_nonzero(_squared_distance_to(bp)[bg] <= t2) / ng
    if precision + recall == 0:
        return 0.0
    return float(2 * precision * recall / (precision + recall))


def boundary_f1(pred, gt, tolerance: float = DEFAULT_TOLERANCE) -> float:
    """Boundary F1 with a ``tolerance``-pixel (Euclidean, inclusive) matching radius; see the module
    docstring for the boundary definition and the empty-mask conventions."""
    pred, gt = _pair(pred, gt)
    if tolerance < 0:
        raise InputError(f"boundary_f1: tolerance={tolerance!r} must be >= 0")
    return _boundary_f1_one(pred, gt, float(tolerance))


# --------------------------------------------------------------------------------------------------
# Small-region IoU
# --------------------------------------------------------------------------------------------------
def small_region_mask(gt, max_fraction: float = DEFAULT_SMALL_FRACTION, margin: int = DEFAULT_SMALL_MARGIN):
    """(region R, small components S) bool [H,W] each, for :func:`small_region_iou`; R is empty when
    the ground truth has no small component."""
    gt = _as_mask(gt, "gt")
    cv2 = _cv2()
    h, w = gt.shape
    n_lab, labels, stats, _ = cv2.connectedComponentsWithStats(np.ascontiguousarray(gt, dtype=np.uint8),
                                                               connectivity=8)
    areas = stats[1:, cv2.CC_STAT_AREA]
    small_ids = np.flatnonzero(areas < max_fraction * h * w) + 1
    if small_ids.size == 0:
        z = np.zeros_like(gt)
        return z, z
    is_small = np.zeros(n_lab, bool)
    is_small[small_ids] = True
    small = is_small[labels]
    large = gt & ~small
    if margin > 0:
        disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1, 2 * margin + 1))
        region = cv2.dilate(small.astype(np.uint8), disk).astype(bool)
    else:
        region = small.copy()
    return region & ~large, small


def small_region_iou(pred, gt, max_fraction: float = DEFAULT_SMALL_FRACTION,
                     margin: int = DEFAULT_SMALL_MARGIN) -> float:
    """IoU restricted to small ground-truth objects (a supplementary diagnostic of the paper).

    S = union of the 8-connected components of G whose pixel count is < ``max_fraction`` * H * W
    (1 % of the frame by default).  R = S dilated by a Euclidean disk of radius ``margin`` px,
    minus the pixels of the larger GT components (so that they neither help nor hurt).  Then
    small-region IoU = |P & S & R| / |(P & R) | S|  (note S is inside R, so G & R = S): missed small
    parts and false positives within ``margin`` px of them both count.  NaN when G has no small
    component (the image does not enter the mean).
    """
    pred, gt = _pair(pred, gt)
    region, small = small_region_mask(gt, max_fraction, margin)
    if not small.any():
        return float("nan")
    p = pred & region
    return float(np.count_nonzero(p & small) / np.count_nonzero(p | small))


# --------------------------------------------------------------------------------------------------
# Batched
# --------------------------------------------------------------------------------------------------
METRIC_NAMES = ("iou", "bf1", "precision", "recall", "area_ratio", "small_iou")


def per_image_metrics(preds, gts, tolerance: float = DEFAULT_TOLERANCE, *,
                      max_fraction: float = DEFAULT_SMALL_FRACTION,
                      margin: int = DEFAULT_SMALL_MARGIN) -> dict[str, np.ndarray]:
    """Every metric for N images at once: preds, gts bool [N,H,W] -> dict of float64 [N] arrays
    ``iou, bf1, precision, recall, area_ratio, small_iou`` (same values as the single-image
    functions; region metrics vectorised, boundary/small-region metrics per image with OpenCV)."""
    preds, gts = _pair(preds, gts, ndim=3)
    if tolerance < 0:
        raise InputError(f"per_image_metrics: tolerance={tolerance!r} must be >= 0")
    n = preds.shape[0]
    inter, np_, ng = _region_counts(preds, gts)
    both = (np_ == 0) & (ng == 0)
    hw = float(np.prod(preds.shape[1:])) if n else 1.0
    bf1 = np.empty(n)
    small = np.empty(n)
    for i in range(n):
        bf1[i] = _boundary_f1_one(preds[i], gts[i], float(tolerance))
        small[i] = small_region_iou(preds[i], gts[i], max_fraction, margin)
    return {
        "iou": _ratio(inter, np_ + ng - inter, both),
        "bf1": bf1,
        "precision": _ratio(inter, np_, both),
        "recall": _ratio(inter, ng, both),
        "area_ratio": np_ / hw,
        "small_iou": small,
    }


# --------------------------------------------------------------------------------------------------
# Threshold calibration
# --------------------------------------------------------------------------------------------------
def iou_curve(probs, gts, grid, *, chunk: int = 16) -> np.ndarray:
    """Image IoU of [P >= tau] (eq:inference-mask) for every image and every tau of ``grid``:
    float64 [N, G].  One pass over the pixels: each probability is binned by the number of grid
    points it reaches, and cumulative counts give |P|, |P & G| at every tau (no per-tau loop)."""
    probs = np.asarray(probs)
    gts = _as_mask(gts, "gts")
    grid = np.asarray(grid, dtype=np.float64)
    if probs.shape != gts.shape or probs.ndim != 3:
        raise InputError(f"probs {probs.shape} and gts {gts.shape} must be equal [N,H,W] shapes")
    if grid.ndim != 1 or grid.size == 0 or not np.isfinite(grid).all() or (np.diff(grid) <= 0).any():
        raise InputError("calibration grid must be a non-empty, finite, strictly increasing 1-D sequence")
    n = probs.shape[0]
    g = grid.size
    out = np.empty((n, g))
    for s in range(0, n, chunk):
        p = probs[s:s + chunk].reshape(min(chunk, n - s), -1)
        if not np.isfinite(p).all():
            raise InputError("probs contain NaN or infinite values")
        m = gts[s:s + chunk].reshape(p.shape)
        b = p.shape[0]
        # reach = number of grid points tau_j with p >= tau_j  (0..G)
        reach = np.searchsorted(grid, p.astype(np.float64), side="right")
        flat = (reach + (g + 1) * np.arange(b)[:, None]).ravel()
        hist_all = np.bincount(flat, minlength=b * (g + 1)).reshape(b, g + 1)
        hist_fg = np.bincount(flat, weights=m.ravel().astype(np.float64), minlength=b * (g + 1)).reshape(b, g + 1)
        # count of pixels with reach > j, i.e. p >= tau_j, for j = 0..G-1
        n_pred = np.cumsum(hist_all[:, ::-1], axis=1)[:, ::-1][:, 1:]
        inter = np.cumsum(hist_fg[:, ::-1], axis=1)[:, ::-1][:, 1:]
        ng = np.count_nonzero(m, axis=1)[:, None]
        union = n_pred + ng - inter
        out[s:s + b] = _ratio(inter, union, (n_pred == 0) & (ng == 0))
    return out

