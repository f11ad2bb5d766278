"""The rankings of ``review export --ranking`` (and ``review.ranking``).

Each scores an image in [0, 1], higher = more in need of a person, ties by image id (the default,
:data:`DEFAULT_RANKING`: docs/decisions.md).
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
    """One ranking of the images to review.

    Attributes
    ----------
    name : str
        Its name (``--ranking``, ``review.ranking``).
    description : str
        What it scores, for ``--help``.
    needs : tuple of str
        The label table's columns it reads.
    """

    name: str
    description: str
    needs: tuple[str, ...]


RANKINGS = {r.name: r for r in (
    Ranking("combined", "mean percentile rank of 1 - g and h (and the student disagreement when given)", ("g", "h")),
    Ranking("gate", "1 - g: lowest reliability gate first", ("g",)),
    Ranking("disagreement", "h: highest prompt disagreement first", ("h",)),
    Ranking("student", "1 - IoU(student, vote): student-teacher disagreement (needs --student)", (STUDENT_COLUMN,)),
)}
DEFAULT_RANKING = "combined"


def _pct(values) -> np.ndarray:
    """Rank ``values`` as percentiles in (0, 1] (ties share their average rank)."""
    import pandas as pd

    return pd.Series(np.asarray(values, np.float64)).rank(method="average", pct=True).to_numpy()


def scores(table, ranking: str = DEFAULT_RANKING) -> np.ndarray:
    """Score every row of a label ``table`` under ``ranking``: higher = more in need of a person.

    ``gate``: 1 - g (eq:reliability-gate); ``disagreement``: the prompt disagreement h
    (:func:`pipeline.consensus.agreement_entropy`); ``student``: the student disagreement column;
    ``combined``: the mean percentile rank of 1 - g, h and (when the table has it) the student disagreement.

    Parameters
    ----------
    table : pandas.DataFrame
        The label table (``labels.parquet`` of ``geodistill label``, or the DAG's view of the training images).
    ranking : str
        A key of :data:`RANKINGS` (default :data:`DEFAULT_RANKING`).

    Returns
    -------
    numpy.ndarray
        float64 [len(table)], in [0, 1].

    Raises
    ------
    pipeline.runtime.errors.InputError
        Naming ``--ranking`` for an unknown ranking or a column the table lacks (the student's: pass
        ``--student``).
    """
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
    """Order ``table`` by :func:`scores` (highest first), ties by image id.

    Parameters
    ----------
    table : pandas.DataFrame
        The label table (``image_id`` and the columns ``ranking`` reads).
    ranking : str
        A key of :data:`RANKINGS`.
    top : int, optional
        Keep the first ``top`` rows; None keeps all.

    Returns
    -------
    pandas.DataFrame
        A copy with ``rank`` (1-based) and ``score`` columns first, re-indexed from 0.
    """
    out = table.copy()
    out.insert(0, "score", scores(table, ranking))
    out = out.sort_values(["score", "image_id"], ascending=[False, True], kind="mergesort").reset_index(drop=True)
    out.insert(0, "rank", np.arange(1, len(out) + 1))
    return out if top is None else out.head(int(top)).reset_index(drop=True)


def student_disagreement(student: np.ndarray, voted: np.ndarray) -> float:
    """Measure how much the student disagrees with the teacher vote: 1 - Image IoU of their masks.

    Parameters
    ----------
    student : numpy.ndarray
        The student's binary mask (eq:inference-mask).
    voted : numpy.ndarray
        The voted pseudo-mask (eq:majority-vote), the same shape.

    Returns
    -------
    float
        1 - :func:`pipeline.metrics.image_iou` (student, voted), in [0, 1].
    """
    return 1.0 - image_iou(student, voted)
