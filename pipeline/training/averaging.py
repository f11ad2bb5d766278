"""Weight averaging: the mean of the last epochs' weights (``train.average_last``) and the per-step exponential
moving average (``train.ema_decay``).  Either replaces the selected checkpoint, with BN statistics recomputed
for the averaged weights (the loop does that); not in the paper (docs/decisions.md)."""

from __future__ import annotations

from typing import Mapping, Sequence

import torch


def average_update(avg: dict | None, state: Mapping[str, torch.Tensor]) -> dict:
    """The running mean ``{"n", "state"}`` with ``state`` folded in: m <- m + (w - m) / (n + 1).

    Parameters
    ----------
    avg : dict or None
        The mean so far (None: none yet).
    state : Mapping
        A model state dict; copied to the CPU.

    Returns
    -------
    dict
        ``n`` the states averaged, ``state`` their mean; a non-float tensor (BN's batch counter) takes the newest.
    """
    new = {k: v.detach().to("cpu", copy=True) for k, v in state.items()}
    if avg is None:
        return {"n": 1, "state": new}
    n, old = int(avg["n"]) + 1, avg["state"]
    return {"n": n, "state": {k: old[k] + (v - old[k]) / n if v.is_floating_point() else v for k, v in new.items()}}


def in_average(epoch: int, epochs: int, last: int, decay_started: bool) -> bool:
    """Whether epoch ``epoch`` of ``epochs`` is one of the ``last`` averaged (``train.average_last``; 0 = none).

    Under ``until: plateau`` the run's end is not known before the stable phase stops: only epochs after that
    (``decay_started``) are averaged."""
    return decay_started and last > 0 and epoch > epochs - last


def ema_update(ema: Sequence[torch.Tensor], params: Sequence[torch.Tensor], decay: float) -> None:
    """After an optimizer step, in place: e <- d e + (1 - d) w for each parameter, d = ``decay``."""
    torch._foreach_lerp_(list(ema), [p.detach() for p in params], 1.0 - decay)
