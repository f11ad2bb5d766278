"""What "the same published number" means: the reproducibility tolerance, written once.

A rerun of a published protocol -- another machine of the same kind, another thread count, fp32 instead
of bf16 -- reproduces a student metric when every test group's mean metric is within these absolute
tolerances of the published one.  The stability benchmark judges a training recipe against them, and CI
judges a fresh demo run against the committed metrics with them.

Keys are the metric names of the DVC metrics files (``reports/metrics/students/<group>/<method>.json``):
``iou`` = mean test Image IoU, ``bf1`` = mean test Boundary F1 (pipeline.metrics).

:func:`compare_metrics` and :func:`difference_table` are CI's check (``geodistill reproduce-check``,
pipeline/cli/reproduce_check.py): the student metrics of a fresh ``make demo`` against the committed ones.
"""

from __future__ import annotations

import dataclasses
from typing import Mapping, Sequence

#: Absolute tolerance per published student metric (mean over a test group's images).
TOLERANCE: dict[str, float] = {"iou": 0.01, "bf1": 0.02}


# --------------------------------------------------------------------------------------------------
# CI's check: a fresh demo run against the committed student metrics
# --------------------------------------------------------------------------------------------------
#: float slack when judging |fresh - committed| <= tolerance: the files hold 4-decimal values
#: (pipeline.report.dvc_results.DECIMALS), whose difference is not exact in binary floating point
SLACK = 1e-9


@dataclasses.dataclass(frozen=True)
class MetricDiff:
    """One (metrics file, key) compared: ``status`` is ``ok``, ``over`` (|fresh - committed| above the
    tolerance), ``missing`` (committed, but the fresh run has no such file or key) or ``extra`` (in the
    fresh run, not committed)."""

    file: str
    key: str
    committed: float | None
    fresh: float | None
    tolerance: float
    status: str

    @property
    def diff(self) -> float | None:
        return None if self.committed is None or self.fresh is None else self.fresh - self.committed


def compare_metrics(committed: Mapping[str, Mapping[str, float]], fresh: Mapping[str, Mapping[str, float]],
                    tolerance: Mapping[str, float] = TOLERANCE) -> list[MetricDiff]:
    """Compare every ``tolerance`` key of every metrics file, ``{relative path: {key: value}}`` on both
    sides (``<group>/<method>.json`` under reports/metrics/students).

    A value reproduces when ``|fresh - committed| <= tolerance[key]`` (+ :data:`SLACK`).  A file or key
    only committed is ``missing``; a file only in the fresh run is ``extra`` (the committed results no
    longer describe what the DAG produces).  Rows sorted by file, then key order of ``tolerance``.
    """
    rows = []
    for file in sorted(set(committed) | set(fresh)):
        c, f = committed.get(file), fresh.get(file)
        for key, tol in tolerance.items():
            cv = None if c is None else c.get(key)
            fv = None if f is None else f.get(key)
            if cv is None and fv is None:
                continue
            if cv is None:
                status = "extra"
            elif fv is None:
                status = "missing"
            else:
                status = "ok" if abs(float(fv) - float(cv)) <= tol + SLACK else "over"
            rows.append(MetricDiff(file, key, None if cv is None else float(cv), None if fv is None else float(fv),
                                   float(tol), status))
    return rows


def reproduced(rows: Sequence[MetricDiff]) -> bool:
    """True when there is something to compare and every row is ``ok``."""
    return bool(rows) and all(r.status == "ok" for r in rows)


STATUS_TEXT = {"ok": "ok", "over": "DIFFERS", "missing": "MISSING in the fresh run",
               "extra": "NOT COMMITTED (only in the fresh run)"}


def difference_table(rows: Sequence[MetricDiff]) -> str:
    """The comparison as a Markdown table (metrics file, metric, committed, fresh, difference,
    tolerance, status)."""
    def num(v, sign=False):
        return "--" if v is None else (f"{v:+.4f}" if sign else f"{v:.4f}")

    lines = ["| metrics file | metric | committed | fresh | fresh - committed | tolerance | status |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {r.file} | {r.key} | {num(r.committed)} | {num(r.fresh)} | {num(r.diff, True)} | "
              f"{r.tolerance:.4f} | {STATUS_TEXT[r.status]} |" for r in rows]
    return "\n".join(lines)
