"""The per-frame confidence of a prediction: a score flight software can threshold ("don't trust this frame").

Decision (the paper has none): :func:`frame_confidence`, returned by
:meth:`pipeline.Segmenter.score` and ``predict(..., return_score=True)``, is a number in [0, 1] that flight
software can threshold ("don't trust this frame"): the mean normalised margin of the probabilities from
tau, ``|P - tau| / (1 - tau)`` where P >= tau and ``|P - tau| / tau`` below, over the pixels that decide
the mask -- the predicted foreground and a band of :data:`CONFIDENCE_BAND` working pixels around it (the
whole frame when nothing is predicted).  1 = every deciding pixel is saturated (P = 0 or 1); near 0 = the
mask and its boundary sit at tau, where a small change of the input flips them.  It is computed at the
working resolution, so it does not depend on the frame's size, and from P alone (no second model).  It
ranks frames, it is not a calibrated probability of being right: choose the threshold on frames of your
own with :func:`confidence_rank_check` (Spearman between the score and per-frame IoU).
"""

from __future__ import annotations

import numpy as np

from pipeline.stats import SpearmanResult, spearman

#: the band (working-resolution pixels) around the predicted mask that :func:`frame_confidence` scores too
CONFIDENCE_BAND = 2


def _dilate(mask: np.ndarray, band: int) -> np.ndarray:
    """``mask`` [H,W] grown by ``band`` pixels (a square neighbourhood; numpy only)."""
    if band <= 0:
        return mask
    h, w = mask.shape
    padded = np.pad(mask, band)
    out = np.zeros_like(mask)
    for dy in range(2 * band + 1):
        for dx in range(2 * band + 1):
            out |= padded[dy:dy + h, dx:dx + w]
    return out


def frame_confidence(probs: np.ndarray, tau: float, band: int = CONFIDENCE_BAND) -> float:
    """The per-frame confidence in [0, 1] of P [H,W] (module docstring): the mean of the normalised
    margin ``|P - tau| / (1 - tau)`` (P >= tau) or ``|P - tau| / tau`` (P < tau) over the predicted
    foreground [P >= tau] grown by ``band`` pixels, or over the whole frame when it is empty."""
    p = np.asarray(probs, np.float64)
    tau = float(tau)
    fg = p >= tau
    margin = np.where(fg, (p - tau) / max(1.0 - tau, 1e-12), (tau - p) / max(tau, 1e-12))
    region = _dilate(fg, int(band)) if fg.any() else np.ones_like(fg)
    return float(np.clip(margin[region].mean(), 0.0, 1.0))


def confidence_rank_check(scores, ious) -> SpearmanResult:
    """Does the per-frame confidence rank bad frames?  Spearman's rho between ``scores``
    (:func:`frame_confidence`) and the frames' Image IoU against reference masks
    (:func:`pipeline.stats.spearman`); a positive rho means low scores go with poor masks."""
    return spearman(np.asarray(scores, np.float64), np.asarray(ious, np.float64))
