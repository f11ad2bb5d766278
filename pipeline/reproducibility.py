"""What "the same published number" means, and CI's check of a fresh demo against the committed metrics.

A rerun reproduces a student metric when every test group's mean is within :data:`TOLERANCE` of the published
one (keys: the DVC metrics files' ``iou`` and ``bf1``).
"""

from __future__ import annotations

import dataclasses
from typing import Mapping, Sequence

__all__ = ["TOLERANCE", "compare_metrics", "reproduced", "difference_table"]

TOLERANCE: dict[str, float] = {"iou": 0.01, "bf1": 0.02}
#: the files hold 4-decimal values, whose difference is not exact in binary floating point
SLACK = 1e-9


@dataclasses.dataclass(frozen=True)
class MetricDiff:
    """One (metrics file, key) compared.

    Attributes
    ----------
    file : str
        The metrics file's path relative to the metrics folder.
    key : str
        The metric (a key of :data:`TOLERANCE`).
    committed, fresh : float or None
        The committed and the fresh value; None where that side lacks it.
    tolerance : float
        The largest accepted absolute difference.
    status : str
        ok | over (the tolerance) | missing (in the fresh run) | extra (not committed).
    """

    file: str
    key: str
    committed: float | None
    fresh: float | None
    tolerance: float
    status: str

    @property
    def diff(self) -> float | None:
        """Fresh minus committed; None where a side is missing."""
        return None if self.committed is None or self.fresh is None else self.fresh - self.committed


def compare_metrics(committed: Mapping[str, Mapping[str, float]], fresh: Mapping[str, Mapping[str, float]],
                    tolerance: Mapping[str, float] = TOLERANCE) -> list[MetricDiff]:
    """Compare every ``tolerance`` key of every metrics file, committed against fresh.

    Parameters
    ----------
    committed, fresh : Mapping
        The metrics files on each side, ``{relative path: {key: value}}``.
    tolerance : Mapping
        Key -> the largest accepted absolute difference (default :data:`TOLERANCE`); other keys are not
        compared.

    Returns
    -------
    list of MetricDiff
        One row per (file, key) that either side holds, sorted by file, then by ``tolerance``'s key order.
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
    """Tell whether a comparison reproduced the published numbers.

    Parameters
    ----------
    rows : sequence of MetricDiff
        :func:`compare_metrics`.

    Returns
    -------
    bool
        True when there is something to compare and every row is ``ok``.
    """
    return bool(rows) and all(r.status == "ok" for r in rows)


STATUS_TEXT = {"ok": "ok", "over": "DIFFERS", "missing": "MISSING in the fresh run",
               "extra": "NOT COMMITTED (only in the fresh run)"}


def difference_table(rows: Sequence[MetricDiff]) -> str:
    """Write the comparison as a Markdown table.

    Parameters
    ----------
    rows : sequence of MetricDiff
        :func:`compare_metrics`.

    Returns
    -------
    str
        The table: file, metric, both values, their difference, the tolerance and the status, a line per row.
    """
    def num(v, sign=False):
        return "--" if v is None else (f"{v:+.4f}" if sign else f"{v:.4f}")

    lines = ["| metrics file | metric | committed | fresh | fresh - committed | tolerance | status |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {r.file} | {r.key} | {num(r.committed)} | {num(r.fresh)} | {num(r.diff, True)} | "
              f"{r.tolerance:.4f} | {STATUS_TEXT[r.status]} |" for r in rows]
    return "\n".join(lines)
