"""Threshold diagnostics of P = sigmoid(Z).

The pixel reliability diagram and ECE, the predicted over reference foreground area across tau, and the target
size classes.
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
    """A reliability diagram of B bins.

    Attributes
    ----------
    edges : numpy.ndarray
        The bin edges [B+1], 0 to 1.
    confidence : numpy.ndarray
        The mean P per bin [B] (NaN when the bin is empty).
    frequency : numpy.ndarray
        The reference-foreground fraction per bin [B] (NaN when empty).
    count : numpy.ndarray
        The pixels per bin [B], int64.
    """

    edges: np.ndarray
    confidence: np.ndarray
    frequency: np.ndarray
    count: np.ndarray


def reliability_bins(probs, gts, n_bins: int = 10, *, chunk: int = 16) -> Reliability:
    """Bin the pixels' probabilities against their reference masks: a reliability diagram.

    Parameters
    ----------
    probs : array_like
        P [N, H, W], finite and in [0, 1].
    gts : array_like
        Reference masks [N, H, W].
    n_bins : int
        Equal-width bins over [0, 1] (P = 1 falls in the last), at least 1.
    chunk : int
        Images binned at a time (bounded memory).

    Returns
    -------
    Reliability
        Per bin the mean P, the reference-foreground fraction and the pixel count.

    Raises
    ------
    InputError
        Shapes that differ or are not [N, H, W], ``n_bins`` < 1, or a probability outside [0, 1] or not finite.
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
    """Compute the expected calibration error of a reliability diagram.

    ECE = sum_b (n_b / N) |frequency_b - confidence_b| over the non-empty bins b, N = sum_b n_b.

    Parameters
    ----------
    confidence : array_like
        Mean P per bin.
    frequency : array_like
        Reference-foreground fraction per bin.
    count : array_like
        Pixels per bin, n_b.

    Returns
    -------
    float
        The ECE; NaN when every bin is empty.
    """
    conf = np.asarray(confidence, dtype=np.float64)
    freq = np.asarray(frequency, dtype=np.float64)
    n = np.asarray(count, dtype=np.float64)
    ok = n > 0
    total = n[ok].sum()
    if total == 0:
        return float("nan")
    return float(np.sum(n[ok] / total * np.abs(freq[ok] - conf[ok])))


def area_ratio_curve(probs, gts, grid, *, chunk: int = 16) -> np.ndarray:
    """Compute the predicted over reference foreground area, |[P >= tau]| / |G|, per image and tau.

    The predicted mask is eq:inference-mask, M(x) = [P(x) >= tau].

    Parameters
    ----------
    probs : array_like
        P [N, H, W].
    gts : array_like
        Reference masks G [N, H, W].
    grid : array_like
        The thresholds tau [T].
    chunk : int
        Images counted at a time (bounded memory).

    Returns
    -------
    numpy.ndarray
        float64 [N, T]; NaN where the reference is empty.
    """
    n_pred, _, n_ref = threshold_counts(probs, gts, grid, chunk=chunk)
    ref = n_ref[:, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(ref > 0, n_pred / np.maximum(ref, 1), np.nan)


def median_area_ratio(ratios) -> np.ndarray:
    """Take the median over images of an :func:`area_ratio_curve`, NaN skipped.

    Parameters
    ----------
    ratios : array_like
        Area ratios [N, T].

    Returns
    -------
    numpy.ndarray
        float64 [T]; NaN where every image is.
    """
    r = np.asarray(ratios, dtype=np.float64)
    out = np.full(r.shape[1:], np.nan)
    ok = np.isfinite(r).any(axis=0)
    if ok.any():
        out[ok] = np.nanmedian(r[:, ok], axis=0)
    return out


def target_fractions(gts) -> np.ndarray:
    """Compute each reference mask's target fraction, |G| / (H W).

    Parameters
    ----------
    gts : array_like
        Masks [N, H, W].

    Returns
    -------
    numpy.ndarray
        float64 [N].

    Raises
    ------
    InputError
        ``gts`` is not [N, H, W].
    """
    g = np.asarray(gts)
    if g.ndim != 3:
        raise InputError(f"target_fractions: expected [N,H,W] masks, got shape {g.shape}")
    n = g.shape[0]
    hw = int(np.prod(g.shape[1:]))
    return np.count_nonzero(g.reshape(n, hw), axis=1) / float(max(hw, 1))


def target_size_class(fraction, max_fraction: float) -> np.ndarray:
    """Class each target by its fraction f: ``"empty"`` (f = 0), ``"tiny"`` (0 < f < ``max_fraction``) or ``"regular"``.

    Parameters
    ----------
    fraction : array_like
        Target fractions (:func:`target_fractions`).
    max_fraction : float
        The tiny class's upper bound, in [0, 1] (``evaluate.tiny_target_max_fraction``).

    Returns
    -------
    numpy.ndarray
        The class names, of ``fraction``'s shape.

    Raises
    ------
    InputError
        ``max_fraction`` outside [0, 1].
    """
    f = np.asarray(fraction, dtype=np.float64)
    if not 0 <= float(max_fraction) <= 1:
        raise InputError(f"target_size_class: max_fraction={max_fraction} must lie in [0, 1]")
    return np.where(f <= 0, "empty", np.where(f < float(max_fraction), "tiny", "regular"))
