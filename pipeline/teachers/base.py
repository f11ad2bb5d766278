"""The teacher interface shared by every backend (eq:teacher-prediction).

For image :math:`I_i` and prompt :math:`p_k` a teacher returns its highest-scoring candidate mask
:math:`M_{ik} \\in \\{0,1\\}^{H\\times W}` and score :math:`s_{ik}` (eq:teacher-prediction).  A prompt
with no candidate, or a score :math:`\\le 0`, is *invalid*: its score is 0 and its mask is empty, so
it drops out of the valid-prompt set :math:`\\mathcal{V}_i` of eq:valid-set downstream.

Backends (``teacher.backend``):

* ``sam3``      -- :class:`pipeline.teachers.sam3.Sam3Teacher`, SAM 3 through transformers;
* ``imported``  -- :class:`pipeline.teachers.imported.ImportedTeacher`, masks produced elsewhere;
* ``simulated`` -- :class:`pipeline.teachers.simulated.SimulatedFoundationTeacher`, a SIMULATOR of a
  foundation model's prompt-dependent errors for the synthetic benchmark; it reads the synthetic
  scene's ground truth and is therefore never a real teacher.

Every backend works at the working resolution of ``images.zarr``: inputs are uint8 [H,W,3] images,
outputs bool [K,H,W] masks at the same H,W.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping, Protocol, Sequence, runtime_checkable

import numpy as np

VIEWS = ("identity", "vflip")
#: the manifest columns a teacher that reads the reference (the SIMULATOR) also gets (``TeacherInput.extras``)
MANIFEST_EXTRAS = ("background", "hard_case", "area_fraction")


@dataclasses.dataclass
class TeacherInput:
    """One image as a teacher sees it.

    ``image`` is uint8 [H,W,3] at the working resolution, already transformed to ``view`` (for
    ``vflip`` the rows are reversed; the runner flips the answer back).  ``reference`` (``mask``
    bool [H,W], optional ``parts`` uint8 [H,W]) and ``extras`` (manifest extra columns) are filled
    only for a teacher whose ``needs_reference`` is true -- the simulator.
    """

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
    needs_reference: bool   # the simulator reads reference.zarr; real teachers never do
    use_cache: bool         # False where reading the source is as cheap as the cache (imported)

    def fingerprint(self) -> dict:
        """Everything that determines the answers (backend, checkpoint hash, resolution, dtype, ...)."""

    def predict(self, batch: Sequence[TeacherInput], prompts: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        """Answer every prompt for every image: masks bool [B,K,H,W], scores float32 [B,K] (0 = invalid)."""


def finalize_answers(masks: np.ndarray, scores: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Enforce the invalid-prompt convention: score <= 0 (or NaN) -> score 0 and an empty mask.

    ``masks`` bool [..., H, W], ``scores`` float [...]; returns copies (bool, float32).
    """
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
