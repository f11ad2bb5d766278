"""Teachers of eq:teacher-prediction: SAM 3 (transformers), imported masks, and a SIMULATOR, by backend name."""

from __future__ import annotations

import hashlib
from typing import Any, Mapping

from pipeline.artifacts.lineage import canonical_json
from pipeline.params import BACKENDS, validate_section
from pipeline.teachers.base import VIEWS, Teacher, TeacherInput, finalize_answers
from pipeline.teachers.imported import ImportedTeacher
from pipeline.teachers.sam3 import Sam3Teacher
from pipeline.teachers.simulated import SimulatedFoundationTeacher

__all__ = ["BACKENDS", "TEACHERS", "VIEWS", "Teacher", "TeacherInput", "finalize_answers", "check_teacher_params",
           "make_teacher", "teacher_fingerprint"]

TEACHERS: dict[str, type] = {cls.backend: cls for cls in (SimulatedFoundationTeacher, Sam3Teacher, ImportedTeacher)}


def check_teacher_params(cfg: Mapping[str, Any]) -> dict:
    """Validate the ``teacher:`` section against the params schema (:mod:`pipeline.params`)."""
    return validate_section("teacher", cfg)


def make_teacher(cfg: Mapping[str, Any], resolution: tuple[int, int], device: str = "auto") -> Teacher:
    """The backend named by ``cfg['backend']`` (:data:`TEACHERS`) working at ``resolution`` (H, W) of images.zarr."""
    cfg = check_teacher_params(cfg)
    return TEACHERS[cfg["backend"]].from_params(cfg, resolution, device)


def teacher_fingerprint(teacher: Teacher) -> str:
    """sha256 of the canonical JSON of ``teacher.fingerprint()`` (the cache's teacher component)."""
    return hashlib.sha256(canonical_json(teacher.fingerprint()).encode()).hexdigest()
