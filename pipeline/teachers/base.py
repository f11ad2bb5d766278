"""The teacher interface (eq:teacher-prediction): per (image, prompt) the best candidate mask and score at
the working resolution; no candidate or a score <= 0 is *invalid* (score 0, empty mask, out of eq:valid-set)."""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path
from typing import Any, Mapping, Protocol, Sequence, runtime_checkable

import numpy as np

from pipeline.teacher_table import teacher_spec

VIEWS = ("identity", "vflip")
#: the manifest columns a teacher that reads the reference (the SIMULATOR) also gets (``TeacherInput.extras``)
MANIFEST_EXTRAS = ("background", "hard_case", "area_fraction")


@dataclasses.dataclass
class TeacherInput:
    """One image as a teacher sees it: uint8 [H,W,3], already in ``view`` (the runner flips answers back);
    ``reference`` (``mask``, optional ``parts``) and ``extras`` only for the SIMULATOR."""

    image_id: str
    image_sha256: str
    image: np.ndarray
    view: str = "identity"
    reference: Mapping[str, np.ndarray] | None = None
    extras: Mapping[str, Any] = dataclasses.field(default_factory=dict)


@runtime_checkable
class Teacher(Protocol):
    """What the teacher stage needs from a backend."""

    backend: str
    use_cache: bool         # False where reading the source is as cheap as the cache (imported)

    def fingerprint(self) -> dict:
        """Everything that determines the answers (backend, checkpoint hash, resolution, dtype, ...)."""

    def predict(self, batch: Sequence[TeacherInput], prompts: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        """Answer every prompt for every image: masks bool [B,K,H,W], scores float32 [B,K] (0 = invalid)."""


class RegisteredTeacher:
    """What the backends share: ``backend``, their name in :data:`pipeline.teacher_table.TEACHER_TABLE`, whose row
    states their capabilities; a subclass sets ``backend`` and writes ``from_params(cfg, resolution, device)``
    (from the validated ``teacher:`` section, :func:`pipeline.teachers.make_teacher`), ``fingerprint`` and
    ``predict``."""

    backend: str

    @property
    def use_cache(self) -> bool:
        return teacher_spec(self.backend).use_cache


def finalize_answers(masks: np.ndarray, scores: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Enforce the invalid-prompt convention on copies: score <= 0 (or NaN) -> score 0 and an empty mask."""
    masks = np.asarray(masks, dtype=bool).copy()
    scores = np.asarray(scores, dtype=np.float32).copy()
    invalid = ~(scores > 0)  # catches NaN too
    scores[invalid] = 0.0
    masks[invalid] = False
    return masks, scores


def manifest_extras(manifest) -> list[dict[str, Any]]:
    """Per row of the manifest frame (index 0..N-1), its :data:`MANIFEST_EXTRAS` values (those it has)."""
    cols = [c for c in MANIFEST_EXTRAS if c in manifest.columns]
    return [{c: manifest.at[row, c] for c in cols} for row in range(len(manifest))]


def files_digest(root: Path, files: Sequence[Path], h=None) -> str:
    """sha256 (continuing ``h``) over each file's path relative to ``root`` and its bytes, in the given order."""
    h = h or hashlib.sha256()
    for p in files:
        h.update(Path(p).relative_to(root).as_posix().encode())
        with open(p, "rb") as f:
            for block in iter(lambda: f.read(1 << 22), b""):
                h.update(block)
    return h.hexdigest()
