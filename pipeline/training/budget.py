"""A wall-clock budget for Stage I (``distill --time``), converted once on this host into optimizer steps
(``train.step_budget``, kept in the run's params so that a rerun with the same ``--time`` does nothing)."""

from __future__ import annotations

import re
import time
from typing import Any, Mapping

from pipeline.runtime.errors import InputError
from pipeline.methods import STAGE_ONE, get_method

_UNITS = {"s": 1, "m": 60, "h": 3600}


def parse_duration(text: str) -> float:
    """Seconds of a duration such as ``90s``, ``20m``, ``1.5h`` or ``1h30m``; InputError naming ``--time``."""
    parts = re.fullmatch(r"\s*((\d+(\.\d+)?)\s*([smh])\s*)+", str(text))
    seconds = sum(float(n) * _UNITS[u] for n, _, u in re.findall(r"(\d+(\.\d+)?)\s*([smh])", str(text))) if parts else 0
    if seconds <= 0:
        raise InputError(f"--time {text!r}: expected a duration such as 90s, 20m, 1.5h or 1h30m")
    return float(seconds)


#: images per probe step: a step's cost is linear in the batch, so a small probe scaled up keeps the measurement short
PROBE_BATCH = 2


def step_seconds(cfg: Mapping[str, Any], resolution: int, device: str = "cpu", steps: int = 2) -> float:
    """Seconds of one Stage-I optimizer step at ``resolution``: the median of ``steps`` probe steps after a warm-up,
    scaled to ``train.batch_size``."""
    import torch

    from pipeline.losses import raw_terms
    from pipeline.training.loop import build_model

    if int(cfg.get("num_threads") or 0) > 0:
        torch.set_num_threads(int(cfg["num_threads"]))
    model = build_model(get_method(STAGE_ONE), cfg, 0).to(device).train()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(PROBE_BATCH, 3, int(resolution), int(resolution), generator=gen).to(device)
    y = (torch.rand(x.shape[0], 1, x.shape[2], x.shape[3], generator=gen) > 0.7).float().to(device)
    times = []
    for i in range(steps + 1):
        t0 = time.perf_counter()
        loss = raw_terms(model.forward_train(x)["mask"], y)["raw"]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if device != "cpu":
            torch.cuda.synchronize()
        if i:
            times.append(time.perf_counter() - t0)
    return sorted(times)[len(times) // 2] * int(cfg["batch_size"]) / PROBE_BATCH


def steps_for(seconds: float, per_step: float) -> int:
    """Optimizer steps that fit in ``seconds`` at ``per_step`` seconds each (at least 1)."""
    return max(1, int(seconds // max(per_step, 1e-9)))


def with_time_budget(params: dict, text: str | None, previous: Mapping | None = None, device: str = "cpu") -> dict:
    """``params`` with ``train.time_budget`` = ``text`` and ``train.step_budget`` its steps on this host (those of
    ``previous`` params holding the same ``text``: no new measurement); ``text`` None: unchanged."""
    if text is None:
        return params
    seconds = parse_duration(text)
    old = (previous or {}).get("train") or {}
    if old.get("time_budget") == text and int(old.get("step_budget") or 0) > 0:
        steps = int(old["step_budget"])
    else:
        steps = steps_for(seconds, step_seconds(params["train"], int(params["data"]["resolution"]), device))
    # a budget needs the stop-and-decay schedule
    train = {**params["train"], "time_budget": text, "step_budget": steps, "until": "plateau"}
    return {**params, "train": train}
