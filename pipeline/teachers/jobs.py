"""The teacher's unit of work (:class:`TeacherJob`) and its one per-batch function (:func:`answer_job`).

Both are shared by the serial loop and the Ray actors.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from pipeline.teachers import make_teacher
from pipeline.teachers.base import VIEWS, Teacher, TeacherInput, finalize_answers
from pipeline.teachers.cache import TeacherCache

__all__ = ["InputLoader", "flip_answer", "in_view", "TeacherBuildArgs", "TeacherJob", "predict_view", "answer_job"]

#: row index, view -> TeacherInput (image already in that view); picklable for the Ray executor
InputLoader = Callable[[int, str], TeacherInput]


def flip_answer(mask: np.ndarray) -> np.ndarray:
    """Undo the vertical flip of the ``vflip`` view (rows reversed; an involution).

    Parameters
    ----------
    mask : numpy.ndarray
        Masks [..., H, W] answered in the ``vflip`` view.

    Returns
    -------
    numpy.ndarray
        The masks in the identity view, contiguous.
    """
    return np.ascontiguousarray(mask[..., ::-1, :])


def in_view(array: np.ndarray, view: str) -> np.ndarray:
    """Show an image (or reference mask) of the identity view as the teacher sees it in ``view``.

    Parameters
    ----------
    array : numpy.ndarray
        [H, W, ...] in the identity view.
    view : str
        One of :data:`pipeline.teachers.base.VIEWS`.

    Returns
    -------
    numpy.ndarray
        ``array`` itself for ``identity``; its rows reversed (contiguous) for ``vflip``.

    Raises
    ------
    ValueError
        ``view`` is not one of the views.
    """
    if view not in VIEWS:
        raise ValueError(f"view {view!r}: expected one of {VIEWS}")
    return np.ascontiguousarray(array[::-1]) if view == "vflip" else array


@dataclasses.dataclass(frozen=True)
class TeacherBuildArgs:
    """What a worker needs to build the same teacher: :func:`pipeline.teachers.make_teacher` arguments.

    Attributes
    ----------
    cfg : Mapping
        The ``teacher:`` section.
    resolution : tuple of int
        (H, W) of the working resolution.
    device : str
        ``auto``, ``cpu`` or ``cuda``.
    """

    cfg: Mapping[str, Any]
    resolution: tuple[int, int]
    device: str = "auto"

    def build(self) -> Teacher:
        """Build the teacher.

        Returns
        -------
        Teacher
            :func:`pipeline.teachers.make_teacher` of these arguments.
        """
        return make_teacher(self.cfg, self.resolution, self.device)


@dataclasses.dataclass(frozen=True)
class TeacherJob:
    """One batch of work: ``rows`` in ``view``, one forward over ``prompts``.

    Only ``missing[b]`` is written for ``rows[b]``, never overwriting a cached answer.

    Attributes
    ----------
    view : str
        One of :data:`pipeline.teachers.base.VIEWS`.
    rows : tuple of int
        The images' rows.
    prompts : tuple of str
        The union of the rows' missing prompts: what the forward answers.
    missing : tuple of tuple of str
        Per row, the prompts whose answers are not cached.
    """

    view: str
    rows: tuple[int, ...]
    prompts: tuple[str, ...]
    missing: tuple[tuple[str, ...], ...]

    def inputs(self, load: InputLoader) -> list[TeacherInput]:
        """Load the job's images in its view.

        Parameters
        ----------
        load : InputLoader
            ``(row, view) -> TeacherInput``.

        Returns
        -------
        list of TeacherInput
            One per row, in order.
        """
        return [load(r, self.view) for r in self.rows]


def predict_view(teacher: Teacher, inputs: Sequence[TeacherInput], prompts: Sequence[str],
                 view: str) -> tuple[np.ndarray, np.ndarray]:
    """Answer ``prompts`` for ``inputs`` in ``view``, the masks flipped back to the identity view.

    Parameters
    ----------
    teacher : Teacher
        The teacher.
    inputs : sequence of TeacherInput
        B images, already in ``view``.
    prompts : sequence of str
        The K prompts.
    view : str
        One of :data:`pipeline.teachers.base.VIEWS`.

    Returns
    -------
    tuple of numpy.ndarray
        Masks bool [B,K,H,W] and scores float32 [B,K], the invalid-prompt convention enforced
        (:func:`pipeline.teachers.base.finalize_answers`).

    Raises
    ------
    RuntimeError
        The teacher answered another number of images or prompts.
    """
    masks, scores = teacher.predict(list(inputs), list(prompts))
    masks, scores = finalize_answers(masks, scores)
    if masks.shape[:2] != (len(inputs), len(prompts)):
        raise RuntimeError(f"teacher {teacher.backend} returned masks {masks.shape} for "
                           f"{len(inputs)} images x {len(prompts)} prompts")
    if view == "vflip":
        masks = flip_answer(masks)
    return masks, scores


def answer_job(teacher: Teacher, cache: TeacherCache, job: TeacherJob, inputs: Sequence[TeacherInput]) -> int:
    """Compute one job and write its missing entries to the cache (a retry rewrites the same bytes).

    Parameters
    ----------
    teacher : Teacher
        The teacher.
    cache : TeacherCache
        Where the answers go.
    job : TeacherJob
        The job.
    inputs : sequence of TeacherInput
        Its images (:meth:`TeacherJob.inputs`).

    Returns
    -------
    int
        The entries written.
    """
    masks, scores = predict_view(teacher, inputs, job.prompts, job.view)
    written = 0
    for b, (item, want) in enumerate(zip(inputs, job.missing)):
        for k, prompt in enumerate(job.prompts):
            if prompt in want:
                cache.put(cache.key(item.image_sha256, prompt, job.view), masks[b, k], float(scores[b, k]))
                written += 1
    return written
