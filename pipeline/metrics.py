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
  exact Euclidean distance to the nearest boundary pixel of G is <= t (computed as a dilation of G's
  boundary by the disk of integer offsets with dy^2 + dx^2 <= t^2, which is exact);
  BF-precision = matched P-boundary / |P-boundary|, BF-recall symmetric,
  BF1 = 2PR / (P + R) (0 when P + R = 0).  Both masks empty -> 1, exactly one empty -> 0; two
  full-frame masks (no contour at all) -> 1, exactly one contour-less -> 0.
* Predicted foreground area ratio = mean(P).
* Small-region IoU (``small_region_iou``): IoU restricted to the neighbourhood of small ground-truth
  objects -- see that function; NaN when the ground truth has no small component.
* Calibration (eq:inference-mask): :func:`iou_curve` gives the Image IoU of M = [P >= tau] at every tau
  of a grid; the selection rule lives in pipeline.thresholds (calibrate_threshold).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from pipeline.runtime.errors import InputError
from pipeline.params import PAPER

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


def mask_agreement(fast_logits: np.ndarray, reference_logits: np.ndarray, z_tau: float) -> float:
    """Mean per-image IoU of the masks [Z >= z_tau] of a fast engine and of the fp32 reference (both
    [N,1,H,W] or [N,H,W]); 1 = the same masks (:func:`image_ious`: both empty -> 1)."""
    a = np.asarray(fast_logits).reshape(len(fast_logits), *np.shape(fast_logits)[-2:]) >= z_tau
    b = np.asarray(reference_logits).reshape(len(reference_logits), *np.shape(reference_logits)[-2:]) >= z_tau
    return float(np.mean(image_ious(a, b)))


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
# Stacked morphology: N masks in one OpenCV call
# --------------------------------------------------------------------------------------------------
# The batch is laid out as one uint8 (0/1) image: the N masks one above the other, each followed by
# ``pad`` rows of 0, so one 2-D OpenCV call equals N calls on the masks as long as the operation's
# reach is <= ``pad`` rows.  OpenCV's SIMD loops (erode, dilate, bitwise ops, countNonZero) are several
# times faster than numpy's on bool arrays, and the evaluation scores every run's test set twice.
_K3 = np.ones((3, 3), np.uint8)
_SMALL_LUT_ABOVE = 256  # more small components than this: label lookup table instead of per-box loop


def _stack(masks: np.ndarray, pad: int) -> np.ndarray:
    """bool [N,H,W] -> uint8 0/1 [N*(H+pad), W] with ``pad`` zero rows after each mask."""
    n, h, w = masks.shape
    buf = np.zeros((n, h + pad, w), np.uint8)
    buf[:, :h] = masks
    return buf.reshape(n * (h + pad), w)


def _unstack(stacked: np.ndarray, n: int, h: int) -> np.ndarray:
    """uint8 stack -> bool [N,H,W] (the pad rows dropped)."""
    return stacked.reshape(n, -1, stacked.shape[1])[:, :h].astype(bool)


def _counts(stacked: np.ndarray, n: int) -> np.ndarray:
    """Non-zero pixels of each mask of a stack (pad rows are zero) -> int64 [N]."""
    cv2 = _cv2()
    per = stacked.reshape(n, -1)
    return np.fromiter((cv2.countNonZero(row) for row in per), np.int64, count=n)


def _boundaries(stacked: np.ndarray, n: int, h: int) -> np.ndarray:
    """Stacked masks minus their 3x3 erosion.  During the erosion the pad rows are set to 1: outside
    the frame counts as foreground (OpenCV's default border does the same at the stack's ends), so
    the frame edge is not boundary."""
    rows = stacked.reshape(n, -1, stacked.shape[1])
    rows[:, h:] = 1
    eroded = _cv2().erode(stacked, _K3)
    rows[:, h:] = 0
    return _cv2().subtract(stacked, eroded)


def tolerance_disk(tolerance: float) -> np.ndarray:
    """uint8 [2r+1, 2r+1], r = floor(t): the offsets (dy, dx) with dy^2 + dx^2 <= t^2.  Dilating a
    set by it marks exactly the pixels whose Euclidean distance to the set is <= t (inclusive): the
    Boundary-F1 match test without a distance transform."""
    r = int(np.floor(tolerance))
    d = np.arange(-r, r + 1)
    return ((d[:, None] ** 2 + d[None, :] ** 2) <= tolerance * tolerance).astype(np.uint8)


def mask_boundaries(masks) -> np.ndarray:
    """:func:`mask_boundary` of every mask of bool [N,H,W] (one stacked erosion)."""
    masks = _as_mask(masks, "masks")
    n, h, _ = masks.shape
    if n == 0:
        return masks.copy()
    return _unstack(_boundaries(_stack(masks, 1), n, h), n, h)


def mask_boundary(mask) -> np.ndarray:
    """One-pixel-wide inner boundary: mask minus its 3x3 erosion (frame edge is not boundary)."""
    mask = _as_mask(mask, "mask")
    return mask_boundaries(mask[None])[0]


def _near(boundary: np.ndarray, tolerance: float) -> np.ndarray:
    """Stacked boundary dilated by :func:`tolerance_disk` (the pixels within ``tolerance`` of it)."""
    disk = tolerance_disk(tolerance)
    return _cv2().dilate(boundary, disk) if disk.shape[0] > 1 else boundary


def _boundary_counts(ps: np.ndarray, gs: np.ndarray, n: int, h: int, tolerance: float, bg=None, near_g=None):
    """(|P-boundary|, |G-boundary|, matched P-boundary, matched G-boundary) int64 [N] each, from
    stacks padded by >= floor(tolerance) rows: a boundary pixel is matched when it lies in the other
    boundary dilated by :func:`tolerance_disk`.  ``bg``/``near_g``: G's boundary and its dilation when
    already known (:class:`ScoringReference`)."""
    cv2 = _cv2()
    bp = _boundaries(ps, n, h)
    if bg is None:
        bg = _boundaries(gs, n, h)
        near_g = _near(bg, tolerance)
    return (_counts(bp, n), _counts(bg, n), _counts(cv2.bitwise_and(bp, near_g), n),
            _counts(cv2.bitwise_and(bg, _near(bp, tolerance)), n))


def _boundary_counts_torch(preds: np.ndarray, gts: np.ndarray, tolerance: float, device):
    """:func:`_boundary_counts` with torch on ``device`` (GPU where present), from bool [N,H,W]:
    erosion = 1 - maxpool(1 - M) (max-pooling ignores its padding, so the frame edge is not
    boundary), dilation by the tolerance disk = conv2d > 0 (small integer sums, exact in float32)."""
    import torch
    import torch.nn.functional as F

    disk = torch.from_numpy(tolerance_disk(tolerance).astype(np.float32))[None, None].to(device)
    r = disk.shape[-1] // 2
    with torch.inference_mode():
        m = torch.from_numpy(np.ascontiguousarray(np.stack([preds, gts], 1))).to(device)  # [N,2,H,W] bool
        mf = m.flatten(0, 1)[:, None].float()                                             # [2N,1,H,W]
        bnd = mf - (1 - F.max_pool2d(1 - mf, 3, stride=1, padding=1))                     # mask & ~erosion
        near = (F.conv2d(bnd, disk, padding=r) > 0).view(len(preds), 2, *mf.shape[-2:])
        bnd = bnd.view_as(near) > 0
        counts = bnd.flatten(2).sum(-1)                                                   # [N,2]
        hit_p = (bnd[:, 0] & near[:, 1]).flatten(1).sum(-1)
        hit_g = (bnd[:, 1] & near[:, 0]).flatten(1).sum(-1)
        out = torch.stack([counts[:, 0], counts[:, 1], hit_p, hit_g]).cpu().numpy().astype(np.int64)
    return out[0], out[1], out[2], out[3]


def _bf1_from_counts(np_: np.ndarray, ng: np.ndarray, nbp: np.ndarray, nbg: np.ndarray,
                     hit_p: np.ndarray, hit_g: np.ndarray) -> np.ndarray:
    """Boundary F1 per image from mask sizes, boundary sizes and matched boundary pixels, with the
    module docstring's conventions: both masks empty -> 1, one empty -> 0; both contour-less (two
    full-frame masks) -> 1, one contour-less -> 0; P + R = 0 -> 0."""
    precision = np.divide(hit_p, nbp, out=np.zeros(len(nbp)), where=nbp > 0)
    recall = np.divide(hit_g, nbg, out=np.zeros(len(nbg)), where=nbg > 0)
    s = precision + recall
    f1 = np.divide(2 * precision * recall, s, out=np.zeros(len(s)), where=s > 0)
    f1 = np.where((nbp == 0) | (nbg == 0), np.where((nbp == 0) & (nbg == 0), 1.0, 0.0), f1)
    p_any, g_any = np_ > 0, ng > 0
    return np.where(p_any != g_any, 0.0, np.where(~p_any & ~g_any, 1.0, f1))


def boundary_f1(pred, gt, tolerance: float = DEFAULT_TOLERANCE) -> float:
    """Boundary F1 with a ``tolerance``-pixel (Euclidean, inclusive) matching radius; see the module
    docstring for the boundary definition and the empty-mask conventions."""
    pred, gt = _pair(pred, gt)
    if tolerance < 0:
        raise InputError(f"boundary_f1: tolerance={tolerance!r} must be >= 0")
    h = pred.shape[0]
    pad = max(1, int(np.floor(tolerance)))
    ps, gs = _stack(pred[None], pad), _stack(gt[None], pad)
    return float(_bf1_from_counts(_counts(ps, 1), _counts(gs, 1), *_boundary_counts(ps, gs, 1, h, float(tolerance)))[0])


# --------------------------------------------------------------------------------------------------
# Small-region IoU
# --------------------------------------------------------------------------------------------------
def _small_regions_stacked(gs: np.ndarray, n: int, h: int, w: int, max_fraction: float, margin: int):
    """(region R, small components S, |S| per image) -- R and S as uint8 stacks (pad >= max(1, margin)
    rows) -- or None when no ground truth of the batch has a small component (:func:`small_region_iou`)."""
    cv2 = _cv2()
    n_lab, labels, stats, _ = cv2.connectedComponentsWithStats(gs, connectivity=8)
    small_ids = np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] < max_fraction * h * w) + 1
    if small_ids.size == 0:
        return None
    if small_ids.size > _SMALL_LUT_ABOVE:
        lut = np.zeros(n_lab, np.uint8)
        lut[small_ids] = 1
        small = lut[labels]
    else:  # few small components: mark each inside its bounding box (no pass over the whole stack)
        small = np.zeros_like(gs)
        for k in small_ids:
            x, y, bw, bh = stats[k, :4]
            box = (slice(y, y + bh), slice(x, x + bw))
            small[box] |= (labels[box] == k).view(np.uint8)
    large = cv2.subtract(gs, small)
    if margin > 0:
        disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1, 2 * margin + 1))
        region = cv2.dilate(small, disk)
    else:
        region = small.copy()
    return cv2.subtract(region, large), small, _counts(small, n)


def _small_region_ious_stacked(ps: np.ndarray, n: int, found) -> np.ndarray:
    """Small-region IoU per image from the stacked predictions and ``found`` =
    :func:`_small_regions_stacked` of the references (NaN where a reference has no small component)."""
    cv2 = _cv2()
    if found is None:
        return np.full(n, np.nan)
    region, small, n_small = found
    p = cv2.bitwise_and(ps, region)
    inter, union = _counts(cv2.bitwise_and(p, small), n), _counts(cv2.bitwise_or(p, small), n)
    return np.divide(inter, union, out=np.full(n, np.nan), where=n_small > 0)


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
    h, w = gt.shape
    pad = max(1, int(margin))
    found = _small_regions_stacked(_stack(gt[None], pad), 1, h, w, max_fraction, margin)
    return float(_small_region_ious_stacked(_stack(pred[None], pad), 1, found)[0])


# --------------------------------------------------------------------------------------------------
# Batched
# --------------------------------------------------------------------------------------------------
METRIC_NAMES = ("iou", "bf1", "precision", "recall", "area_ratio", "small_iou")


@dataclasses.dataclass(frozen=True, eq=False)
class ScoringReference:
    """The ground-truth side of :func:`per_image_metrics` for N reference masks, computed once by
    :func:`scoring_reference` and reused for every prediction set scored against them (the evaluate
    stage scores each run at two thresholds, every run against the same test masks).  Holds the
    stacked masks (uint8, ``pad`` zero rows after each), their counts, boundaries and tolerance
    dilations, and the small-region masks (``small`` = None when no mask has a small component)."""

    gts: np.ndarray
    tolerance: float
    max_fraction: float
    margin: int
    pad: int
    stacked: np.ndarray
    count: np.ndarray
    boundary: np.ndarray
    near_boundary: np.ndarray
    small: tuple | None

    def __len__(self) -> int:
        return len(self.gts)


def scoring_reference(gts, tolerance: float = DEFAULT_TOLERANCE, *, max_fraction: float = DEFAULT_SMALL_FRACTION,
                      margin: int = DEFAULT_SMALL_MARGIN) -> ScoringReference:
    """:class:`ScoringReference` of bool [N,H,W] reference masks (for :func:`score_masks`)."""
    gts = _as_mask(gts, "gts")
    if gts.ndim != 3:
        raise InputError(f"expected 3-D masks, got shape {gts.shape}")
    if tolerance < 0:
        raise InputError(f"per_image_metrics: tolerance={tolerance!r} must be >= 0")
    tolerance = float(tolerance)
    n, h, w = gts.shape
    pad = max(1, int(np.floor(tolerance)), int(margin))
    gs = _stack(gts, pad)
    bg = _boundaries(gs, n, h) if n else gs
    return ScoringReference(gts=gts, tolerance=tolerance, max_fraction=float(max_fraction), margin=int(margin),
                            pad=pad, stacked=gs, count=_counts(gs, n), boundary=bg,
                            near_boundary=_near(bg, tolerance) if n else gs,
                            small=_small_regions_stacked(gs, n, h, w, max_fraction, margin) if n else None)


def score_masks(preds, reference: ScoringReference, *, device=None) -> dict[str, np.ndarray]:
    """:func:`per_image_metrics` of ``preds`` bool [N,H,W] against a prepared :class:`ScoringReference`
    (same numbers; the reference side is not recomputed)."""
    preds = _as_mask(preds, "preds")
    if preds.shape != reference.gts.shape:
        raise InputError(f"pred {preds.shape} and gt {reference.gts.shape} shapes differ")
    n, h, w = preds.shape
    if n == 0:
        return {k: np.zeros(0) for k in METRIC_NAMES}
    ps = _stack(preds, reference.pad)
    np_, ng = _counts(ps, n), reference.count
    inter = _counts(_cv2().bitwise_and(ps, reference.stacked), n)
    both = (np_ == 0) & (ng == 0)
    if device is None:
        nbp, nbg, hit_p, hit_g = _boundary_counts(ps, reference.stacked, n, h, reference.tolerance,
                                                  reference.boundary, reference.near_boundary)
    else:
        nbp, nbg, hit_p, hit_g = _boundary_counts_torch(preds, reference.gts, reference.tolerance, device)
    return {
        "iou": _ratio(inter, np_ + ng - inter, both),
        "bf1": _bf1_from_counts(np_, ng, nbp, nbg, hit_p, hit_g),
        "precision": _ratio(inter, np_, both),
        "recall": _ratio(inter, ng, both),
        "area_ratio": np_ / float(h * w),
        "small_iou": _small_region_ious_stacked(ps, n, reference.small),
    }


def per_image_metrics(preds, gts, tolerance: float = DEFAULT_TOLERANCE, *,
                      max_fraction: float = DEFAULT_SMALL_FRACTION,
                      margin: int = DEFAULT_SMALL_MARGIN, device=None) -> dict[str, np.ndarray]:
    """Every metric for N images at once: preds, gts bool [N,H,W] -> dict of float64 [N] arrays
    ``iou, bf1, precision, recall, area_ratio, small_iou`` (the single-image functions' values).

    Vectorised over the batch: the masks are stacked into one image and every step (counts,
    erosions, the tolerance-disk dilation that replaces distance transforms, the connected-component
    labelling) is one OpenCV call for the whole batch.  ``device`` (a torch device such as ``cuda``)
    runs the Boundary-F1 morphology there instead; None = OpenCV on the CPU.  Same numbers either way.
    To score several prediction sets against the same references, build the reference side once:
    ``score_masks(preds, scoring_reference(gts, ...))``.
    """
    preds, gts = _pair(preds, gts, ndim=3)
    return score_masks(preds, scoring_reference(gts, tolerance, max_fraction=max_fraction, margin=margin),
                       device=device)


# --------------------------------------------------------------------------------------------------
# Threshold calibration
# --------------------------------------------------------------------------------------------------
def threshold_counts(probs, gts, grid, *, chunk: int = 16) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel counts of M = [P >= tau] (eq:inference-mask) for every image and every tau of ``grid``
    (strictly increasing): ``(n_pred, inter, n_ref)`` = |M|, |M & G| float64 [N, G] and |G| float64 [N].

    One pass over the pixels: each probability is binned by the number of grid points it reaches,
    and cumulative counts give |M| and |M & G| at every tau (no per-tau loop).  The one counting
    core of :func:`iou_curve` and :func:`pipeline.evaluation.diagnostics.area_ratio_curve`.
    """
    probs = np.asarray(probs)
    gts = _as_mask(gts, "gts")
    grid = np.asarray(grid, dtype=np.float64)
    if probs.shape != gts.shape or probs.ndim != 3:
        raise InputError(f"probs {probs.shape} and gts {gts.shape} must be equal [N,H,W] shapes")
    if grid.ndim != 1 or grid.size == 0 or not np.isfinite(grid).all() or (np.diff(grid) <= 0).any():
        raise InputError("calibration grid must be a non-empty, finite, strictly increasing 1-D sequence")
    n = probs.shape[0]
    g = grid.size
    n_pred, inter, n_ref = np.empty((n, g)), np.empty((n, g)), np.empty(n)
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
        n_pred[s:s + b] = np.cumsum(hist_all[:, ::-1], axis=1)[:, ::-1][:, 1:]
        inter[s:s + b] = np.cumsum(hist_fg[:, ::-1], axis=1)[:, ::-1][:, 1:]
        n_ref[s:s + b] = np.count_nonzero(m, axis=1)
    return n_pred, inter, n_ref


def iou_curve(probs, gts, grid, *, chunk: int = 16) -> np.ndarray:
    """Image IoU of [P >= tau] (eq:inference-mask) for every image and every tau of ``grid``:
    float64 [N, G], from :func:`threshold_counts` (one pass over the pixels)."""
    n_pred, inter, n_ref = threshold_counts(probs, gts, grid, chunk=chunk)
    ng = n_ref[:, None]
    return _ratio(inter, n_pred + ng - inter, (n_pred == 0) & (ng == 0))

