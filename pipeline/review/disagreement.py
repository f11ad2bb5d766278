"""The per-image prompt disagreement: the agreement map's mean binary entropy over the union of the
prompt masks.

For image i with valid prompt set V_i and agreement map A_i (eq:agreement-map,
A_i(x) = (1/|V_i|) sum_{k in V_i} M_ik(x)):

    U_i = {x : A_i(x) > 0}                          the union of the valid prompts' masks
    h(p) = -p log2 p - (1 - p) log2 (1 - p)         binary entropy in bits, h(0) = h(1) = 0
    H_i = (1 / |U_i|) sum_{x in U_i} h(A_i(x))      in [0, 1];  H_i = 0 when U_i is empty

H_i = 0: every valid prompt drew the same mask; H_i = 1: every pixel any prompt claimed got exactly half
of the votes (the tie eq:majority-vote keeps as foreground).  Averaging over the union rather than the
frame makes the statistic independent of the object's size and of the background (a small spacecraft
on a large black frame is not "agreed on" because of its empty sky); averaging over the union rather
than the voted mask also counts the pixels a minority of prompts claimed (the outvoted panel, the
glare blob), which eq:foreground-agreement's c_i does not see.  An image where no prompt is valid, or
every valid prompt is empty, has U_i empty and H_i = 0: the reliability gate (g_valid, g_area) is what
flags it.  The union is read off A_i itself (A_i(x) > 0 exactly where some valid prompt voted), so the
statistic needs only the stored agreement map.
"""

from __future__ import annotations

import numpy as np


def binary_entropy(p: np.ndarray) -> np.ndarray:
    """h(p) = -p log2 p - (1-p) log2 (1-p) elementwise (float64), with h(0) = h(1) = 0."""
    p = np.clip(np.asarray(p, np.float64), 0.0, 1.0)
    out = np.zeros_like(p)
    inner = (p > 0) & (p < 1)
    q = p[inner]
    out[inner] = -(q * np.log2(q) + (1 - q) * np.log2(1 - q))
    return out


def agreement_entropy(agreement: np.ndarray) -> float | np.ndarray:
    """H_i of one agreement map [H,W] (a float) or of a stack [N,H,W] (float64 [N]) (module docstring)."""
    a = np.asarray(agreement)
    if a.ndim not in (2, 3):
        raise ValueError(f"agreement: expected [H,W] or [N,H,W], got shape {a.shape}")
    stack = a.reshape((-1, *a.shape[-2:]))
    out = np.zeros(len(stack))
    for i, m in enumerate(stack):
        union = m > 0
        n = int(np.count_nonzero(union))
        if n:
            out[i] = float(binary_entropy(m[union]).sum() / n)
    return float(out[0]) if a.ndim == 2 else out
