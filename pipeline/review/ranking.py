"""The rankings of ``review export --ranking``: each scores an image in [0, 1], higher = more in need of a
person, ties by image id (the default ``combined``: docs/decisions.md).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from pipeline.runtime.errors import InputError, Option
from pipeline.metrics import image_iou

__all__ = ["STUDENT_COLUMN", "RANKINGS", "DEFAULT_RANKING", "scores", "rank", "student_disagreement"]

RANKING = Option("--ranking", "ranking")
STUDENT_COLUMN = "student_disagreement"


@dataclasses.dataclass(frozen=True)
class Ranking:
    name: str
    description: str
    needs: tuple[str, ...]   # the label table's columns it reads


RANKINGS = {r.name: r for r in (
    Ranking("combined", "mean percentile rank of 1 - g and h (and the student disagreement when given)", ("g", "h")),
    Ranking("gate", "1 - g: lowest reliability gate first", ("g",)),
    Ranking("disagreement", "h: highest prompt disagreement first", ("h",)),
    Ranking("student", "1 - IoU(student, vote): student-teacher disagreement (needs --student)", (STUDENT_COLUMN,)),
)}
DEFAULT_RANKING = "combined"


def _pct(values) -> np.ndarray:
    """Percentile ranks in (0, 1] (ties share their average rank)."""
    import pandas as pd

    return pd.Series(np.asarray(values, np.float64)).rank(method="average", pct=True).to_numpy()


def scores(table, ranking: str = DEFAULT_RANKING) -> np.ndarray:
    """The score of every row of a label ``table`` under ``ranking``; InputError on an unknown one or column."""
    if ranking not in RANKINGS:
        raise InputError(f"{{}}: unknown ranking (choose one of {', '.join(RANKINGS)})", RANKING(ranking))
    missing = [c for c in RANKINGS[ranking].needs if c not in table.columns]
    if missing == [STUDENT_COLUMN]:
        raise InputError("{}: needs a student (pass --student BUNDLE, a deploy bundle)", RANKING(ranking))
    if missing:
        raise InputError(f"{{}}: the label table has no column {missing[0]!r} (made by an older label; rerun "
                         f"geodistill label into the same folder: it resumes from its cache)", RANKING(ranking))
    if ranking != "combined":   # one column: g (as 1 - g), h or the student's
        values = table[RANKINGS[ranking].needs[0]].to_numpy(np.float64)
        return 1.0 - values if ranking == "gate" else values
    parts = [_pct(1.0 - table["g"].to_numpy(np.float64)), _pct(table["h"])]
    if STUDENT_COLUMN in table.columns:
        parts.append(_pct(table[STUDENT_COLUMN]))
    return np.mean(parts, axis=0)


def rank(table, ranking: str = DEFAULT_RANKING, top: int | None = None):
    """The first ``top`` rows (None: all) of ``table`` by :func:`scores`, then image id, with ``rank`` and ``score``."""
    out = table.copy()
    out.insert(0, "score", scores(table, ranking))
    out = out.sort_values(["score", "image_id"], ascending=[False, True], kind="mergesort").reset_index(drop=True)
    out.insert(0, "rank", np.arange(1, len(out) + 1))
    return out if top is None else out.head(int(top)).reset_index(drop=True)


def student_disagreement(student: np.ndarray, voted: np.ndarray) -> float:
    """1 - Image IoU of the student's and the vote's masks."""
    return 1.0 - image_iou(student, voted)
