"""The teacher's unit of work (:class:`TeacherJob`) and its one per-batch function (:func:`answer_job`),
shared by the serial loop and the Ray actors."""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from pipeline.teachers import make_teacher
from pipeline.teachers.base import VIEWS, Teacher, TeacherInput, finalize_answers
from pipeline.teachers.cache import TeacherCache

# row index, view -> TeacherInput (image already in that view); picklable for the Ray executor
InputLoader = Callable[[int, str], TeacherInput]


def flip_answer(mask: np.ndarray) -> np.ndarray:
    """Undo the vertical flip of the ``vflip`` view (rows reversed; an involution)."""
    return np.ascontiguousarray(mask[..., ::-1, :])


def in_view(array: np.ndarray, view: str) -> np.ndarray:
    """An image (or reference mask) of the identity view as the teacher sees it in ``view``."""
    if view not in VIEWS:
        raise ValueError(f"view {view!r}: expected one of {VIEWS}")
    return np.ascontiguousarray(array[::-1]) if view == "vflip" else array


@dataclasses.dataclass(frozen=True)
class TeacherBuildArgs:
    """What a worker needs to build the same teacher: :func:`pipeline.teachers.make_teacher` arguments."""

    cfg: Mapping[str, Any]
    resolution: tuple[int, int]
    device: str = "auto"

    def build(self) -> Teacher:
        return make_teacher(self.cfg, self.resolution, self.device)


@dataclasses.dataclass(frozen=True)
class TeacherJob:
    """One batch of work: ``rows`` in ``view``, one forward over ``prompts`` (the union of the rows'
    missing prompts); only ``missing[b]`` is written for ``rows[b]``, never overwriting a cached answer."""

    view: str
    rows: tuple[int, ...]
    prompts: tuple[str, ...]
    missing: tuple[tuple[str, ...], ...]

    def inputs(self, load: InputLoader) -> list[TeacherInput]:
        return [load(r, self.view) for r in self.rows]


def predict_view(teacher: Teacher, inputs: Sequence[TeacherInput], prompts: Sequence[str],
                 view: str) -> tuple[np.ndarray, np.ndarray]:
    """masks bool [B,K,H,W] and scores float32 [B,K] of ``inputs`` (already in ``view``), flipped back."""
    masks, scores = teacher.predict(list(inputs), list(prompts))
    masks, scores = finalize_answers(masks, scores)
    if masks.shape[:2] != (len(inputs), len(prompts)):
        raise RuntimeError(f"teacher {teacher.backend} returned masks {masks.shape} for "
                           f"{len(inputs)} images x {len(prompts)} prompts")
    if view == "vflip":
        masks = flip_answer(masks)
    return masks, scores


def answer_job(teacher: Teacher, cache: TeacherCache, job: TeacherJob, inputs: Sequence[TeacherInput]) -> int:
    """Compute one job and write its missing entries (a retry rewrites the same bytes); returns how many."""
    masks, scores = predict_view(teacher, inputs, job.prompts, job.view)
    written = 0
    for b, (item, want) in enumerate(zip(inputs, job.missing)):
        for k, prompt in enumerate(job.prompts):
            if prompt in want:
                cache.put(cache.key(item.image_sha256, prompt, job.view), masks[b, k], float(scores[b, k]))
                written += 1
    return written
