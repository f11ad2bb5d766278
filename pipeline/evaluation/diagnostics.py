"""Threshold and calibration diagnostics (issue 17 item 3): why a student's fixed-tau and calibrated-tau
results can disagree.

Pure numpy functions on arrays (no I/O); the calibrate stage applies them to every run's validation
probabilities, the evaluate stage labels test images by target size, the report draws and explains
the results.

* :func:`reliability_bins` / :func:`expected_calibration_error` -- the pixel-level reliability diagram
  of P = sigmoid(Z): pixels binned by P into ``n_bins`` equal-width bins of [0, 1]; per bin the mean P
  (confidence), the fraction of reference-foreground pixels (frequency) and the pixel count.
  ECE = sum_b (n_b / N) |frequency_b - confidence_b| over the non-empty bins (Naeini et al. 2015,
  here over pixels).  A student whose probabilities are too high has frequency < confidence in the
  upper bins; its IoU-optimal tau then lies above 0.5.
* :func:`area_ratio_curve` / :func:`median_area_ratio` -- predicted foreground area of [P >= tau]
  (eq:inference-mask) divided by the reference area, per image and tau; the median over images.
  A ratio above 1 is foreground inflation.
* :func:`target_fractions` / :func:`target_size_class` -- the reference foreground fraction of each
  image and its size class: ``tiny`` (0 < fraction < ``evaluate.tiny_target_max_fraction``, 0.2 % of
  the frame), ``regular``, or ``empty`` (no reference foreground).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from pipeline.runtime.errors import InputError
from pipeline.metrics import threshold_counts

SIZE_CLASSES = ("tiny", "regular", "empty")


def _probs_and_masks(probs, gts) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(probs)
    g = np.asarray(gts)
    if p.shape != g.shape or p.ndim != 3:
        raise InputError(f"probs {p.shape} and gts {g.shape} must be equal [N,H,W] shapes")
    if g.dtype != bool:
        g = g.astype(bool)
    return p, g


# --------------------------------------------------------------------------------------------------
# Reliability diagram and ECE
# --------------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Reliability:
    """Per-bin statistics of a reliability diagram; ``edges`` float64 [B+1], the others [B].

    ``confidence``: mean predicted probability of the bin's pixels; ``frequency``: fraction of them
    that are reference foreground (both NaN for an empty bin); ``count``: pixels in the bin.
    """

    edges: np.ndarray
    confidence: np.ndarray
    frequency: np.ndarray
    count: np.ndarray


def reliability_bins(probs, gts, n_bins: int = 10, *, chunk: int = 16) -> Reliability:
    """Pixel-level reliability diagram of ``probs`` float [N,H,W] in [0, 1] against ``gts`` bool [N,H,W].

    Bin b holds the pixels with b/B <= P < (b+1)/B; P = 1 falls in the last bin.  Computed in chunks
    of ``chunk`` images (bounded memory).  InputError for mismatched shapes, non-finite or
    out-of-range probabilities, or ``n_bins < 1``.
    """
    p_all, g_all = _probs_and_masks(probs, gts)
    n_bins = int(n_bins)
    if n_bins < 1:
        raise InputError(f"reliability_bins: n_bins={n_bins} must be >= 1")
    sum_p = np.zeros(n_bins)
    sum_fg = np.zeros(n_bins)
    count = np.zeros(n_bins, dtype=np.int64)
    for s in range(0, p_all.shape[0], chunk):
        p = p_all[s:s + chunk].astype(np.float64).ravel()
        if not np.isfinite(p).all() or (p.size and (p.min() < 0 or p.max() > 1)):
            raise InputError("reliability_bins: probabilities must be finite and in [0, 1]")
        g = g_all[s:s + chunk].ravel()
        b = np.minimum((p * n_bins).astype(np.int64), n_bins - 1)
        count += np.bincount(b, minlength=n_bins)
        sum_p += np.bincount(b, weights=p, minlength=n_bins)
        sum_fg += np.bincount(b, weights=g.astype(np.float64), minlength=n_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        conf = np.where(count > 0, sum_p / np.maximum(count, 1), np.nan)
        freq = np.where(count > 0, sum_fg / np.maximum(count, 1), np.nan)
    return Reliability(np.linspace(0.0, 1.0, n_bins + 1), conf, freq, count)


def expected_calibration_error(confidence, frequency, count) -> float:
    """ECE = sum_b (n_b / N) |frequency_b - confidence_b| over bins with n_b > 0 (N = sum n_b).

    In [0, 1]; 0 for a perfectly calibrated predictor; NaN when every bin is empty.
    """
    conf = np.asarray(confidence, dtype=np.float64)
    freq = np.asarray(frequency, dtype=np.float64)
    n = np.asarray(count, dtype=np.float64)
    ok = n > 0
    total = n[ok].sum()
    if total == 0:
        return float("nan")
    return float(np.sum(n[ok] / total * np.abs(freq[ok] - conf[ok])))


# --------------------------------------------------------------------------------------------------
# Foreground area across tau
# --------------------------------------------------------------------------------------------------
def area_ratio_curve(probs, gts, grid, *, chunk: int = 16) -> np.ndarray:
    """Predicted over reference foreground area, |[P >= tau]| / |G|, for every image and every tau of
    ``grid`` (strictly increasing): float64 [N, G]; NaN for an image whose reference is empty.

    The counts come from :func:`pipeline.metrics.threshold_counts` (one pass over the pixels).
    """
    _probs_and_masks(probs, gts)
    n_pred, _, n_ref = threshold_counts(probs, gts, grid, chunk=chunk)
    ref = n_ref[:, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(ref > 0, n_pred / np.maximum(ref, 1), np.nan)


def median_area_ratio(ratios) -> np.ndarray:
    """Median over images (axis 0) of an :func:`area_ratio_curve`, skipping NaN (empty references);
    NaN at a tau where no image has a reference foreground."""
    r = np.asarray(ratios, dtype=np.float64)
    out = np.full(r.shape[1:], np.nan)
    ok = np.isfinite(r).any(axis=0)
    if ok.any():
        out[ok] = np.nanmedian(r[:, ok], axis=0)
    return out


# --------------------------------------------------------------------------------------------------
# Target size
# --------------------------------------------------------------------------------------------------
def target_fractions(gts) -> np.ndarray:
    """Reference foreground fraction |G| / (H W) of each mask of ``gts`` bool [N,H,W] -> float64 [N]."""
    g = np.asarray(gts)
    if g.ndim != 3:
        raise InputError(f"target_fractions: expected [N,H,W] masks, got shape {g.shape}")
    n = g.shape[0]
    hw = int(np.prod(g.shape[1:]))
    return np.count_nonzero(g.reshape(n, hw), axis=1) / float(max(hw, 1))


def target_size_class(fraction, max_fraction: float) -> np.ndarray:
    """Size class of each target fraction: ``"tiny"`` when 0 < f < ``max_fraction`` (strict),
    ``"empty"`` when f = 0, ``"regular"`` otherwise -> str array of the input's shape."""
    f = np.asarray(fraction, dtype=np.float64)
    if not 0 <= float(max_fraction) <= 1:
        raise InputError(f"target_size_class: max_fraction={max_fraction} must lie in [0, 1]")
    return np.where(f <= 0, "empty", np.where(f < float(max_fraction), "tiny", "regular"))
