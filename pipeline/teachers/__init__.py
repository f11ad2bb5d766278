"""Teachers of eq:teacher-prediction: SAM 3 (transformers), imported masks, and a SIMULATOR.

``make_teacher(cfg, resolution, device)`` builds the backend named by ``teacher.backend``;
``check_teacher_params(cfg)`` validates the ``teacher:`` section; ``teacher_fingerprint(t)`` is the
sha256 that keys the content-addressed cache (:mod:`pipeline.teachers.cache`).
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any, Mapping

from pipeline.artifacts import canonical_json
from pipeline.errors import InputError
from pipeline.params import require
from pipeline.teachers.base import VIEWS, Teacher, TeacherInput, finalize_answers

BACKENDS = ("simulated", "sam3", "imported")
SPLITS = ("train", "val", "test")

__all__ = ["BACKENDS", "VIEWS", "Teacher", "TeacherInput", "finalize_answers", "check_teacher_params",
           "make_teacher", "teacher_fingerprint"]


def check_teacher_params(cfg: Mapping[str, Any]) -> dict:
    """Validate the ``teacher:`` section; InputError naming the parameter on any problem."""
    cfg = dict(cfg)
    backend = require(cfg, "backend", "teacher", kind=str)
    if backend not in BACKENDS:
        raise InputError(f"params: teacher.backend={backend!r} is not one of {list(BACKENDS)}")
    prompts = require(cfg, "prompts", "teacher", kind=list)
    if not prompts:
        raise InputError("params: teacher.prompts is empty; eq:prompt-set needs at least one prompt")
    for i, p in enumerate(prompts):
        if not isinstance(p, str) or not p.strip():
            raise InputError(f"params: teacher.prompts[{i}]={p!r} must be a non-empty string")
    if len({p.strip().lower() for p in prompts}) != len(prompts):
        raise InputError(f"params: teacher.prompts has duplicates: {prompts}")
    k = require(cfg, "base_prompt_index", "teacher", kind=int, lo=0, hi=len(prompts) - 1)
    require(cfg, "vflip_base_prompt", "teacher", kind=bool)
    splits = require(cfg, "splits", "teacher", kind=list)
    bad = [s for s in splits if s not in SPLITS]
    if bad or not splits:
        raise InputError(f"params: teacher.splits={splits!r} must be a non-empty subset of {list(SPLITS)}")
    dtype = require(cfg, "dtype", "teacher", kind=str)
    if dtype not in ("fp32", "bf16"):
        raise InputError(f"params: teacher.dtype={dtype!r}: expected fp32 or bf16")
    require(cfg, "batch_size", "teacher", kind=int, lo=1)
    require(cfg, "seed", "teacher", kind=int)
    require(cfg, "cache_dir", "teacher", kind=str)
    for key in ("score_threshold", "mask_threshold"):
        if key in cfg:
            require(cfg, key, "teacher", kind=(int, float), lo=0.0, hi=1.0)
    if backend == "sam3" and not cfg.get("checkpoint"):
        raise InputError("params: teacher.checkpoint is required for backend sam3 "
                         "(a local directory saved with save_pretrained)")
    if backend == "imported" and not cfg.get("imported_dir"):
        raise InputError("params: teacher.imported_dir is required for backend imported")
    cfg["base_prompt_index"] = k
    return cfg


def make_teacher(cfg: Mapping[str, Any], resolution: tuple[int, int], device: str = "auto") -> Teacher:
    """The backend named by ``cfg['backend']`` working at ``resolution`` (H, W) of images.zarr."""
    cfg = check_teacher_params(cfg)
    backend = cfg["backend"]
    if backend == "simulated":
        from pipeline.teachers.simulated import SimulatedFoundationTeacher

        return SimulatedFoundationTeacher(seed=cfg["seed"], resolution=resolution)
    if backend == "imported":
        from pipeline.teachers.imported import ImportedTeacher

        return ImportedTeacher(cfg["imported_dir"], resolution=resolution)
    from pipeline.teachers.sam3 import Sam3Teacher

    return Sam3Teacher(cfg["checkpoint"], device=device, dtype=cfg["dtype"], batch_size=cfg["batch_size"],
                       resolution=resolution, score_threshold=cfg.get("score_threshold", 0.3),
                       mask_threshold=cfg.get("mask_threshold", 0.5),
                       hash_memo=Path(cfg["cache_dir"]) / "checkpoint_hashes.json")


def teacher_fingerprint(teacher: Teacher) -> str:
    """sha256 of the canonical JSON of ``teacher.fingerprint()`` (the cache's teacher component)."""
    return hashlib.sha256(canonical_json(teacher.fingerprint()).encode()).hexdigest()
