"""The per-frame confidence of a prediction: a score in [0, 1] that ranks frames ("don't trust this frame");
not a calibrated probability (docs/real-data.md)."""

from __future__ import annotations

import numpy as np

from pipeline.stats import SpearmanResult, spearman

#: working-resolution pixels around the predicted mask that :func:`frame_confidence` scores too
CONFIDENCE_BAND = 2


def frame_confidence(probs: np.ndarray, tau: float, band: int = CONFIDENCE_BAND) -> float:
    """Mean normalised margin of P [H,W] from tau, ``|P - tau| / (1 - tau)`` (P >= tau) or ``|P - tau| / tau``,
    over the mask [P >= tau] grown by ``band`` pixels (the whole frame when it is empty)."""
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
    """Spearman's rho between frame confidences and the frames' Image IoU (positive: low scores, poor masks)."""
    return spearman(np.asarray(scores, np.float64), np.asarray(ious, np.float64))
