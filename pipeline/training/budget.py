"""A wall-clock budget for Stage I (``distill --time``), converted once on this host into optimizer steps.

The steps go into ``train.step_budget``, kept in the run's params so that a rerun with the same ``--time`` does
nothing.
"""

from __future__ import annotations

import bisect
import math
import re
import time
from pathlib import Path
from typing import Any, Mapping

from pipeline.datasets.scan import scan_inputs
from pipeline.runtime.errors import InputError
from pipeline.methods import STAGE_ONE, get_method
from pipeline.runtime.device import autocast, autocast_dtype, reuse_freed_memory

__all__ = ["PROBE_BATCH", "parse_duration", "step_seconds", "steps_for", "plan_seconds", "scheduled_steps",
           "raised_cap", "training_images", "with_time_budget"]

_UNITS = {"s": 1, "m": 60, "h": 3600}


def parse_duration(text: str) -> float:
    """Return the seconds of a duration such as ``90s``, ``20m``, ``1.5h`` or ``1h30m``.

    Parameters
    ----------
    text : str
        The ``--time`` value: numbers each followed by a unit (``s``, ``m`` or ``h``), summed.

    Returns
    -------
    float
        The duration in seconds, > 0.

    Raises
    ------
    InputError
        ``text`` is no such duration, or it comes to 0 s (one line naming ``--time``).
    """
    parts = re.fullmatch(r"\s*((\d+(\.\d+)?)\s*([smh])\s*)+", str(text))
    seconds = sum(float(n) * _UNITS[u] for n, _, u in re.findall(r"(\d+(\.\d+)?)\s*([smh])", str(text))) if parts else 0
    if seconds <= 0:
        raise InputError(f"--time {text!r}: expected a duration such as 90s, 20m, 1.5h or 1h30m")
    return float(seconds)


#: images per probe step: a step's cost is linear in the batch, so a small probe scaled up keeps the measurement short
PROBE_BATCH = 2


def step_seconds(cfg: Mapping[str, Any], resolution: int, device: str = "cpu", steps: int = 2) -> float:
    """Measure the seconds of one Stage-I optimizer step at ``resolution`` on this host.

    The step runs in the precision and memory format that will train (``train.precision``'s autocast,
    :func:`pipeline.runtime.device.autocast_dtype`, and ``train.channels_last``, as
    :func:`pipeline.training.loop.train` sets them), on :data:`PROBE_BATCH` random images with
    ``train.num_threads`` torch threads and the heap's reuse (:func:`pipeline.runtime.device.reuse_freed_memory`):
    the median of ``steps`` probe steps after a warm-up, scaled to ``train.batch_size``.

    Parameters
    ----------
    cfg : Mapping
        The validated ``train`` section.
    resolution : int
        The image side of the probe.
    device : str
        The training device.
    steps : int
        Timed probe steps (one more warms up).

    Returns
    -------
    float
        Seconds per optimizer step of ``train.batch_size`` images.
    """
    import torch

    from pipeline.losses import raw_terms
    from pipeline.training.loop import build_model

    if int(cfg["num_threads"]) > 0:
        torch.set_num_threads(int(cfg["num_threads"]))
    reuse_freed_memory(device)  # as train() will: the probe times the steps that will train
    amp = autocast_dtype(torch.device(device), cfg["precision"])
    memory_format = torch.channels_last if cfg["channels_last"] else torch.contiguous_format
    # the model that will train: with train.expand_branches, its RepVGG branches too
    model = build_model(get_method(STAGE_ONE), cfg, 0, expand=bool(cfg["expand_branches"])).to(device)
    model = model.to(memory_format=memory_format).train()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(PROBE_BATCH, 3, int(resolution), int(resolution), generator=gen).to(device)
    x = x.contiguous(memory_format=memory_format)
    y = (torch.rand(x.shape[0], 1, x.shape[2], x.shape[3], generator=gen) > 0.7).float().to(device)
    times = []
    for i in range(steps + 1):
        t0 = time.perf_counter()
        with autocast(device, amp):  # the forward under autocast, the loss outside it: as the training step
            logits = model.forward_train(x)["mask"]
        loss = raw_terms(logits, y)["raw"]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if device != "cpu":
            torch.cuda.synchronize()
        if i:
            times.append(time.perf_counter() - t0)
    return sorted(times)[len(times) // 2] * int(cfg["batch_size"]) / PROBE_BATCH


def steps_for(seconds: float, per_step: float) -> int:
    """Return the optimizer steps that fit in ``seconds`` at ``per_step`` seconds each.

    Parameters
    ----------
    seconds : float
        The time budget.
    per_step : float
        Seconds of one optimizer step (:func:`step_seconds`).

    Returns
    -------
    int
        floor(``seconds`` / ``per_step``), at least 1.
    """
    return max(1, int(seconds // max(per_step, 1e-9)))


def plan_seconds(stable: int, decay: int, low: int, steps_per_epoch: int, full_step: float,
                 half_step: float) -> float:
    """Price a Stage-I plan: spe (min(E, L) t_h + (max(E - L, 0) + D) t_f) seconds.

    Parameters
    ----------
    stable : int
        E, the stable epochs.
    decay : int
        D, the decay epochs after them (at full side).
    low : int
        L, the epochs at half the side (:func:`pipeline.training.schedule.low_res_epochs`).
    steps_per_epoch : int
        spe, optimizer steps per epoch.
    full_step, half_step : float
        t_f and t_h, seconds of a full-side and a half-side step (:func:`step_seconds`).

    Returns
    -------
    float
        The plan's seconds.
    """
    return steps_per_epoch * (min(stable, low) * half_step + (max(stable - low, 0) + decay) * full_step)


def scheduled_steps(seconds: float, full_step: float, half_step: float, cfg: Mapping[str, Any],
                    steps_per_epoch: int) -> int:
    """Return the optimizer steps B of the longest Stage-I run under ``until: plateau`` that fits ``seconds``.

    The resolution schedule (``train.low_res_fraction``) is priced in.  E stable epochs, their first min(E, L)
    at half the side (t_h a step), the rest and the decay D(E) at full side (t_f):
    spe (min(E, L) t_h + (max(E - L, 0) + D(E)) t_f) <= ``seconds``, B = (E + D(E)) spe, so the run's stable cap
    (:func:`pipeline.training.schedule.stable_cap`) is that E; E runs up to ``train.epochs_stage1`` with its
    decay.  When the epochs cap fits, the time left buys full-side steps on top (a later, longer ``--time``
    continues the run).  When not one stable epoch and its decay fit, the run trains that one anyway and B is
    :func:`steps_for` at full side.

    Parameters
    ----------
    seconds : float
        The time budget.
    full_step : float
        t_f, seconds of a full-side step (:func:`step_seconds`).
    half_step : float
        t_h, seconds of a half-side step (:func:`step_seconds` at the low resolution).
    cfg : Mapping
        The validated ``train`` section (``epochs_stage1``, ``decay_fraction``, ``low_res_fraction``).
    steps_per_epoch : int
        spe, from the training images (:func:`training_images`); at least 1 is used.

    Returns
    -------
    int
        B, optimizer steps, at least 1.
    """
    from pipeline.training.schedule import decay_epochs
    from pipeline.training.settings import Settings

    s = Settings.from_params(get_method(STAGE_ONE), cfg, 0.5)
    spe = max(1, int(steps_per_epoch))
    best, cap_fits = None, True
    for e in range(1, s.epochs + 1):
        d = decay_epochs(e, s.decay_fraction)
        if e + d > s.epochs:
            continue
        cost = plan_seconds(e, d, s.low_res_epochs, spe, full_step, half_step)
        if cost > seconds:
            cap_fits = False
            break
        best = (e + d, cost)
    if best is None:  # not one stable epoch and its decay: the run trains that one anyway
        return steps_for(seconds, full_step)
    return best[0] * spe + (int((seconds - best[1]) // max(full_step, 1e-9)) if cap_fits else 0)


def raised_cap(seconds: float, full_step: float, half_step: float, cfg: Mapping[str, Any], steps_per_epoch: int,
               factor: float) -> int:
    """Return the Stage-I epochs cap that ``--time`` raises ``train.epochs_stage1`` to when the time allows more.

    C is the largest cap in [E0, floor(``factor`` E0)] (E0 = ``train.epochs_stage1``) whose whole run fits
    ``seconds``: its most stable epochs E with E + D(E) <= C (D = :func:`pipeline.training.schedule.decay_epochs`),
    the first L(C) = :func:`pipeline.training.schedule.low_res_epochs` of them at half the side (t_h a step), the
    rest and the decay at full side (t_f): spe (min(E, L) t_h + (max(E - L, 0) + D(E)) t_f) <= ``seconds``.  The
    resolution schedule scales with the cap (``train.low_res_fraction`` is a share of it).  E0 when no larger cap
    fits or ``factor`` < (E0 + 1) / E0: then the cap stays and the budget stops the run (:func:`scheduled_steps`).

    Parameters
    ----------
    seconds, full_step, half_step, cfg, steps_per_epoch
        As in :func:`scheduled_steps` (t_h = t_f where no epoch trains at half the side).
    factor : float
        ``train.time_cap_factor``: the cap rises to this multiple of E0 at most.

    Returns
    -------
    int
        C, in [E0, max(E0, floor(``factor`` E0))].
    """
    from pipeline.training.schedule import decay_epochs, low_res_epochs
    from pipeline.training.settings import Settings

    s = Settings.from_params(get_method(STAGE_ONE), cfg, 0.5)
    top = max(s.epochs, math.floor(float(factor) * s.epochs))
    spe, frac = max(1, int(steps_per_epoch)), float(cfg["low_res_fraction"] or 0)
    ends = [e + decay_epochs(e, s.decay_fraction) for e in range(1, top + 1)]  # E + D(E), non-decreasing in E

    def cost(cap: int) -> float:
        e = bisect.bisect_right(ends, cap)  # the most stable epochs whose run ends by the cap
        return plan_seconds(e, decay_epochs(e, s.decay_fraction), low_res_epochs(cap, frac), spe, full_step, half_step)

    # every cap is priced: one more epoch of cap can make the run cheaper (one more of them at half the side)
    return max((c for c in range(s.epochs, top + 1) if cost(c) <= seconds), default=s.epochs)


def training_images(input_dir: str | Path, val_masks: str | Path | None, holdout_fraction: float) -> int:
    """Count the images Stage I of ``distill`` trains on.

    Those under ``input_dir`` without a mask in ``val_masks`` (matched by relative path without suffix, as the
    folder reader does), less the held-out share the plateau rule scores when there are no validation masks
    (:func:`pipeline.training.schedule.holdout_size`).  Unreadable files still count: an estimate for pricing
    the time, not the split.

    Parameters
    ----------
    input_dir : str or Path
        The folder of training images.
    val_masks : str or Path or None
        The folder of validation masks; None: the plateau rule holds images out instead.
    holdout_fraction : float
        The held-out share without validation masks (``train.holdout_fraction``).

    Returns
    -------
    int
        The number of training images.
    """
    from pipeline.datasets.manifest import relative_id
    from pipeline.training.schedule import holdout_size

    root = Path(input_dir)
    ids = {relative_id(root, f) for f in scan_inputs(root).files}
    if val_masks is not None:
        masked = {relative_id(Path(val_masks), f) for f in scan_inputs(Path(val_masks)).files}
        return len(ids - masked)
    return len(ids) - holdout_size(len(ids), holdout_fraction)


def with_time_budget(params: dict, text: str | None, previous: Mapping | None = None, device: str = "cpu",
                     n_train: int | None = None) -> dict:
    """Return ``params`` with ``train.time_budget`` = ``text`` and ``train.step_budget`` its steps on this host.

    The steps are those of ``previous`` params holding the same ``text`` (no new measurement), else measured
    (:func:`step_seconds`).  Under a resolution schedule the steps are priced by :func:`scheduled_steps`, the
    half-side ones at their own probed time, over ``n_train`` training images (:func:`training_images`); without
    ``n_train`` every step is priced at full side (fewer steps than the time allows).  When the time allows the
    whole run at a larger epochs cap, ``train.epochs_stage1`` rises to it (:func:`raised_cap`, up to
    ``train.time_cap_factor`` times) and ``train.time_raised_from`` records the cap it replaced.  A budget needs
    the stop-and-decay schedule, so ``train.until`` becomes ``plateau``.

    Parameters
    ----------
    params : dict
        The validated params.
    text : str or None
        The ``--time`` value (:func:`parse_duration`); None: ``params`` unchanged.
    previous : Mapping or None
        The params of the previous run, whose step budget is reused for the same ``text``.
    device : str
        The training device the probe runs on.
    n_train : int or None
        The training images (:func:`training_images`); None: every step priced at full side.

    Returns
    -------
    dict
        A new params dict (``params`` is not modified).
    """
    if text is None:
        return params
    seconds = parse_duration(text)
    # unvalidated: the previous run's params as read (an absent key says nothing)
    old = (previous or {}).get("train") or {}
    train, res = dict(params["train"]), int(params["data"]["resolution"])
    base = int(train["epochs_stage1"])
    if (old.get("time_budget") == text and int(old.get("step_budget") or 0) > 0
            and int(old.get("time_raised_from") or old.get("epochs_stage1") or 0) == base
            # a project written before time_cap_factor existed keeps its budget and cap: same --time, same run
            and float(old.get("time_cap_factor", train["time_cap_factor"])) == float(train["time_cap_factor"])):
        steps, cap = int(old["step_budget"]), int(old["epochs_stage1"])
    elif n_train:
        from pipeline.training.schedule import LOW_RES_FACTOR, steps_per_epoch

        spe = steps_per_epoch(n_train, int(train["batch_size"]))
        full, scheduled = step_seconds(train, res, device), float(train["low_res_fraction"]) > 0
        half = step_seconds(train, max(1, res // LOW_RES_FACTOR), device) if scheduled else full
        cap = raised_cap(seconds, full, half, train, spe, float(train["time_cap_factor"]))
        steps = (scheduled_steps(seconds, full, half, {**train, "epochs_stage1": cap}, spe) if scheduled
                 else steps_for(seconds, full))
    else:  # no training images to count: every step priced at full side, the cap kept
        steps, cap = steps_for(seconds, step_seconds(train, res, device)), base
    # a budget needs the stop-and-decay schedule
    train.update(time_budget=text, step_budget=steps, until="plateau", epochs_stage1=cap,
                 time_raised_from=base if cap > base else 0)
    return {**params, "train": train}
