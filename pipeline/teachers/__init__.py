"""Teachers of eq:teacher-prediction: SAM 3 (transformers), imported masks, and a SIMULATOR.

``make_teacher(cfg, resolution, device)`` builds the backend named by ``teacher.backend``;
``check_teacher_params(cfg)`` validates the ``teacher:`` section; ``teacher_fingerprint(t)`` is the
sha256 that keys the content-addressed cache (:mod:`pipeline.teachers.cache`).
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any, Mapping

from fsspec.core import url_to_fs
from fsspec.implementations.local import LocalFileSystem

from pipeline.artifacts import canonical_json
from pipeline.params import BACKENDS, validate_section
from pipeline.teachers.base import VIEWS, Teacher, TeacherInput, finalize_answers
from pipeline.teachers.sam3 import Sam3Teacher
from pipeline.teachers.simulated import SimulatedFoundationTeacher


__all__ = ["BACKENDS", "VIEWS", "Teacher", "TeacherInput", "finalize_answers", "check_teacher_params",
           "make_teacher", "teacher_fingerprint"]


def check_teacher_params(cfg: Mapping[str, Any]) -> dict:
    """Validate the ``teacher:`` section against the params schema (:mod:`pipeline.params`)."""
    return validate_section("teacher", cfg)


def make_teacher(cfg: Mapping[str, Any], resolution: tuple[int, int], device: str = "auto") -> Teacher:
    """The backend named by ``cfg['backend']`` working at ``resolution`` (H, W) of images.zarr."""
    cfg = check_teacher_params(cfg)
    backend = cfg["backend"]
    if backend == "simulated":
        return SimulatedFoundationTeacher(seed=cfg["seed"], resolution=resolution)
    if backend == "imported":
        from pipeline.teachers.imported import ImportedTeacher

        return ImportedTeacher(cfg["imported_dir"], resolution=resolution)

    return Sam3Teacher(cfg["checkpoint"], device=device, dtype=cfg["dtype"], batch_size=cfg["batch_size"],
                       resolution=resolution, score_threshold=cfg.get("score_threshold", 0.3),
                       mask_threshold=cfg.get("mask_threshold", 0.5), compile=bool(cfg.get("compile", False)),
                       hash_memo=_local_memo(cfg["cache_dir"]))


def _local_memo(cache_dir: str) -> Path | None:
    """Where the checkpoint-hash memo lives: beside a local cache; none for a cache on object storage
    (the checkpoint is then hashed once per run)."""
    fs, path = url_to_fs(str(cache_dir))
    return Path(path) / "checkpoint_hashes.json" if isinstance(fs, LocalFileSystem) else None


def teacher_fingerprint(teacher: Teacher) -> str:
    """sha256 of the canonical JSON of ``teacher.fingerprint()`` (the cache's teacher component)."""
    return hashlib.sha256(canonical_json(teacher.fingerprint()).encode()).hexdigest()
