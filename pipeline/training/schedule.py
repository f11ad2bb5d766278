"""How long Stage I and Stage II train and at what rate.

The learning-rate schedules, the resolution schedule (``train.low_res_fraction``), ``train.until: plateau``'s
stopping rule and its budget, and the held-out images the rule scores without validation masks.  Pure functions
of the settings and the step counts; the loop (:mod:`pipeline.training.loop`) calls them.  Rationale:
docs/decisions.md, "Training"; the rule: docs/student.md.
"""

from __future__ import annotations

import math
from typing import Callable, Mapping, Protocol

import numpy as np
import torch
import torch.nn.functional as F

from pipeline.augment import hard_region
from pipeline.runtime.errors import InputError
from pipeline.stats import ONE_SIDED_95_Z
from pipeline.training.inputs import TrainData, ValData

__all__ = ["LOW_RES_FACTOR", "PLATEAU_Z", "lr_lambda", "decay_steps", "steps_per_epoch", "low_res_epochs",
           "low_resolution", "decay_epochs", "over_budget", "stable_cap", "plateau_reached", "plateau_window",
           "until_lambda", "holdout_size", "holdout"]


class StopSettings(Protocol):
    """What the stopping rule's budget reads of :class:`pipeline.training.settings.Settings`.

    Attributes
    ----------
    epochs : int
        ``train.epochs_stage1``: the cap on the stable phase and its decay together.
    decay_fraction : float
        ``train.decay_fraction``, f in (0, 1): the decay's share of the whole run.
    step_budget : int
        ``train.step_budget``: optimizer steps at most, warm-up and decay included; 0 = none.
    """

    epochs: int
    decay_fraction: float
    step_budget: int

#: the resolution schedule (``train.low_res_fraction``) trains its first epochs at 1 / this of the side
LOW_RES_FACTOR = 2
#: the plateau rule stops only when the last doubling's gain is surely small: its one-sided 95 % bound
PLATEAU_Z = ONE_SIDED_95_Z
#: the schedules ``train.schedule`` names
SCHEDULES = ("cosine", "constant", "wsd")


def lr_lambda(schedule: str, total_steps: int, warmup_steps: int = 0, decay_steps: int = 0) -> Callable[[int], float]:
    """Return the learning-rate factor of optimizer step ``step`` (0-based) for ``torch.optim.lr_scheduler.LambdaLR``.

    With T = ``total_steps``, D = ``decay_steps`` and W = ``warmup_steps``:

    - ``constant``: 1;
    - ``cosine``: 0.5 (1 + cos(pi min(step, T) / max(T, 1))), 0 from step T on;
    - ``wsd``: min(1, max(0, T - step) / D) (constant, then linear to 0 over the last D steps);

    times the warm-up min(1, (step + 1) / W) when W > 0.  The paper gives initial rates only
    (docs/decisions.md).

    Parameters
    ----------
    schedule : str
        One of :data:`SCHEDULES` (``train.schedule``).
    total_steps : int
        T, the run's optimizer steps.
    warmup_steps : int
        W; 0 = no warm-up.
    decay_steps : int
        D for ``wsd`` (at least 1 is used); ignored by the other schedules.

    Returns
    -------
    callable
        step -> factor of the peak learning rate.

    Raises
    ------
    pipeline.runtime.errors.InputError
        ``schedule`` is not one of :data:`SCHEDULES`.
    """
    d = max(int(decay_steps), 1)
    bases = {"constant": lambda step: 1.0,
             "cosine": lambda step: 0.5 * (1.0 + math.cos(math.pi * min(step, total_steps) / max(total_steps, 1))),
             "wsd": lambda step: min(1.0, max(0, total_steps - step) / d)}
    if schedule not in bases:
        raise InputError(f"params: train.schedule={schedule!r}: expected {', '.join(SCHEDULES)}")
    base = bases[schedule]
    if warmup_steps <= 0:
        return base
    return lambda step: min(1.0, (step + 1) / warmup_steps) * base(step)


def decay_steps(total_steps: int, fraction: float) -> int:
    """Count the optimizer steps in the decay phase of the ``wsd`` schedule: D = max(1, round(f T)).

    ``round`` is Python's: a half rounds to the even integer.

    Parameters
    ----------
    total_steps : int
        T, the run's optimizer steps.
    fraction : float
        f = ``train.decay_fraction``, the decay's share of the steps.

    Returns
    -------
    int
        D, at least 1.
    """
    return max(1, int(round(total_steps * fraction)))


def steps_per_epoch(n_train: int, batch_size: int) -> int:
    """Count the optimizer steps of one epoch: max(1, ceil(N / B)), the last batch short.

    Parameters
    ----------
    n_train : int
        N, the training images.
    batch_size : int
        B, images per optimizer step (``train.batch_size``, at least 1).

    Returns
    -------
    int
        The steps, at least 1 (also for N = 0).
    """
    return max(1, math.ceil(int(n_train) / int(batch_size)))


def low_res_epochs(epochs: int, fraction: float) -> int:
    """Count the resolution schedule's epochs at 1/:data:`LOW_RES_FACTOR` of the side.

    L = max(0, min(round(f E), E - 1)), so the last epoch trains at full side; ``round`` is Python's (a half
    rounds to the even integer).  The first L epochs (1..L) train at the lower side.

    Parameters
    ----------
    epochs : int
        E, the run's epochs (``train.epochs_stage1``).
    fraction : float
        f = ``train.low_res_fraction``, in [0, 1); 0 = no low-resolution epoch.

    Returns
    -------
    int
        L, in [0, max(0, E - 1)].
    """
    return max(0, min(int(round(float(fraction) * int(epochs))), int(epochs) - 1))


def low_resolution(b: Mapping[str, torch.Tensor], soft: bool = False, factor: int = LOW_RES_FACTOR
                   ) -> dict[str, torch.Tensor]:
    """Shrink batch ``b`` to 1/``factor`` of its side, for the resolution schedule's epochs.

    The image and, with ``soft`` (the agreement map A of ``train.soft_targets``), the target by area mean; a
    hard voted mask M^T (eq:majority-vote) as [area mean >= 1/2] (a tie is foreground), so eq:raw-loss keeps a
    binary target.  A side that is not a multiple of ``factor`` is floored, the pooling windows then overlap
    (``torch.nn.functional.adaptive_avg_pool2d``).  The other keys are kept as they are.

    Parameters
    ----------
    b : Mapping
        A training batch: ``x`` [B,3,H,W], ``mask`` [B,1,H,W], and per-image ``area``, ``gate`` (kept as they are).
    soft : bool
        Whether ``mask`` is a soft target (kept soft) or a voted mask (re-binarised).
    factor : int
        The side is divided by this (floor).

    Returns
    -------
    dict
        The batch at the lower resolution.
    """
    out = dict(b)
    size = (b["x"].shape[-2] // factor, b["x"].shape[-1] // factor)
    out["x"] = F.adaptive_avg_pool2d(b["x"], size)
    m = F.adaptive_avg_pool2d(b["mask"], size)
    out["mask"] = m if soft else (m >= 0.5).to(m.dtype)
    return out


def decay_epochs(stable: int, fraction: float) -> int:
    """Count the decay epochs after E stable ones: D(E) = max(1, round(E f / (1 - f))).

    The decay is then the share f of the whole run E + D(E); ``round`` is Python's (a half rounds to the even
    integer).

    Parameters
    ----------
    stable : int
        E, the stable epochs.
    fraction : float
        f = ``train.decay_fraction``, in (0, 1).

    Returns
    -------
    int
        D(E), at least 1.

    Raises
    ------
    ZeroDivisionError
        f = 1: the decay would be the whole run (the schema refuses it under ``until: plateau``).
    """
    return max(1, int(round(stable * fraction / (1.0 - fraction))))


def over_budget(s: StopSettings, stable: int, steps_per_epoch: int) -> bool:
    """Tell whether E stable epochs and their decay exceed ``train.step_budget``: (E + D(E)) S > budget.

    D = :func:`decay_epochs`; never over a budget of 0 (none).

    Parameters
    ----------
    s : StopSettings
        The run's ``decay_fraction`` and ``step_budget``.
    stable : int
        E, the stable epochs.
    steps_per_epoch : int
        S, optimizer steps per epoch (:func:`steps_per_epoch`).

    Returns
    -------
    bool
        True when the run would take more optimizer steps than the budget (equal is within it).
    """
    return bool(s.step_budget) and (stable + decay_epochs(stable, s.decay_fraction)) * steps_per_epoch > s.step_budget


def stable_cap(s: StopSettings, steps_per_epoch: int) -> int:
    """Find the most stable epochs E with E + D(E) <= ``train.epochs_stage1`` and within the step budget.

    D = :func:`decay_epochs`; the budget test is :func:`over_budget`.

    Parameters
    ----------
    s : StopSettings
        The run's ``epochs`` (the cap), ``decay_fraction`` and ``step_budget``.
    steps_per_epoch : int
        Optimizer steps per epoch (:func:`steps_per_epoch`).

    Returns
    -------
    int
        The largest such E in [1, ``s.epochs``]; 1 when none fits (the cap then holds without room for a decay).
    """
    fits = [e for e in range(1, s.epochs + 1)
            if e + decay_epochs(e, s.decay_fraction) <= s.epochs and not over_budget(s, e, steps_per_epoch)]
    return max(fits, default=1)


def plateau_reached(scores: list[float], gain: float, min_epochs: int) -> bool:
    """Tell whether ``train.until: plateau``'s stopping rule stops the stable phase (docs/student.md).

    After E >= max(4, ``min_epochs``) scored epochs, with a = the first floor(E/2) scores and b = the rest, stop
    when the upper one-sided 95 % bound of the last doubling's gain is below ``gain``:
    mean(b) - mean(a) + z sqrt(var(a)/|a| + var(b)/|b|) < ``gain``, z = :data:`PLATEAU_Z`, var with ddof 1.
    A bound equal to ``gain`` does not stop.

    Parameters
    ----------
    scores : list of float
        The scored epochs' validation Image IoU, oldest first.
    gain : float
        ``train.plateau_gain``.
    min_epochs : int
        ``train.plateau_min_epochs`` (or the window of :func:`plateau_window`).

    Returns
    -------
    bool
        Whether to stop; False while fewer epochs are scored or any score is not finite (NaN, inf).
    """
    e = len(scores)
    if e < max(4, int(min_epochs)) or not all(math.isfinite(v) for v in scores):
        return False
    a, b = np.asarray(scores[:e // 2]), np.asarray(scores[e // 2:])
    se = math.sqrt(a.var(ddof=1) / len(a) + b.var(ddof=1) / len(b))
    return float(b.mean() - a.mean()) + PLATEAU_Z * se < gain


def plateau_window(min_epochs: int, min_steps: int, steps_per_epoch: int) -> int:
    """Count the scored epochs the plateau rule waits for: max(``min_epochs``, ceil(``min_steps`` / S)).

    ``train.plateau_min_steps`` makes the least window one of optimizer steps: with 16 training images (2 steps
    an epoch) eight epochs are 16 steps, a window over which the validation curve is flat within its noise.

    Parameters
    ----------
    min_epochs : int
        ``train.plateau_min_epochs``.
    min_steps : int
        ``train.plateau_min_steps``; 0 = epochs only.
    steps_per_epoch : int
        S, optimizer steps per epoch (below 1 counts as 1).

    Returns
    -------
    int
        The ``min_epochs`` argument of :func:`plateau_reached`.
    """
    return max(int(min_epochs), math.ceil(int(min_steps) / max(1, int(steps_per_epoch))))


def until_lambda(until: Mapping, steps_per_epoch: int, warmup_steps: int) -> Callable[[int], float]:
    """Return the learning-rate factor under ``train.until: plateau``.

    The warm-up, then 1 until the stable phase ends, then the ``wsd`` decay to 0 at the run's end
    (:func:`lr_lambda` with T = ``until["epochs"]`` S and D = T - ``until["stable_end"]`` S).

    Parameters
    ----------
    until : Mapping
        Read at each step (the loop updates it): ``stable_end``, the last stable epoch or None while the phase
        runs, and ``epochs``, the run's length so far.
    steps_per_epoch : int
        S, optimizer steps per epoch.
    warmup_steps : int
        W, the warm-up's optimizer steps; 0 = none.

    Returns
    -------
    callable
        step (0-based) -> factor of the peak learning rate.
    """
    spe = int(steps_per_epoch)

    def factor(step: int) -> float:
        end, total = until["stable_end"], until["epochs"] * spe
        return lr_lambda("constant" if end is None else "wsd", total, warmup_steps, total - (end or 0) * spe)(step)

    return factor


def holdout_size(n: int, fraction: float) -> int:
    """Count the images :func:`holdout` takes from n: k = min(n // 2, max(2, round(f n))), 0 below 8.

    ``round`` is Python's (a half rounds to the even integer).

    Parameters
    ----------
    n : int
        The training images.
    fraction : float
        f = ``train.holdout_fraction``.

    Returns
    -------
    int
        k: 0 when n < 8, else in [2, n // 2].
    """
    return 0 if n < 8 else min(n // 2, max(2, int(round(fraction * n))))


def holdout(data: TrainData, fraction: float) -> tuple[TrainData, ValData | None]:
    """Hold out the images ``until: plateau`` scores when there are no validation masks.

    ``fraction`` of ``data`` (:func:`holdout_size`), evenly spaced in manifest order (indices
    round(linspace(0, n - 1, k))), scored against their vote (eq:majority-vote; a soft target through
    :func:`pipeline.augment.hard_region`): never a validation set, never reference masks.

    Parameters
    ----------
    data : TrainData
        The pseudo-labelled training images.
    fraction : float
        ``train.holdout_fraction``.

    Returns
    -------
    (TrainData, ValData or None)
        The rest (its ``stats`` gain ``plateau_scored_on``), and the held-out images, named
        ``holdout:<image_id>`` (None below 8 images: nothing is held out and ``data`` comes back as it is).
    """
    n = len(data)
    k = holdout_size(n, fraction)
    if not k:
        return data, None
    held = np.unique(np.linspace(0, n - 1, k).round().astype(int))
    rest = np.setdiff1d(np.arange(n), held)
    val = ValData([f"holdout:{data.image_ids[i]}" for i in held], np.asarray(data.images[held]),
                  hard_region(np.asarray(data.mask[held])))
    return data.subset(rest, stats={**data.stats, "plateau_scored_on": f"{len(held)} held-out pseudo-labelled "
                                   "training images against their vote (no validation masks)"}), val
