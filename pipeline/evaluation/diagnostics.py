"""Threshold diagnostics: the pixel reliability diagram and ECE of P = sigmoid(Z), the predicted over
reference foreground area across tau, and the target size classes.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from pipeline.runtime.errors import InputError
from pipeline.metrics import threshold_counts

__all__ = ["reliability_bins", "expected_calibration_error", "area_ratio_curve", "median_area_ratio",
           "target_fractions", "target_size_class"]


@dataclasses.dataclass(frozen=True)
class Reliability:
    """A reliability diagram: per bin the mean P (``confidence``), the reference-foreground fraction
    (``frequency``; both NaN when empty) and the pixel ``count``; ``edges`` [B+1].
    """

    edges: np.ndarray
    confidence: np.ndarray
    frequency: np.ndarray
    count: np.ndarray


def reliability_bins(probs, gts, n_bins: int = 10, *, chunk: int = 16) -> Reliability:
    """Reliability diagram of ``probs`` [N,H,W] in [0, 1] against ``gts`` in ``n_bins`` equal-width bins (P = 1 in
    the last), ``chunk`` images at a time.
    """
    p_all, g_all = np.asarray(probs), np.asarray(gts, dtype=bool)
    if p_all.shape != g_all.shape or p_all.ndim != 3:
        raise InputError(f"probs {p_all.shape} and gts {g_all.shape} must be equal [N,H,W] shapes")
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
    """ECE = sum_b (n_b / N) |frequency_b - confidence_b| over the non-empty bins; NaN when all are empty."""
    conf = np.asarray(confidence, dtype=np.float64)
    freq = np.asarray(frequency, dtype=np.float64)
    n = np.asarray(count, dtype=np.float64)
    ok = n > 0
    total = n[ok].sum()
    if total == 0:
        return float("nan")
    return float(np.sum(n[ok] / total * np.abs(freq[ok] - conf[ok])))


def area_ratio_curve(probs, gts, grid, *, chunk: int = 16) -> np.ndarray:
    """|[P >= tau]| / |G| (eq:inference-mask) for every image and tau of ``grid`` -> float64 [N, G]; NaN where
    the reference is empty.
    """
    n_pred, _, n_ref = threshold_counts(probs, gts, grid, chunk=chunk)
    ref = n_ref[:, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(ref > 0, n_pred / np.maximum(ref, 1), np.nan)


def median_area_ratio(ratios) -> np.ndarray:
    """Median over images of an :func:`area_ratio_curve`, NaN skipped (NaN where every image is)."""
    r = np.asarray(ratios, dtype=np.float64)
    out = np.full(r.shape[1:], np.nan)
    ok = np.isfinite(r).any(axis=0)
    if ok.any():
        out[ok] = np.nanmedian(r[:, ok], axis=0)
    return out


def target_fractions(gts) -> np.ndarray:
    """|G| / (H W) of each mask of ``gts`` [N,H,W] -> float64 [N]."""
    g = np.asarray(gts)
    if g.ndim != 3:
        raise InputError(f"target_fractions: expected [N,H,W] masks, got shape {g.shape}")
    n = g.shape[0]
    hw = int(np.prod(g.shape[1:]))
    return np.count_nonzero(g.reshape(n, hw), axis=1) / float(max(hw, 1))


def target_size_class(fraction, max_fraction: float) -> np.ndarray:
    """``"empty"`` (f = 0), ``"tiny"`` (0 < f < ``max_fraction``) or ``"regular"``, per target fraction."""
    f = np.asarray(fraction, dtype=np.float64)
    if not 0 <= float(max_fraction) <= 1:
        raise InputError(f"target_size_class: max_fraction={max_fraction} must lie in [0, 1]")
    return np.where(f <= 0, "empty", np.where(f < float(max_fraction), "tiny", "regular"))
