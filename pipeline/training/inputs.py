"""What a training run reads, opened from an artifacts directory: the train stage's inputs, callable
without the CLI (the train stage and the recipe study both call :func:`load_inputs`).

This module stays torch-free: :mod:`pipeline.training.loop` (torch) is imported when a run loads its arrays.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from pipeline import catalog
from pipeline.artifacts.lineage import require_same_run
from pipeline.artifacts.store import open_artifact
from pipeline.augment import recompute_geometry
from pipeline.runtime.errors import InputError
from pipeline.geometry import area_ratio
from pipeline.evaluation.inference import REVIEW_MODE_KEY, corrected_validation, require_mode
from pipeline.training.streaming import RowSource, select_rows


def load_inputs(artifacts: str | Path, spec, cfg: Mapping[str, Any], review: Mapping[str, Any] | None = None
                ) -> tuple[Any, Any, list]:
    """Open what the method's training reads and the validation reference; build the arrays.

    ``review``: the params' ``review`` section.  With ``review.corrections`` set, the ``corrected``
    artifact (stage corrections) is opened too and applied in ``review.mode``
    (:func:`apply_to_training` / :func:`apply_to_validation`; the modes: :mod:`pipeline.review.apply`):
    ``validate`` moves the corrected training images to validation; ``replace`` puts the corrected masks
    in the loss (NOT annotation-free: :func:`pipeline.methods.run_annotation_free`).  Unset (the
    default), nothing else is opened and the run is what it was.

    Returns (TrainData, ValData or None, the artifacts opened -- the checkpoint's lineage).
    reference.zarr is opened only when the manifest has validation rows, and goes only to
    :func:`pipeline.training.loop.validation_data` -- except for the supervised ceiling (NOT
    annotation-free), whose targets :func:`pipeline.training.supervised.ceiling_training_data` builds from it.
    """
    from pipeline.training import loop as training  # torch: imported when a run trains, not with the stage module

    def opened_artifact(name: str):
        return open_artifact(catalog.path(name, artifacts), name)

    inputs = {name: opened_artifact(name) for name in training.training_inputs(spec, cfg)}
    # outputs of one stage must come from one run (a kill between geometry.zarr and gates.parquet)
    require_same_run(*inputs.values())
    opened = list(inputs.values())
    reference = None
    if spec.annotation_free:
        data = training.training_data(spec, cfg, inputs)
    else:  # the supervised ceiling: the one method whose loss sees reference masks (NOT annotation-free)
        from pipeline.training.supervised import ceiling_training_data  # imports pipeline.training.loop (torch)

        reference = opened_artifact("reference")
        opened.append(reference)
        require_same_run(*opened)
        data = ceiling_training_data(spec, inputs, reference)
    corrected = None
    if review and review.get("corrections") and spec.annotation_free:
        corrected = opened_artifact("corrected")
        opened.append(corrected)
        data = apply_to_training(data, corrected, review["mode"])
    val = None
    if len(training.validation_rows(inputs["manifest"])):
        if reference is None:
            reference = opened_artifact("reference")
            opened.append(reference)
            require_same_run(*opened)
        val = training.validation_data(inputs["manifest"], inputs["images"], reference)
    if corrected is not None and review["mode"] == "validate":
        val = apply_to_validation(val, corrected, inputs["images"], training.ValData)
    return data, val, opened


# --------------------------------------------------------------------------------------------------
# Human corrections (params review; the stage corrections writes the corrected artifact)
# --------------------------------------------------------------------------------------------------
#: how the corrected artifact enters a run (:mod:`pipeline.review.apply` says what each means)
MODES = ("validate", "replace")
MODE_KEY = REVIEW_MODE_KEY


class PatchedRows(RowSource):
    """The rows of ``base`` with some replaced: ``patch`` maps a position in ``base`` to its row (a
    corrected target), read like any row source (nothing else is read until indexed)."""

    def __init__(self, base, patch: Mapping[int, np.ndarray]):
        self.base = base
        self.patch = dict(patch)
        self.dtype = np.dtype(base.dtype)

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self.base.shape)

    def select(self, sel) -> "PatchedRows":
        pos = np.arange(len(self))[sel]
        return PatchedRows(select_rows(self.base, pos), {k: self.patch[p] for k, p in enumerate(pos)
                                                         if p in self.patch})

    def read(self, key) -> np.ndarray:
        pos = np.arange(len(self))[key]
        out = np.array(self.base[pos], dtype=self.dtype)
        for k, p in enumerate(pos):
            if int(p) in self.patch:
                out[k] = self.patch[int(p)]
        return out


def _positions(data, ids: list[str]) -> dict[int, str]:
    want = set(ids)
    return {k: iid for k, iid in enumerate(data.image_ids) if iid in want}


def apply_to_training(data, corrected, mode: str):
    """``data`` (a :class:`pipeline.training.loop.TrainData`) with the opened ``corrected`` artifact applied
    in ``mode``: ``validate`` drops the corrected images, ``replace`` patches their targets (module
    docstring).  Records ``human_corrections`` (how many applied), ``corrections_mode`` and, in replace
    mode, ``annotation_free: False`` and the targets in ``data.stats``."""
    require_mode(corrected, mode)
    ids = list(corrected.attrs["image_ids"])
    masks = np.asarray(corrected["mask"], dtype=bool)
    by_id = dict(zip(ids, masks))
    pos = _positions(data, ids)
    stats = {**data.stats, "corrections_mode": mode, "human_corrections": len(pos),
             "human_corrections_not_applied": len(ids) - len(pos)}
    if mode == "validate":
        keep = np.array([k not in pos for k in range(len(data))])
        if not keep.any():
            raise InputError(f"{corrected.path}: every training image is corrected; {MODE_KEY}=validate would "
                             f"leave nothing to train on")
        sel = np.flatnonzero(keep)
        out = type(data)(**{**_fields(data), "image_ids": [data.image_ids[k] for k in sel],
                            "images": select_rows(data.images, sel), "mask": select_rows(data.mask, sel),
                            "area": data.area[sel], "gate": data.gate[sel],
                            "sdf": None if data.sdf is None else select_rows(data.sdf, sel),
                            "skeleton": None if data.skeleton is None else select_rows(data.skeleton, sel),
                            "stats": stats})
        out.stats["n_train"] = len(out)
        return out
    return replace_targets(data, by_id, stats)


def replace_targets(data, masks: Mapping[str, np.ndarray], stats: Mapping[str, Any] | None = None):
    """``data`` (TrainData) whose images in ``masks`` ({image id: bool [R,R]}) train on those masks
    (``replace``, :mod:`pipeline.review.apply`): region target, g = 1, a and the geometry targets
    recomputed; ``stats`` (default ``data.stats``) gains ``annotation_free: False``.  Images of
    ``masks`` that ``data`` lacks are left out."""
    pos = _positions(data, list(masks))
    stats = dict(data.stats if stats is None else stats)
    stats.setdefault("human_corrections", len(pos))
    new = {k: np.asarray(masks[iid], bool) for k, iid in pos.items()}
    area, gate = np.array(data.area, copy=True), np.array(data.gate, copy=True)
    fields = {**_fields(data), "mask": PatchedRows(_as_rows(data.mask), new), "area": area, "gate": gate}
    geo = {k: recompute_geometry(m, data.geometry) for k, m in new.items()} if data.sdf is not None else {}
    for k, m in new.items():
        area[k], gate[k] = area_ratio(m), 1.0
    if geo:
        fields["sdf"] = PatchedRows(_as_rows(data.sdf), {k: g[0] for k, g in geo.items()})
        fields["skeleton"] = PatchedRows(_as_rows(data.skeleton), {k: g[1] for k, g in geo.items()})
    stats.update(annotation_free=False,
                 targets=f"voted masks, {len(pos)} replaced by human corrections (NOT annotation-free)")
    return type(data)(**{**fields, "stats": stats})


def apply_to_validation(val, corrected, images, val_cls):
    """Validation data with the corrected images appended (``validate`` mode): ``val`` (a
    :class:`pipeline.training.loop.ValData`, or None when the run has no validation masks) plus the corrected
    images (read from the opened ``images`` artifact at the ``corrected`` artifact's rows) and their
    corrected masks; ``val_cls`` builds it (ValData)."""
    ids, imgs, masks = corrected_validation(corrected, images)
    if val is None:
        return val_cls(image_ids=ids, images=imgs, masks=masks)
    return val_cls(image_ids=list(val.image_ids) + ids, images=np.concatenate([val.images, imgs]),
                   masks=np.concatenate([val.masks, masks]))


def _fields(data) -> dict[str, Any]:
    return {f.name: getattr(data, f.name) for f in dataclasses.fields(data)}


def _as_rows(x):
    """A row source over ``x`` (an in-memory array is wrapped so :class:`PatchedRows` reads it alike)."""
    return x if isinstance(x, RowSource) else _ArrayRows(np.asarray(x))


class _ArrayRows(RowSource):
    def __init__(self, arr: np.ndarray):
        self.arr = arr
        self.dtype = arr.dtype

    @property
    def shape(self) -> tuple[int, ...]:
        return self.arr.shape

    def select(self, sel) -> "_ArrayRows":
        return _ArrayRows(self.arr[sel])

    def read(self, key) -> np.ndarray:
        return self.arr[key]
