"""What the benchmark scripts share: round-robin timing, its medians and minima, the study data's test split."""

from __future__ import annotations

import statistics
import time
from typing import Callable


def seconds(fn: Callable[[], object]) -> float:
    """Wall seconds of ``fn()``."""
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def best_of(fn: Callable[[], object], repeats: int) -> float:
    return min(seconds(fn) for _ in range(max(1, repeats)))


def round_robin(cases: dict[str, Callable[[int], object]], rounds: int, order: str = "fixed") -> dict[str, list]:
    """``{case: [its result per round]}``; every round calls each case once with the round's index, in a
    ``fixed`` order, or reversed every other round (``alternate``), or shifted by one each round (``rotate``),
    so that load from other processes on a shared machine hits every case alike."""
    names = list(cases)
    out: dict[str, list] = {n: [] for n in names}
    for i in range(rounds):
        k = i % len(names) if order == "rotate" else 0
        seq = names[::-1] if order == "alternate" and i % 2 else names[k:] + names[:k]
        for name in seq:
            out[name].append(cases[name](i))
    return out


def medians(times: dict[str, list[float]]) -> dict[str, float]:
    return {k: statistics.median(v) for k, v in times.items()}


def minima(times: dict[str, list[float]]) -> dict[str, float]:
    return {k: min(v) for k, v in times.items()}
