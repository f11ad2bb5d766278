"""Which images a person should check first: the rankings of ``geodistill review export --ranking``.

Every ranking gives each image a score in [0, 1], higher = more in need of a person; images are listed
by score, highest first, ties broken by image id (the same table gives the same order).

``gate``          1 - g: the reliability gate (eq:reliability-gate) -- low agreement c, few valid prompts
                  v, or an implausible area a against the folder's median a0.
``disagreement``  h: the prompts' disagreement (:func:`pipeline.consensus.agreement_entropy`, the agreement map's
                  mean binary entropy over the union of the prompt masks; eq:agreement-map).
``student``       1 - IoU(student mask, voted mask) at the image's own size: where the distilled student
                  and its teacher's vote part ways (only with a student: ``--student BUNDLE``).
``combined``      the DEFAULT: the mean of the percentile ranks of 1 - g and h (and of the student
                  disagreement when a student is given).

Why ``combined`` is the default.  The two annotation-free signals see different failures: the gate sees
a vote that agrees with itself but is implausible (too few valid prompts, an area far from the
folder's median) -- where h can be 0 (every valid prompt empty, or all prompts wrong in the same way);
h sees disagreement on pixels the vote dropped (the outvoted panel, the glare blob a minority claimed),
which the gate's c (agreement inside the voted mask only, eq:foreground-agreement) does not.  The
gate also has a long tie at g = 0 (g_valid and g_conf floor to 0), which h orders.  Percentile ranks
combine them without calibrating one scale against the other.  The choice is argued; the one
measurement (``python -m benchmarks.review_value``, docs/review.md) does not settle it: on the
synthetic benchmark no selection of up to 50 corrected images moves the Plain Student's test IoU beyond
the seed noise, ``combined`` does not beat random at k = 25, and past its top ~10 its picks are no
worse-labelled than random's while ``gate`` keeps finding the simulator's breakdowns (which it finds
by construction there; a real teacher's failures need not line up with g).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from pipeline.runtime.errors import InputError, Option
from pipeline.metrics import image_iou

RANKING = Option("--ranking", "ranking")
STUDENT_COLUMN = "student_disagreement"


@dataclasses.dataclass(frozen=True)
class Ranking:
    name: str
    description: str
    needs: tuple[str, ...]   # columns of the label table (plus the student column) it reads


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
    """The score of every row of ``table`` (a label table, with the student column when there is one)
    under ``ranking`` (module docstring); InputError on an unknown ranking or a missing column."""
    if ranking not in RANKINGS:
        raise InputError(f"{{}}: unknown ranking (choose one of {', '.join(RANKINGS)})", RANKING(ranking))
    missing = [c for c in RANKINGS[ranking].needs if c not in table.columns]
    if missing == [STUDENT_COLUMN]:
        raise InputError("{}: needs a student (pass --student BUNDLE, a deploy bundle)", RANKING(ranking))
    if missing:
        raise InputError(f"{{}}: the label table has no column {missing[0]!r} (made by an older label; rerun "
                         f"geodistill label into the same folder: it resumes from its cache)", RANKING(ranking))
    g = 1.0 - table["g"].to_numpy(np.float64) if "g" in table.columns else None
    if ranking == "gate":
        return g
    if ranking == "disagreement":
        return table["h"].to_numpy(np.float64)
    if ranking == "student":
        return table[STUDENT_COLUMN].to_numpy(np.float64)
    parts = [_pct(g), _pct(table["h"])]
    if STUDENT_COLUMN in table.columns:
        parts.append(_pct(table[STUDENT_COLUMN]))
    return np.mean(parts, axis=0)


def rank(table, ranking: str = DEFAULT_RANKING, top: int | None = None):
    """``table`` sorted by :func:`scores` (highest first, then by image id), with columns ``rank``
    (1 = check first) and ``score`` in front; the first ``top`` rows (None: all)."""
    out = table.copy()
    out.insert(0, "score", scores(table, ranking))
    out = out.sort_values(["score", "image_id"], ascending=[False, True], kind="mergesort").reset_index(drop=True)
    out.insert(0, "rank", np.arange(1, len(out) + 1))
    return out if top is None else out.head(int(top)).reset_index(drop=True)


def student_disagreement(student: np.ndarray, voted: np.ndarray) -> float:
    """1 - Image IoU (:func:`pipeline.metrics.image_iou`) of the student's and the vote's masks."""
    return 1.0 - image_iou(student, voted)
