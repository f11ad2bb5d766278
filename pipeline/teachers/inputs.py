"""The teacher stage's input loader: a row of ``images.zarr`` as a :class:`~pipeline.teachers.base.TeacherInput`.

For the SIMULATOR, ``reference.zarr`` too.  The loader is picklable for Ray workers (artifacts reopened
lazily).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from pipeline.artifacts.store import open_artifact
from pipeline.teachers.base import TeacherInput
from pipeline.teachers.jobs import in_view

__all__ = ["ArtifactInputs"]


class ArtifactInputs:
    """``(row, view) -> TeacherInput`` over ``images.zarr``; ``reference.zarr`` is read only when given.

    Parameters
    ----------
    images : str or Path
        The ``images`` artifact.
    reference : str or Path or None
        The ``reference`` artifact, for the SIMULATOR only; None for a real teacher.
    ids : sequence of str
        The image id of each row.
    shas : sequence of str
        The pixel sha256 of each row.
    extras : sequence of Mapping
        The SIMULATOR's extras of each row (:func:`pipeline.teachers.base.manifest_extras`).
    """

    def __init__(self, images: str | Path, reference: str | Path | None, ids: Sequence[str],
                 shas: Sequence[str], extras: Sequence[Mapping[str, Any]]):
        self.images = os.path.abspath(images)  # absolute: Ray workers need not share this cwd
        self.reference = os.path.abspath(reference) if reference is not None else None
        self.ids, self.shas, self.extras = list(ids), list(shas), list(extras)
        self._arrays = None

    def __getstate__(self) -> dict:
        """Pickle without the open arrays: each Ray worker reopens the zarr artifacts."""
        return {**self.__dict__, "_arrays": None}  # zarr handles are reopened by each worker

    def _open(self):
        """Open the arrays once per process: (image, reference mask or None, reference parts or None)."""
        if self._arrays is None:
            image = open_artifact(self.images, "images")["image"]
            mask = parts = None
            if self.reference is not None:
                ref = open_artifact(self.reference, "reference")
                mask = ref["mask"]
                parts = ref["parts"] if "parts" in ref else None
            self._arrays = image, mask, parts
        return self._arrays

    def __call__(self, row: int, view: str) -> TeacherInput:
        """Load row ``row`` in ``view``.

        Parameters
        ----------
        row : int
            A row of the artifacts.
        view : str
            One of :data:`pipeline.teachers.base.VIEWS`.

        Returns
        -------
        TeacherInput
            The image (and, when given, its reference) in ``view``, with its id, sha256 and extras.
        """
        image, mask, parts = self._open()
        reference = None
        if mask is not None:
            reference = {"mask": in_view(np.asarray(mask[row], dtype=bool), view)}
            if parts is not None:
                reference["parts"] = in_view(np.asarray(parts[row]), view)
        return TeacherInput(image_id=self.ids[row], image_sha256=self.shas[row],
                            image=in_view(np.asarray(image[row]), view), view=view, reference=reference,
                            extras=dict(self.extras[row]))
