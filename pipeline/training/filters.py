"""The data filters of the training methods (``Method.data``, :mod:`pipeline.methods`), torch-free.

The confidence filter on c_i (eq:foreground-agreement) or the mean valid-prompt score, the annotation-free-style
control's fused base-prompt masks and score filter, and the pass ratio r of a filter.
"""

from __future__ import annotations

import numpy as np

from pipeline.params import PAPER
from pipeline.runtime.errors import InputError

__all__ = ["mean_valid_score", "confidence_pass", "pass_ratio", "afs_fuse", "afs_keep"]


def mean_valid_score(scores: np.ndarray) -> np.ndarray:
    """Average each image's teacher scores over its valid prompts (s_ik > 0).

    Parameters
    ----------
    scores : numpy.ndarray
        Teacher scores s_ik, float [N, K] (0 for an invalid prompt).

    Returns
    -------
    numpy.ndarray
        float64 [N]; 0 for an image without a valid prompt.
    """
    s = np.asarray(scores, dtype=np.float64)
    valid = s > 0
    n = valid.sum(1)
    return np.where(n > 0, (s * valid).sum(1) / np.maximum(n, 1), 0.0)


def confidence_pass(agreement: np.ndarray, n_valid: np.ndarray, mean_score: np.ndarray | None,
                    criterion: str, threshold: float, min_valid: int) -> np.ndarray:
    """Pass the images with at least ``min_valid`` valid prompts and a confidence >= ``threshold``.

    The confidence is c_i = sum_x A_i(x) M_i^T(x) / sum_x M_i^T(x) (eq:foreground-agreement, 0 for an empty
    pseudo-mask), or the mean valid-prompt score.

    Parameters
    ----------
    agreement : numpy.ndarray
        c_i per image [N].
    n_valid : numpy.ndarray
        Valid prompts per image, |V_i| [N].
    mean_score : numpy.ndarray or None
        Mean valid-prompt score per image [N] (:func:`mean_valid_score`); needed by ``mean_score`` only.
    criterion : str
        ``agreement`` or ``mean_score`` (``train.confidence.criterion``).
    threshold : float
        The lowest confidence that passes.
    min_valid : int
        The fewest valid prompts that pass.

    Returns
    -------
    numpy.ndarray
        Bool [N].

    Raises
    ------
    InputError
        An unknown ``criterion``, naming ``params: train.confidence.criterion``.
    ValueError
        ``criterion`` ``mean_score`` without ``mean_score``.
    """
    if criterion not in ("agreement", "mean_score"):
        raise InputError(f"params: train.confidence.criterion={criterion!r}: expected agreement or mean_score")
    if criterion == "mean_score" and mean_score is None:
        raise ValueError("criterion 'mean_score' needs mean_score")
    conf = np.asarray(agreement if criterion == "agreement" else mean_score, dtype=np.float64)
    return (np.asarray(n_valid) >= int(min_valid)) & (conf >= float(threshold))


def pass_ratio(passed: np.ndarray) -> float:
    """Compute the fraction r of images passing a filter.

    Parameters
    ----------
    passed : numpy.ndarray
        Bool [N].

    Returns
    -------
    float
        r; 0 for an empty set.
    """
    passed = np.asarray(passed, dtype=bool)
    return float(passed.mean()) if passed.size else 0.0


def afs_fuse(mask_image: np.ndarray, mask_vflip: np.ndarray, fusion: str = PAPER.train.afs.fusion) -> np.ndarray:
    """Fuse the base-prompt masks of the image and of its vertical flip (flipped back).

    Parameters
    ----------
    mask_image : numpy.ndarray
        The image's mask.
    mask_vflip : numpy.ndarray
        The flipped view's mask, flipped back to the image.
    fusion : str
        ``intersection`` or ``union`` (``train.afs.fusion``).

    Returns
    -------
    numpy.ndarray
        The fused bool mask.

    Raises
    ------
    InputError
        An unknown ``fusion``, naming ``params: train.afs.fusion``.
    """
    fuse = {"intersection": np.logical_and, "union": np.logical_or}.get(fusion)
    if fuse is None:
        raise InputError(f"params: train.afs.fusion={fusion!r}: expected intersection or union")
    return fuse(np.asarray(mask_image, dtype=bool), np.asarray(mask_vflip, dtype=bool))


def afs_keep(score: np.ndarray, threshold: float = PAPER.train.afs.score_threshold) -> np.ndarray:
    """Keep the images the annotation-free-style control trains on: base-prompt score >= ``threshold``.

    Parameters
    ----------
    score : numpy.ndarray
        The base-prompt score per image [N].
    threshold : float
        The lowest score kept (``train.afs.score_threshold``).

    Returns
    -------
    numpy.ndarray
        Bool [N].
    """
    return np.asarray(score, dtype=np.float64) >= float(threshold)
