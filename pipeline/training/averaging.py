"""Weight averaging: the mean of the last epochs' weights and the per-step exponential moving average.

The mean is ``train.average_last``'s, the moving average ``train.ema_decay``'s.  Either replaces the selected
checkpoint, with BN statistics recomputed for the averaged weights (the loop does that); not in the paper
(docs/decisions.md).
"""

from __future__ import annotations

from typing import Mapping, Sequence

import torch

__all__ = ["average_update", "in_average", "ema_update"]


def average_update(avg: dict | None, state: Mapping[str, torch.Tensor]) -> dict:
    """Fold ``state`` into the running mean ``{"n", "state"}``: m <- m + (w - m) / (n + 1).

    n is the count of states averaged before ``state``, m their mean and w ``state``'s tensor of the same key.

    Parameters
    ----------
    avg : dict or None
        The mean so far, ``{"n": int, "state": dict of CPU tensors}`` (None: none yet; the result is ``state``
        itself with n = 1).  Not modified.
    state : Mapping of str to torch.Tensor
        A model state dict; copied to the CPU (detached), so later steps do not change the mean.

    Returns
    -------
    dict
        ``n`` the states averaged, ``state`` their mean (float tensors); a non-float tensor (BN's
        ``num_batches_tracked`` counter) takes the newest value instead of a mean.
    """
    new = {k: v.detach().to("cpu", copy=True) for k, v in state.items()}
    if avg is None:
        return {"n": 1, "state": new}
    n, old = int(avg["n"]) + 1, avg["state"]
    return {"n": n, "state": {k: old[k] + (v - old[k]) / n if v.is_floating_point() else v for k, v in new.items()}}


def in_average(epoch: int, epochs: int, last: int, decay_started: bool) -> bool:
    """Tell whether epoch ``epoch`` of ``epochs`` is one of the ``last`` averaged (``train.average_last``).

    True when ``decay_started`` and ``last`` > 0 and ``epoch`` > ``epochs`` - ``last``.  Under ``until: plateau``
    the run's end is not known before the stable phase stops: only epochs after that (``decay_started``) are
    averaged.

    Parameters
    ----------
    epoch : int
        The epoch just trained, 1-based.
    epochs : int
        The run's length in epochs (under ``until: plateau``, the length known so far).
    last : int
        ``train.average_last``: how many final epochs are averaged; 0 = none (always False).
    decay_started : bool
        Whether the run's end is fixed: True for a fixed-epoch run, and under ``until: plateau`` once the stable
        phase has stopped.

    Returns
    -------
    bool
        Whether the weights after ``epoch`` enter the mean (:func:`average_update`).
    """
    return decay_started and last > 0 and epoch > epochs - last


def ema_update(ema: Sequence[torch.Tensor], params: Sequence[torch.Tensor], decay: float) -> None:
    """Update the exponential moving average after an optimizer step, in place: e <- d e + (1 - d) w.

    Parameters
    ----------
    ema : sequence of torch.Tensor
        The moving averages e, one per parameter, on the parameters' device; updated in place.
    params : sequence of torch.Tensor
        The model's parameters w after the step, in the order of ``ema`` (read detached).
    decay : float
        d = ``train.ema_decay``, in [0, 1): the weight the old average keeps per step.

    Returns
    -------
    None
        ``ema`` is updated in place.
    """
    torch._foreach_lerp_(list(ema), [p.detach() for p in params], 1.0 - decay)
