"""The data filters of the training methods (``Method.data``, :mod:`pipeline.methods`), torch-free: the
confidence filter on c_i (eq:foreground-agreement) or the mean valid-prompt score, the annotation-free-style
control's fused base-prompt masks and score filter, and the pass ratio r of a filter.
"""

from __future__ import annotations

import numpy as np

from pipeline.params import PAPER
from pipeline.runtime.errors import InputError

__all__ = ["mean_valid_score", "confidence_pass", "pass_ratio", "afs_fuse", "afs_keep"]


def mean_valid_score(scores: np.ndarray) -> np.ndarray:
    """Mean teacher score over the valid prompts (s_ik > 0) per image, 0 if none: float [N,K] -> float64 [N]."""
    s = np.asarray(scores, dtype=np.float64)
    valid = s > 0
    n = valid.sum(1)
    return np.where(n > 0, (s * valid).sum(1) / np.maximum(n, 1), 0.0)


def confidence_pass(agreement: np.ndarray, n_valid: np.ndarray, mean_score: np.ndarray | None,
                    criterion: str, threshold: float, min_valid: int) -> np.ndarray:
    """Bool [N]: at least ``min_valid`` valid prompts and a confidence >= ``threshold``, the confidence being
    c_i (eq:foreground-agreement, ``agreement``) or the mean valid-prompt score (``mean_score``).
    """
    if criterion not in ("agreement", "mean_score"):
        raise InputError(f"params: train.confidence.criterion={criterion!r}: expected agreement or mean_score")
    if criterion == "mean_score" and mean_score is None:
        raise ValueError("criterion 'mean_score' needs mean_score")
    conf = np.asarray(agreement if criterion == "agreement" else mean_score, dtype=np.float64)
    return (np.asarray(n_valid) >= int(min_valid)) & (conf >= float(threshold))


def pass_ratio(passed: np.ndarray) -> float:
    """Fraction r of images passing a filter (0 for an empty set)."""
    passed = np.asarray(passed, dtype=bool)
    return float(passed.mean()) if passed.size else 0.0


def afs_fuse(mask_image: np.ndarray, mask_vflip: np.ndarray, fusion: str = PAPER.train.afs.fusion) -> np.ndarray:
    """The base-prompt masks of the image and of its vertical flip (flipped back), fused."""
    fuse = {"intersection": np.logical_and, "union": np.logical_or}.get(fusion)
    if fuse is None:
        raise InputError(f"params: train.afs.fusion={fusion!r}: expected intersection or union")
    return fuse(np.asarray(mask_image, dtype=bool), np.asarray(mask_vflip, dtype=bool))


def afs_keep(score: np.ndarray, threshold: float = 0.60) -> np.ndarray:
    """The images the annotation-free-style control keeps: base-prompt score >= threshold."""
    return np.asarray(score, dtype=np.float64) >= float(threshold)
