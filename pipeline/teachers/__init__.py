"""Teachers of eq:teacher-prediction: SAM 3 (transformers), imported masks, and a SIMULATOR, by backend name."""

from __future__ import annotations

import hashlib
from typing import Any, Mapping

from pipeline.artifacts.lineage import canonical_json
from pipeline.params import validate_section
from pipeline.teacher_table import TEACHER_TABLE, teacher_class, teacher_spec
from pipeline.teachers.base import VIEWS, Teacher, TeacherInput, finalize_answers

# the built-in backends TEACHER_TABLE names as "module:Class", imported here too so that running a teacher
# depends on their code (the stage's code version, dvc.yaml's deps: pipeline.runtime.codeversion)
from pipeline.teachers import imported, sam3, simulated  # noqa: F401

__all__ = ["TEACHER_TABLE", "VIEWS", "Teacher", "TeacherInput", "finalize_answers", "check_teacher_params",
           "make_teacher", "teacher_class", "teacher_fingerprint", "teacher_record"]


def check_teacher_params(cfg: Mapping[str, Any]) -> dict:
    """Validate the ``teacher:`` section against the params schema (:mod:`pipeline.params`).

    Parameters
    ----------
    cfg : Mapping
        A ``teacher:`` section.

    Returns
    -------
    dict
        The validated section, every default filled in.
    """
    return validate_section("teacher", cfg)


def make_teacher(cfg: Mapping[str, Any], resolution: tuple[int, int], device: str = "auto") -> Teacher:
    """Build the teacher backend that ``cfg['backend']`` names (:data:`TEACHER_TABLE`; a plug-in's loaded now).

    Parameters
    ----------
    cfg : Mapping
        The ``teacher:`` section, validated here (:func:`check_teacher_params`).
    resolution : tuple of int
        (H, W) of images.zarr: the working resolution of its answers.
    device : str, optional
        ``auto`` (default), ``cpu`` or ``cuda``.

    Returns
    -------
    Teacher
        The backend's ``from_params(cfg, resolution, device)``.
    """
    cfg = check_teacher_params(cfg)
    return teacher_class(cfg["backend"]).from_params(cfg, resolution, device)


def teacher_record(teacher: Teacher) -> dict:
    """Return what determines a teacher's answers: its fingerprint, with a plug-in's distribution.

    Parameters
    ----------
    teacher : Teacher
        A built teacher.

    Returns
    -------
    dict
        ``teacher.fingerprint()``, with a plug-in's ``"distribution"`` (its package's name and version: DVC and
        the code version do not see its code); a built-in backend's is its own fingerprint, unchanged.
    """
    dist = teacher_spec(teacher.backend).distribution
    return teacher.fingerprint() | ({"distribution": dist} if dist else {})


def teacher_fingerprint(teacher: Teacher) -> str:
    """Hash what determines a teacher's answers (the teacher cache's teacher component).

    Parameters
    ----------
    teacher : Teacher
        A built teacher.

    Returns
    -------
    str
        The sha256 hex digest of the canonical JSON of :func:`teacher_record`.
    """
    return hashlib.sha256(canonical_json(teacher_record(teacher)).encode()).hexdigest()
