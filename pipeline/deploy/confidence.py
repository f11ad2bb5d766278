"""The per-frame confidence of a prediction.

A score in [0, 1] that ranks frames ("don't trust this frame"); not a calibrated probability
(docs/real-data.md).
"""

from __future__ import annotations

import numpy as np

from pipeline.stats import SpearmanResult, spearman

__all__ = ["CONFIDENCE_BAND", "frame_confidence", "confidence_rank_check"]

#: working-resolution pixels around the predicted mask that :func:`frame_confidence` scores too
CONFIDENCE_BAND = 2


def frame_confidence(probs: np.ndarray, tau: float, band: int = CONFIDENCE_BAND) -> float:
    """Score one frame: the mean normalised margin of its probabilities from the threshold.

    c = mean over x in R of m(x), with m(x) = (P(x) - tau) / (1 - tau) where P(x) >= tau, else
    (tau - P(x)) / tau,

    over the region R: the mask [P >= tau] of eq:inference-mask grown by ``band`` pixels (the whole frame when
    the mask is empty), clipped to [0, 1].

    Parameters
    ----------
    probs : np.ndarray
        P [H, W], the student's probabilities at the working resolution.
    tau : float
        The mask threshold.
    band : int
        Pixels the mask is grown by (a square neighbourhood); :data:`CONFIDENCE_BAND` unless given.

    Returns
    -------
    float
        The score c in [0, 1]: low for a frame whose mask and its surroundings sit near the threshold.
    """
    import cv2

    p = np.asarray(probs, np.float64)
    tau = float(tau)
    fg = p >= tau
    margin = np.where(fg, (p - tau) / max(1.0 - tau, 1e-12), (tau - p) / max(tau, 1e-12))
    side = 2 * max(int(band), 0) + 1  # the mask grown by ``band`` pixels: a square neighbourhood
    region = cv2.dilate(fg.astype(np.uint8), np.ones((side, side), np.uint8)).astype(bool) if fg.any() else \
        np.ones_like(fg)
    return float(np.clip(margin[region].mean(), 0.0, 1.0))


def confidence_rank_check(scores, ious) -> SpearmanResult:
    """Rank-correlate frame confidences with the frames' Image IoU.

    Parameters
    ----------
    scores : array-like of float
        :func:`frame_confidence` of each frame.
    ious : array-like of float
        The Image IoU of each frame against its reference mask, in the order of ``scores``.

    Returns
    -------
    SpearmanResult
        Spearman's rho (positive: low scores go with poor masks) and its uncertainty.
    """
    return spearman(np.asarray(scores, np.float64), np.asarray(ious, np.float64))
