"""The teacher interface (eq:teacher-prediction): per (image, prompt) the best candidate mask and score.

The answers are at the working resolution; no candidate or a score <= 0 is *invalid* (score 0, empty mask, out
of the valid-prompt set V_i of eq:agreement-map).
"""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path
from typing import Any, Mapping, Protocol, Sequence, runtime_checkable

import numpy as np

from pipeline.teacher_table import teacher_spec

__all__ = ["VIEWS", "MANIFEST_EXTRAS", "TeacherInput", "Teacher", "RegisteredTeacher", "finalize_answers",
           "manifest_extras", "files_digest"]

#: the views a teacher answers in: the image itself, and flipped vertically (its answers flipped back)
VIEWS = ("identity", "vflip")
#: the manifest columns a teacher that reads the reference (the SIMULATOR) also gets (``TeacherInput.extras``)
MANIFEST_EXTRAS = ("background", "hard_case", "area_fraction")


@dataclasses.dataclass
class TeacherInput:
    """One image as a teacher sees it.

    Attributes
    ----------
    image_id : str
        The image's id in the manifest.
    image_sha256 : str
        The sha256 of its decoded pixels (the teacher cache's image component).
    image : numpy.ndarray
        uint8 [H,W,3] at the working resolution, already in ``view`` (the runner flips answers back).
    view : str
        One of :data:`VIEWS`.
    reference : Mapping or None
        Only for the SIMULATOR: the reference ``mask`` (and optional ``parts``), in ``view``; else None.
    extras : Mapping
        Only for the SIMULATOR: the image's :data:`MANIFEST_EXTRAS` values; else empty.
    """

    image_id: str
    image_sha256: str
    image: np.ndarray
    view: str = "identity"
    reference: Mapping[str, np.ndarray] | None = None
    extras: Mapping[str, Any] = dataclasses.field(default_factory=dict)


@runtime_checkable
class Teacher(Protocol):
    """What the teacher stage needs from a backend (eq:teacher-prediction).

    Attributes
    ----------
    backend : str
        Its name in :data:`pipeline.teacher_table.TEACHER_TABLE`.
    use_cache : bool
        Its answers go through the teacher cache (False where reading the source is as cheap: imported).
    """

    backend: str
    use_cache: bool         # False where reading the source is as cheap as the cache (imported)

    def fingerprint(self) -> dict:
        """Describe everything that determines the answers.

        Returns
        -------
        dict
            JSON-able: backend, checkpoint hash, resolution, dtype, ... (:func:`pipeline.teachers.teacher_record`).
        """

    def predict(self, batch: Sequence[TeacherInput], prompts: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        """Answer every prompt for every image: (M_ik, s_ik) of eq:teacher-prediction.

        Parameters
        ----------
        batch : sequence of TeacherInput
            B images, each in its view.
        prompts : sequence of str
            The K prompts.

        Returns
        -------
        tuple of numpy.ndarray
            Masks bool [B,K,H,W] and scores float32 [B,K] (0 = invalid: :func:`finalize_answers`).
        """


class RegisteredTeacher:
    """What the built-in backends share: their table row states their capabilities.

    A subclass sets ``backend`` and writes ``from_params(cfg, resolution, device)`` (from the validated
    ``teacher:`` section, :func:`pipeline.teachers.make_teacher`), ``fingerprint`` and ``predict``
    (:class:`Teacher`).

    Attributes
    ----------
    backend : str
        Its name in :data:`pipeline.teacher_table.TEACHER_TABLE`, whose row states its capabilities.
    """

    backend: str

    @property
    def use_cache(self) -> bool:
        """Whether the answers go through the teacher cache (the table row's ``use_cache``)."""
        return teacher_spec(self.backend).use_cache


def finalize_answers(masks: np.ndarray, scores: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Enforce the invalid-prompt convention on copies: score <= 0 (or NaN) -> score 0 and an empty mask.

    Parameters
    ----------
    masks : array_like
        Masks [..., H, W] (non-zero: foreground).
    scores : array_like
        Scores, the masks' leading shape.

    Returns
    -------
    tuple of numpy.ndarray
        Masks bool and scores float32: an invalid prompt's score 0 and mask empty (out of V_i,
        eq:agreement-map).
    """
    masks = np.asarray(masks, dtype=bool).copy()
    scores = np.asarray(scores, dtype=np.float32).copy()
    invalid = ~(scores > 0)  # catches NaN too
    scores[invalid] = 0.0
    masks[invalid] = False
    return masks, scores


def manifest_extras(manifest) -> list[dict[str, Any]]:
    """Read the SIMULATOR's extras of every manifest row (:attr:`TeacherInput.extras`).

    Parameters
    ----------
    manifest : pandas.DataFrame
        The manifest, indexed 0..N-1.

    Returns
    -------
    list of dict
        Per row, its :data:`MANIFEST_EXTRAS` values (those the manifest has).
    """
    cols = [c for c in MANIFEST_EXTRAS if c in manifest.columns]
    return [{c: manifest.at[row, c] for c in cols} for row in range(len(manifest))]


def files_digest(root: Path, files: Sequence[Path], h=None) -> str:
    """Hash files: each one's path relative to ``root`` and its bytes, in the given order.

    Parameters
    ----------
    root : Path
        The folder the paths are taken relative to.
    files : sequence of Path
        Files under ``root``.
    h : hashlib sha256 object, optional
        A hash to continue; None (default): a new sha256.

    Returns
    -------
    str
        The hex digest.
    """
    h = h or hashlib.sha256()
    for p in files:
        h.update(Path(p).relative_to(root).as_posix().encode())
        with open(p, "rb") as f:
            for block in iter(lambda: f.read(1 << 22), b""):
                h.update(block)
    return h.hexdigest()
