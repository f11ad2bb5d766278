"""Multi-prompt consensus vote (paper, "Multi-Prompt Consensus-Based Pseudo-Mask Construction").

For image i with K prompt masks M_ik and scores s_ik: V_i = {k : s_ik > 0} (the text before eq:agreement-map),
A_i(x) = (1/|V_i|) sum_{k in V_i} M_ik(x) (eq:agreement-map), M_i^T(x) = [A_i(x) >= 0.5] (eq:majority-vote).
A tie is foreground (3 of 6 valid votes suffice); with no valid prompt A_i = M_i^T = 0.  Scores only decide
validity; they never weight pixels.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from pipeline.runtime.errors import InputError
from pipeline.params import PAPER

__all__ = ["Consensus", "vote", "vote_batch", "agreement_entropy"]

DEFAULT_VOTE_THRESHOLD = PAPER.consensus.vote_threshold  # eq:majority-vote; the schema holds it


class Consensus(NamedTuple):
    """The vote of one image or of a batch.

    Attributes
    ----------
    agreement : numpy.ndarray
        A (eq:agreement-map), float32 [H,W], or [N,H,W] from :func:`vote_batch`; 0 without a valid prompt.
    voted : numpy.ndarray
        M^T (eq:majority-vote), bool [H,W] or [N,H,W].
    valid : numpy.ndarray
        V as bool [K] or [N,K].
    """

    agreement: np.ndarray
    voted: np.ndarray
    valid: np.ndarray

    @property
    def n_valid(self) -> np.ndarray | int:
        """|V|: int for one image, int16 [N] for a batch."""
        n = np.count_nonzero(self.valid, axis=-1)
        return int(n) if np.ndim(n) == 0 else n.astype(np.int16)


def valid_prompts(scores: np.ndarray) -> np.ndarray:
    """Mark the valid prompts V = {k : s_k > 0} (the text before eq:agreement-map).

    Parameters
    ----------
    scores : array_like
        Teacher scores, the prompts on the last axis.

    Returns
    -------
    numpy.ndarray
        bool, the shape of ``scores``.

    Raises
    ------
    InputError
        A score is NaN or infinite.
    """
    scores = np.asarray(scores, dtype=np.float64)
    if not np.isfinite(scores).all():
        raise InputError("scores contain NaN or infinite values")
    return scores > 0


def vote(masks: np.ndarray, scores: np.ndarray, threshold: float = DEFAULT_VOTE_THRESHOLD) -> Consensus:
    """Vote K prompt masks of one image (eq:agreement-map, eq:majority-vote).

    A = mean of the valid masks, M = [A >= threshold]: a tie is foreground; no valid prompt gives A = M = 0.

    Parameters
    ----------
    masks : array_like
        Prompt masks, bool or 0/1 [K,H,W].
    scores : array_like
        Teacher scores [K]; a prompt is valid when its score is > 0.
    threshold : float, optional
        The vote threshold in [0, 1] (default ``consensus.vote_threshold``, 0.5).

    Returns
    -------
    Consensus
        A float32 [H,W], M bool [H,W], V bool [K].

    Raises
    ------
    InputError
        ``masks`` is not [K,H,W], ``scores`` is not [K], or as :func:`vote_batch`.
    """
    masks = np.asarray(masks)
    if masks.ndim != 3:
        raise InputError(f"masks: expected [K,H,W], got shape {masks.shape}")
    scores = np.asarray(scores)
    if scores.shape != masks.shape[:1]:
        raise InputError(f"scores: expected shape ({masks.shape[0]},) to match masks {masks.shape}, got {scores.shape}")
    c = vote_batch(masks[None], scores[None], threshold)
    return Consensus(c.agreement[0], c.voted[0], c.valid[0])


def vote_batch(masks: np.ndarray, scores: np.ndarray, threshold: float = DEFAULT_VOTE_THRESHOLD) -> Consensus:
    """Vote the prompt masks of N images (:func:`vote`, vectorised).

    A takes only the values c / |V|: the vote compares the float64 ratio (3/6 >= 0.5 exactly); the stored map is
    float32.

    Parameters
    ----------
    masks : array_like
        Prompt masks, bool or 0/1 [N,K,H,W], K <= 255.
    scores : array_like
        Teacher scores [N,K].
    threshold : float, optional
        The vote threshold in [0, 1] (default ``consensus.vote_threshold``, 0.5).

    Returns
    -------
    Consensus
        A float32 [N,H,W], M bool [N,H,W], V bool [N,K].

    Raises
    ------
    InputError
        Shapes do not match, ``threshold`` is outside [0, 1], a mask is not binary, K > 255, or a score is not
        finite.
    """
    masks = np.asarray(masks)
    scores = np.asarray(scores)
    if masks.ndim != 4:
        raise InputError(f"masks: expected [N,K,H,W], got shape {masks.shape}")
    if scores.shape != masks.shape[:2]:
        raise InputError(f"scores: expected shape {masks.shape[:2]} to match masks {masks.shape}, got {scores.shape}")
    if not 0.0 <= float(threshold) <= 1.0 or not np.isfinite(threshold):
        raise InputError(f"consensus.vote_threshold={threshold!r} must lie in [0, 1]")
    if masks.dtype != bool:
        if masks.dtype.kind not in "biuf":
            raise InputError(f"masks: masks must be binary (bool or 0/1), got dtype {masks.dtype}")
        if (bad := masks[~np.isin(masks, (0, 1))]).size:
            raise InputError(f"masks: masks must be binary (0/1); found value {bad.flat[0]!r}")
        masks = masks.astype(bool)
    valid = valid_prompts(scores)
    n, k = masks.shape[:2]
    if k > 255:  # the vote counts are uint8
        raise InputError(f"masks: at most 255 prompts supported, got {k}")
    # bool -> 0/1 bytes without a copy, summed over the valid prompts only
    counts = masks.view(np.uint8).sum(axis=1, dtype=np.uint8, where=valid[:, :, None, None])
    n_valid = valid.sum(axis=1)
    # A takes only the values c / |V|: the vote compares the float64 ratio (3/6 >= 0.5 exactly), the
    # stored map is float32
    c = np.arange(k + 1, dtype=np.float64)
    ratio = np.divide(c[None, :], n_valid[:, None], out=np.zeros((n, k + 1)), where=n_valid[:, None] > 0)
    agree_lut = ratio.astype(np.float32)
    vote_lut = (ratio >= threshold) & (n_valid[:, None] > 0)  # no valid prompt: M = 0 (threshold 0 too)
    rows = np.arange(n)[:, None, None]
    return Consensus(agree_lut[rows, counts], vote_lut[rows, counts], valid)


def binary_entropy(p: np.ndarray) -> np.ndarray:
    """Binary entropy h(p) = -p log2 p - (1 - p) log2 (1 - p), elementwise.

    Parameters
    ----------
    p : array_like
        Probabilities; values outside [0, 1] are clipped.

    Returns
    -------
    numpy.ndarray
        float64 in [0, 1], with h(0) = h(1) = 0.
    """
    p = np.clip(np.asarray(p, np.float64), 0.0, 1.0)
    out = np.zeros_like(p)
    inner = (p > 0) & (p < 1)
    q = p[inner]
    out[inner] = -(q * np.log2(q) + (1 - q) * np.log2(1 - q))
    return out


def agreement_entropy(agreement: np.ndarray) -> float | np.ndarray:
    """Prompt disagreement of an agreement map (docs/decisions.md, "The prompt disagreement h").

    U_i = {x : A_i(x) > 0}, H_i = (1/|U_i|) sum_{x in U_i} h(A_i(x)) with :func:`binary_entropy` h; H_i = 0 when
    U_i is empty.

    Parameters
    ----------
    agreement : array_like
        A [H,W] or a stack [N,H,W].

    Returns
    -------
    float or numpy.ndarray
        A float for [H,W], float64 [N] for a stack.

    Raises
    ------
    ValueError
        ``agreement`` is neither 2-D nor 3-D.
    """
    a = np.asarray(agreement)
    if a.ndim not in (2, 3):
        raise ValueError(f"agreement: expected [H,W] or [N,H,W], got shape {a.shape}")
    stack = a.reshape((-1, *a.shape[-2:]))
    out = np.array([binary_entropy(m[m > 0]).mean() if (m > 0).any() else 0.0 for m in stack], dtype=np.float64)
    return float(out[0]) if a.ndim == 2 else out
