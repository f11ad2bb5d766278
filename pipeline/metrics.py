"""Per-image segmentation metrics (paper, "Metrics and Statistical Analysis").

Masks are binary at the working resolution: ``pred`` and ``gt`` bool [H,W] (0/1 integers accepted), batches
[N,H,W].  Conventions, chosen so that per-image means are well defined:

* Image IoU = |P & G| / |P | G|; both masks empty -> 1, exactly one empty -> 0.
* Foreground precision = |P & G| / |P|, recall = |P & G| / |G|: both masks empty -> (1, 1), exactly one
  empty -> (0, 0).
* Boundary F1: the boundary of a mask is the mask minus its 3x3 erosion (one pixel wide, 8-connected); the
  frame edge is not boundary (outside the frame counts as foreground during the erosion).  A boundary pixel
  is matched when its Euclidean distance to the other mask's boundary is <= t (inclusive; t = 2 px by
  default).  Both masks empty -> 1, exactly one empty -> 0; two masks without a contour (both full-frame)
  -> 1, exactly one without a contour -> 0; BF-precision + BF-recall = 0 -> 0.
* Predicted foreground area ratio = (1/HW) sum_x P(x).
* Small-region IoU: IoU near the reference's small components (:func:`small_region_iou`); NaN without one.
* Calibration (eq:inference-mask): :func:`iou_curve` gives the Image IoU of [P >= tau] at every tau of a grid;
  the selection rule lives in :mod:`pipeline.thresholds`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from pipeline.runtime.errors import InputError
from pipeline.params import PAPER

__all__ = ["mask_ratio", "region_counts", "image_iou", "image_ious", "mask_agreement", "precision_recall",
           "boundary_f1", "scoring_reference", "score_masks", "per_image_metrics", "threshold_counts", "iou_curve"]

DEFAULT_TOLERANCE = PAPER.evaluate.bf1_tolerance
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


def mask_ratio(num: np.ndarray, den: np.ndarray, both_empty: np.ndarray) -> np.ndarray:
    """Divide ``num`` by ``den`` per image, with 0/0 = 1 where both masks are empty and 0 elsewhere.

    The convention of every ratio metric here: an empty prediction of an empty reference is perfect.

    Parameters
    ----------
    num, den : numpy.ndarray
        Pixel counts, broadcastable (e.g. |P & G| and |P | G| for IoU).
    both_empty : numpy.ndarray
        bool, True where prediction and reference are both empty.

    Returns
    -------
    numpy.ndarray
        float64 ratios, the broadcast shape of ``num`` and ``den``.
    """
    num = np.asarray(num, dtype=np.float64)
    den = np.asarray(den, dtype=np.float64)
    out = np.divide(num, den, out=np.zeros(np.broadcast(num, den).shape), where=den > 0)
    return np.where(den > 0, out, np.where(both_empty, 1.0, 0.0))


def region_counts(pred: np.ndarray, gt: np.ndarray):
    """Count |P & G|, |P| and |G| of each pair of masks.

    Parameters
    ----------
    pred, gt : numpy.ndarray
        bool masks [N,...] of one shape (N may be 0).

    Returns
    -------
    tuple of numpy.ndarray
        (intersection, predicted, reference) pixel counts, int [N] each.
    """
    n, pixels = pred.shape[0], int(np.prod(pred.shape[1:]))  # not -1: ambiguous when n = 0
    p = pred.reshape(n, pixels)
    g = gt.reshape(n, pixels)
    inter = np.count_nonzero(p & g, axis=1)
    np_ = np.count_nonzero(p, axis=1)
    ng = np.count_nonzero(g, axis=1)
    return inter, np_, ng


def image_iou(pred, gt) -> float:
    """Image IoU of one pair of masks.

    IoU = |P & G| / |P | G|.

    Parameters
    ----------
    pred, gt : array_like
        Predicted and reference masks, bool or 0/1 [H,W], equal shapes.

    Returns
    -------
    float
        IoU in [0, 1]; 1 when both masks are empty, 0 when exactly one is.

    Raises
    ------
    InputError
        A mask is not binary, not 2-D, or the shapes differ.
    """
    pred, gt = _pair(pred, gt)
    return float(image_ious(pred[None], gt[None])[0])


def image_ious(preds, gts) -> np.ndarray:
    """Image IoU of every pair of a batch (:func:`image_iou`, vectorised).

    Parameters
    ----------
    preds, gts : array_like
        Predicted and reference masks, bool or 0/1 [N,H,W], equal shapes.

    Returns
    -------
    numpy.ndarray
        float64 [N]; 1 where both masks are empty, 0 where exactly one is.

    Raises
    ------
    InputError
        A mask is not binary, not 3-D, or the shapes differ.
    """
    preds, gts = _pair(preds, gts, ndim=3)
    inter, np_, ng = region_counts(preds, gts)
    return mask_ratio(inter, np_ + ng - inter, (np_ == 0) & (ng == 0))


def mask_agreement(fast_logits: np.ndarray, reference_logits: np.ndarray, z_tau: float) -> float:
    """Mean per-image IoU of the masks two logit stacks give at one logit threshold.

    Used to compare a fast engine's masks with the fp32 reference's: 1 means the same masks (two empty masks
    agree, :func:`image_ious`).

    Parameters
    ----------
    fast_logits, reference_logits : numpy.ndarray
        Logits Z [N,1,H,W] or [N,H,W], equal N, H and W.
    z_tau : float
        The logit threshold: a mask is [Z >= z_tau] (eq:inference-mask, ``logit(tau)``).

    Returns
    -------
    float
        Mean Image IoU over the N images.
    """
    a, b = (np.asarray(x).reshape(len(x), *np.shape(x)[-2:]) >= z_tau for x in (fast_logits, reference_logits))
    return float(np.mean(image_ious(a, b)))


def precision_recall(pred, gt) -> tuple[float, float]:
    """Foreground precision and recall of one pair of masks.

    precision = |P & G| / |P|, recall = |P & G| / |G|.

    Parameters
    ----------
    pred, gt : array_like
        Predicted and reference masks, bool or 0/1 [H,W], equal shapes.

    Returns
    -------
    tuple of float
        (precision, recall); (1, 1) when both masks are empty, (0, 0) when exactly one is.

    Raises
    ------
    InputError
        A mask is not binary, not 2-D, or the shapes differ.
    """
    pred, gt = _pair(pred, gt)
    inter, np_, ng = region_counts(pred[None], gt[None])
    both = (np_ == 0) & (ng == 0)
    return float(mask_ratio(inter, np_, both)[0]), float(mask_ratio(inter, ng, both)[0])


def area_fraction(pred) -> float:
    """Predicted foreground area ratio (1/HW) sum_x P(x).

    Parameters
    ----------
    pred : array_like
        A bool or 0/1 mask of any shape.

    Returns
    -------
    float
        The foreground fraction in [0, 1]; 0 for a mask without pixels.

    Raises
    ------
    InputError
        The mask is not binary.
    """
    pred = _as_mask(pred, "pred")
    return float(np.count_nonzero(pred)) / pred.size if pred.size else 0.0


# A batch is stacked into one uint8 image, each mask followed by ``pad`` zero rows: one OpenCV call (SIMD,
# several times numpy's speed on bool arrays) equals N calls while its reach is <= ``pad`` rows.
_K3 = np.ones((3, 3), np.uint8)
_SMALL_LUT_ABOVE = 256  # more small components than this: label lookup table instead of per-box loop


def _stack(masks: np.ndarray, pad: int) -> np.ndarray:
    """Stack bool [N,H,W] into uint8 0/1 [N*(H+pad), W] with ``pad`` zero rows after each mask."""
    n, h, w = masks.shape
    buf = np.zeros((n, h + pad, w), np.uint8)
    buf[:, :h] = masks
    return buf.reshape(n * (h + pad), w)


def _counts(stacked: np.ndarray, n: int) -> np.ndarray:
    """Non-zero pixels of each mask of a stack (pad rows are zero) -> int64 [N]."""
    cv2 = _cv2()
    per = stacked.reshape(n, -1)
    return np.fromiter((cv2.countNonZero(row) for row in per), np.int64, count=n)


def _boundaries(stacked: np.ndarray, n: int, h: int) -> np.ndarray:
    """Stacked masks minus their 3x3 erosion, with outside the frame as foreground (pad rows set to 1)."""
    rows = stacked.reshape(n, -1, stacked.shape[1])
    rows[:, h:] = 1
    eroded = _cv2().erode(stacked, _K3)
    rows[:, h:] = 0
    return _cv2().subtract(stacked, eroded)


def tolerance_disk(tolerance: float) -> np.ndarray:
    """Return the disk of integer offsets within a Euclidean tolerance.

    The offsets (dy, dx) with dy^2 + dx^2 <= t^2: dilating a set by it marks exactly the pixels whose
    Euclidean distance to the set is <= t (inclusive), the Boundary-F1 match test without a distance transform.

    Parameters
    ----------
    tolerance : float
        The radius t in pixels, >= 0.

    Returns
    -------
    numpy.ndarray
        uint8 0/1 [2r+1, 2r+1] with r = floor(t).
    """
    r = int(np.floor(tolerance))
    d = np.arange(-r, r + 1)
    return ((d[:, None] ** 2 + d[None, :] ** 2) <= tolerance * tolerance).astype(np.uint8)


def mask_boundary(mask) -> np.ndarray:
    """Return the one-pixel-wide inner boundary of a mask.

    The mask minus its 3x3 erosion; the frame edge is not boundary (a full-frame mask has none).

    Parameters
    ----------
    mask : array_like
        A bool or 0/1 mask [H,W].

    Returns
    -------
    numpy.ndarray
        bool [H,W].

    Raises
    ------
    InputError
        The mask is not binary.
    """
    mask = _as_mask(mask, "mask")
    return _boundaries(_stack(mask[None], 1), 1, mask.shape[0])[:mask.shape[0]].astype(bool)


def _near(boundary: np.ndarray, tolerance: float) -> np.ndarray:
    """Stacked boundary dilated by :func:`tolerance_disk` (the pixels within ``tolerance`` of it)."""
    disk = tolerance_disk(tolerance)
    return _cv2().dilate(boundary, disk) if disk.shape[0] > 1 else boundary


def _boundary_counts(ps: np.ndarray, n: int, h: int, tolerance: float, bg: np.ndarray, near_g: np.ndarray):
    """Count boundary pixels and matched boundary pixels of stacked predictions against a prepared reference.

    Returns (|P-boundary|, |G-boundary|, matched P-boundary, matched G-boundary), int64 [N] each, from stacks
    padded by >= floor(tolerance) rows; ``bg``/``near_g``: G's boundary and its dilation.
    """
    cv2 = _cv2()
    bp = _boundaries(ps, n, h)
    return (_counts(bp, n), _counts(bg, n), _counts(cv2.bitwise_and(bp, near_g), n),
            _counts(cv2.bitwise_and(bg, _near(bp, tolerance)), n))


def _boundary_counts_torch(preds: np.ndarray, gts: np.ndarray, tolerance: float, device):
    """:func:`_boundary_counts` with torch on ``device`` from bool [N,H,W]; the same integers."""
    import torch
    import torch.nn.functional as F

    disk = torch.from_numpy(tolerance_disk(tolerance).astype(np.float32))[None, None].to(device)
    r = disk.shape[-1] // 2
    with torch.inference_mode():
        m = torch.from_numpy(np.ascontiguousarray(np.stack([preds, gts], 1))).to(device)  # [N,2,H,W] bool
        mf = m.flatten(0, 1)[:, None].float()                                             # [2N,1,H,W]
        # max-pooling ignores its padding: the frame edge is not boundary
        bnd = mf - (1 - F.max_pool2d(1 - mf, 3, stride=1, padding=1))
        near = (F.conv2d(bnd, disk, padding=r) > 0).view(len(preds), 2, *mf.shape[-2:])  # exact in float32
        bnd = bnd.view_as(near) > 0
        counts = bnd.flatten(2).sum(-1)                                                   # [N,2]
        hit_p = (bnd[:, 0] & near[:, 1]).flatten(1).sum(-1)
        hit_g = (bnd[:, 1] & near[:, 0]).flatten(1).sum(-1)
        out = torch.stack([counts[:, 0], counts[:, 1], hit_p, hit_g]).cpu().numpy().astype(np.int64)
    return out[0], out[1], out[2], out[3]


def _bf1_from_counts(np_: np.ndarray, ng: np.ndarray, nbp: np.ndarray, nbg: np.ndarray,
                     hit_p: np.ndarray, hit_g: np.ndarray) -> np.ndarray:
    """Boundary F1 per image; two contour-less (full-frame) masks -> 1, one -> 0; P + R = 0 -> 0."""
    precision = np.divide(hit_p, nbp, out=np.zeros(len(nbp)), where=nbp > 0)
    recall = np.divide(hit_g, nbg, out=np.zeros(len(nbg)), where=nbg > 0)
    s = precision + recall
    f1 = np.divide(2 * precision * recall, s, out=np.zeros(len(s)), where=s > 0)
    f1 = np.where((nbp == 0) | (nbg == 0), np.where((nbp == 0) & (nbg == 0), 1.0, 0.0), f1)
    p_any, g_any = np_ > 0, ng > 0
    return np.where(p_any != g_any, 0.0, np.where(~p_any & ~g_any, 1.0, f1))


def boundary_f1(pred, gt, tolerance: float = DEFAULT_TOLERANCE) -> float:
    """Boundary F1 of one pair of masks.

    A boundary (:func:`mask_boundary`) pixel of P is matched when its Euclidean distance to G's boundary is
    <= ``tolerance``; BF-precision = matched P-boundary / |P-boundary|, BF-recall the same from G's side,
    BF1 = 2 PR / (P + R).

    Parameters
    ----------
    pred, gt : array_like
        Predicted and reference masks, bool or 0/1 [H,W], equal shapes.
    tolerance : float, optional
        Matching radius in pixels (inclusive); default ``evaluate.bf1_tolerance`` (2 px at 384x384).

    Returns
    -------
    float
        BF1 in [0, 1].  Both masks empty -> 1, exactly one empty -> 0; no contour in either mask (both
        full-frame) -> 1, no contour in exactly one -> 0; P + R = 0 -> 0.

    Raises
    ------
    InputError
        A mask is not binary, not 2-D, the shapes differ, or ``tolerance`` < 0.
    """
    pred, gt = _pair(pred, gt)
    if tolerance < 0:
        raise InputError(f"boundary_f1: tolerance={tolerance!r} must be >= 0")
    return float(per_image_metrics(pred[None], gt[None], tolerance)["bf1"][0])


def _small_regions_stacked(gs: np.ndarray, n: int, h: int, w: int, max_fraction: float, margin: int):
    """(region R, small components S, |S| per image) as stacks, or None without a small component."""
    cv2 = _cv2()
    n_lab, labels, stats, _ = cv2.connectedComponentsWithStats(gs, connectivity=8)
    small_ids = np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] < max_fraction * h * w) + 1
    if small_ids.size == 0:
        return None
    if small_ids.size > _SMALL_LUT_ABOVE:
        lut = np.zeros(n_lab, np.uint8)
        lut[small_ids] = 1
        small = lut[labels]
    else:  # few: mark each inside its bounding box, no pass over the whole stack
        small = np.zeros_like(gs)
        for k in small_ids:
            x, y, bw, bh = stats[k, :4]
            box = (slice(y, y + bh), slice(x, x + bw))
            small[box] |= (labels[box] == k).view(np.uint8)
    region = small
    if margin > 0:
        region = cv2.dilate(small, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1,) * 2))
    return cv2.subtract(region, cv2.subtract(gs, small)), small, _counts(small, n)


def _small_region_ious_stacked(ps: np.ndarray, n: int, found) -> np.ndarray:
    """Small-region IoU per image against ``found`` = :func:`_small_regions_stacked` (NaN where none)."""
    cv2 = _cv2()
    if found is None:
        return np.full(n, np.nan)
    region, small, n_small = found
    p = cv2.bitwise_and(ps, region)
    inter, union = _counts(cv2.bitwise_and(p, small), n), _counts(cv2.bitwise_or(p, small), n)
    return np.divide(inter, union, out=np.full(n, np.nan), where=n_small > 0)


def small_region_iou(pred, gt, max_fraction: float = DEFAULT_SMALL_FRACTION,
                     margin: int = DEFAULT_SMALL_MARGIN) -> float:
    """IoU restricted to small reference objects (a supplementary diagnostic of the paper).

    S = the union of G's 8-connected components smaller than ``max_fraction`` * H * W pixels; R = S dilated by a
    Euclidean disk of radius ``margin`` px, minus the larger components' pixels (they neither help nor hurt).
    Small-region IoU = |P & S| / |(P & R) | S|: missed small parts and false positives within ``margin`` px of
    them both count.

    Parameters
    ----------
    pred, gt : array_like
        Predicted and reference masks, bool or 0/1 [H,W], equal shapes.
    max_fraction : float, optional
        A component is small below this fraction of the frame; default ``evaluate.small_region_max_fraction``
        (0.01).
    margin : int, optional
        Neighbourhood radius in pixels (default 3).

    Returns
    -------
    float
        The IoU in [0, 1]; NaN when G has no small component (the image does not enter a mean).

    Raises
    ------
    InputError
        A mask is not binary, not 2-D, or the shapes differ.
    """
    pred, gt = _pair(pred, gt)
    return float(per_image_metrics(pred[None], gt[None], max_fraction=max_fraction, margin=margin)["small_iou"][0])


METRIC_NAMES = ("iou", "bf1", "precision", "recall", "area_ratio", "small_iou")


@dataclasses.dataclass(frozen=True, eq=False)
class ScoringReference:
    """The reference side of :func:`per_image_metrics`, prepared once by :func:`scoring_reference`.

    Reused for every prediction set scored against the same masks (:func:`score_masks`).  Masks are stacked
    into one uint8 image, each followed by ``pad`` zero rows, so one OpenCV call serves the whole batch.

    Attributes
    ----------
    gts : numpy.ndarray
        The reference masks, bool [N,H,W].
    tolerance : float
        Boundary-F1 matching radius (px).
    max_fraction : float
        Small-region threshold as a fraction of the frame.
    margin : int
        Small-region neighbourhood radius (px).
    pad : int
        Zero rows after each mask in the stacks.
    stacked : numpy.ndarray
        uint8 0/1 [N*(H+pad), W] stack of ``gts``.
    count : numpy.ndarray
        Foreground pixels of each reference, int64 [N].
    boundary : numpy.ndarray
        The stacked reference boundaries.
    near_boundary : numpy.ndarray
        The boundaries dilated by :func:`tolerance_disk`.
    small : tuple or None
        (region R, small components S, |S| per image) stacks; None when no reference has a small component.
    """

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
        """Return the number of reference masks N."""
        return len(self.gts)


def scoring_reference(gts, tolerance: float = DEFAULT_TOLERANCE, *, max_fraction: float = DEFAULT_SMALL_FRACTION,
                      margin: int = DEFAULT_SMALL_MARGIN) -> ScoringReference:
    """Prepare a :class:`ScoringReference` of reference masks for :func:`score_masks`.

    Parameters
    ----------
    gts : array_like
        Reference masks, bool or 0/1 [N,H,W].
    tolerance : float, optional
        Boundary-F1 matching radius in pixels (default ``evaluate.bf1_tolerance``).
    max_fraction : float, optional
        Small-region threshold (default ``evaluate.small_region_max_fraction``).
    margin : int, optional
        Small-region neighbourhood radius in pixels (default 3).

    Returns
    -------
    ScoringReference
        The prepared reference.

    Raises
    ------
    InputError
        A mask is not binary, the masks are not 3-D, or ``tolerance`` < 0.
    """
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
    """Score predictions against a prepared reference: :func:`per_image_metrics` without redoing the reference side.

    Parameters
    ----------
    preds : array_like
        Predicted masks, bool or 0/1 [N,H,W], the reference's shape.
    reference : ScoringReference
        From :func:`scoring_reference`.
    device : str or torch.device, optional
        Where torch runs the Boundary-F1 morphology (same integers); None (default): OpenCV on the CPU.

    Returns
    -------
    dict of str to numpy.ndarray
        float64 [N] per name of :data:`METRIC_NAMES` (empty arrays for N = 0), with the single-image functions'
        conventions.

    Raises
    ------
    InputError
        A mask is not binary or the shapes differ from the reference's.
    """
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
        nbp, nbg, hit_p, hit_g = _boundary_counts(ps, n, h, reference.tolerance, reference.boundary,
                                                  reference.near_boundary)
    else:
        nbp, nbg, hit_p, hit_g = _boundary_counts_torch(preds, reference.gts, reference.tolerance, device)
    return {
        "iou": mask_ratio(inter, np_ + ng - inter, both),
        "bf1": _bf1_from_counts(np_, ng, nbp, nbg, hit_p, hit_g),
        "precision": mask_ratio(inter, np_, both),
        "recall": mask_ratio(inter, ng, both),
        "area_ratio": np_ / float(h * w),
        "small_iou": _small_region_ious_stacked(ps, n, reference.small),
    }


def per_image_metrics(preds, gts, tolerance: float = DEFAULT_TOLERANCE, *,
                      max_fraction: float = DEFAULT_SMALL_FRACTION,
                      margin: int = DEFAULT_SMALL_MARGIN, device=None) -> dict[str, np.ndarray]:
    """Compute every metric of :data:`METRIC_NAMES` for N pairs of masks at once.

    The values of :func:`image_iou`, :func:`boundary_f1`, :func:`precision_recall`, :func:`area_fraction` and
    :func:`small_region_iou`, with their conventions.

    Parameters
    ----------
    preds, gts : array_like
        Predicted and reference masks, bool or 0/1 [N,H,W], equal shapes.
    tolerance : float, optional
        Boundary-F1 matching radius in pixels (default ``evaluate.bf1_tolerance``).
    max_fraction : float, optional
        Small-region threshold (default ``evaluate.small_region_max_fraction``).
    margin : int, optional
        Small-region neighbourhood radius in pixels (default 3).
    device : str or torch.device, optional
        Where torch runs the Boundary-F1 morphology; None (default): OpenCV.

    Returns
    -------
    dict of str to numpy.ndarray
        ``iou, bf1, precision, recall, area_ratio, small_iou``, each float64 [N].

    Raises
    ------
    InputError
        A mask is not binary, not 3-D, the shapes differ, or ``tolerance`` < 0.
    """
    preds, gts = _pair(preds, gts, ndim=3)
    return score_masks(preds, scoring_reference(gts, tolerance, max_fraction=max_fraction, margin=margin),
                       device=device)


def threshold_counts(probs, gts, grid, *, chunk: int = 16) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Count predicted and overlapping pixels of M = [P >= tau] (eq:inference-mask) at every tau of a grid.

    One pass over the pixels: each pixel is binned by the grid points it reaches, then the bins are cumulated.

    Parameters
    ----------
    probs : array_like
        Probabilities P, float [N,H,W], finite.
    gts : array_like
        Reference masks, bool or 0/1 [N,H,W].
    grid : array_like
        The thresholds, a non-empty, finite, strictly increasing 1-D sequence of G values.
    chunk : int, optional
        Images per pass (bounds the memory; default 16).

    Returns
    -------
    tuple of numpy.ndarray
        (|M| float64 [N,G], |M & G| float64 [N,G], |G| float64 [N]).

    Raises
    ------
    InputError
        Shapes differ or are not [N,H,W], the grid is not as required, a mask is not binary, or ``probs``
        holds NaN or infinity.
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
        reach = np.searchsorted(grid, p.astype(np.float64), side="right")
        flat = (reach + (g + 1) * np.arange(b)[:, None]).ravel()
        hist_all = np.bincount(flat, minlength=b * (g + 1)).reshape(b, g + 1)
        hist_fg = np.bincount(flat, weights=m.ravel().astype(np.float64), minlength=b * (g + 1)).reshape(b, g + 1)
        n_pred[s:s + b] = np.cumsum(hist_all[:, ::-1], axis=1)[:, ::-1][:, 1:]
        inter[s:s + b] = np.cumsum(hist_fg[:, ::-1], axis=1)[:, ::-1][:, 1:]
        n_ref[s:s + b] = np.count_nonzero(m, axis=1)
    return n_pred, inter, n_ref


def iou_curve(probs, gts, grid, *, chunk: int = 16) -> np.ndarray:
    """Image IoU of M = [P >= tau] (eq:inference-mask) for every image and every tau of a grid.

    Parameters
    ----------
    probs : array_like
        Probabilities P, float [N,H,W].
    gts : array_like
        Reference masks, bool or 0/1 [N,H,W].
    grid : array_like
        Strictly increasing thresholds, G values.
    chunk : int, optional
        Images per pass (default 16).

    Returns
    -------
    numpy.ndarray
        float64 [N,G]; 1 where both masks are empty, 0 where exactly one is.

    Raises
    ------
    InputError
        As :func:`threshold_counts`.
    """
    n_pred, inter, n_ref = threshold_counts(probs, gts, grid, chunk=chunk)
    ng = n_ref[:, None]
    return mask_ratio(inter, n_pred + ng - inter, (n_pred == 0) & (ng == 0))

