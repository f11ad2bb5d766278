"""Self-training rounds (Noisy Student, Xie et al. 2020) for Stage I.

The trained student predicts its own training images with flip test-time augmentation, its prediction is fused
with the vote per pixel, and a fresh student trains on the fused targets with augmentation.  A departure from
the two stages (docs/student.md); the reference masks never enter it.
"""

from __future__ import annotations

import numpy as np

from pipeline.evaluation.inference import predict_probs

__all__ = ["flip_tta_probs", "fused_targets"]

#: how a round's target T fuses the student's probability P with the voted mask M (:func:`fused_targets`)
FUSIONS = ("mix", "mix_hard", "prediction")


def flip_tta_probs(model, images, device="cpu", precision: str = "fp32", batch_size: int = 16) -> np.ndarray:
    """Predict the student's probability with left-right flip test-time augmentation.

    P = (P(x) + flip(P(flip(x)))) / 2, flip mirroring the width axis; the model is left in eval mode
    (:func:`pipeline.evaluation.inference.predict_probs`).

    Parameters
    ----------
    model : torch.nn.Module
        The trained student (its averaged weights where the recipe averages).
    images : array-like
        uint8 images [N, H, W, 3]: an array, or a row source (the plain pass reads it a batch at a time, the
        flipped pass as one array).
    device : str or torch.device
        Where to predict.
    precision : str
        ``fp32`` | ``bf16`` | ``auto`` (:func:`pipeline.evaluation.inference.predict_probs`).
    batch_size : int
        Images per forward pass.

    Returns
    -------
    numpy.ndarray
        float32 [N, H, W] in [0, 1].
    """
    plain = predict_probs(model, images, device=device, batch_size=batch_size, precision=precision)
    flipped = np.ascontiguousarray(np.asarray(images)[:, :, ::-1])
    mirrored = predict_probs(model, flipped, device=device, batch_size=batch_size, precision=precision)[:, :, ::-1]
    return ((plain + mirrored) / 2.0).astype(np.float32)


def fused_targets(probs: np.ndarray, voted: np.ndarray, fusion: str, weight: float) -> np.ndarray:
    """Fuse the student's probability P and the voted mask M into a self-training round's region target.

    - ``mix``: T = w P + (1 - w) M, a soft target (w = ``weight``);
    - ``mix_hard``: T = [w P + (1 - w) M >= 1/2] (a tie at exactly 1/2 is foreground); with w < 1/2 this is M
      (at w = 1/2, M except where P = 1), above it the student overrules the vote where it is confident enough;
    - ``prediction``: T = P, the student's own soft prediction (Noisy Student's soft pseudo-labels).

    Parameters
    ----------
    probs : numpy.ndarray
        P, float [N, H, W] in [0, 1] (:func:`flip_tta_probs`); expected finite (a NaN stays NaN in a soft target
        and is background in ``mix_hard``).
    voted : numpy.ndarray
        M, bool [N, H, W] (eq:majority-vote).
    fusion : str
        One of :data:`FUSIONS`.
    weight : float
        w in [0, 1].

    Returns
    -------
    numpy.ndarray
        float32 [N, H, W] for ``mix`` and ``prediction``, bool for ``mix_hard``.

    Raises
    ------
    ValueError
        An unknown ``fusion``, a ``weight`` outside [0, 1], or shapes that differ.
    """
    if fusion not in FUSIONS:
        raise ValueError(f"fusion {fusion!r}: expected one of {', '.join(FUSIONS)}")
    if not 0.0 <= float(weight) <= 1.0:
        raise ValueError(f"weight {weight!r}: expected a value in [0, 1]")
    p, m = np.asarray(probs, dtype=np.float32), np.asarray(voted).astype(np.float32)
    if p.shape != m.shape:
        raise ValueError(f"probs {p.shape} and voted {m.shape} differ in shape")
    if fusion == "prediction":
        return p.copy()
    mixed = float(weight) * p + (1.0 - float(weight)) * m
    return mixed >= 0.5 if fusion == "mix_hard" else mixed.astype(np.float32)
