"""The supervised ceiling: the ONE place in the code where reference (manual) masks enter a loss.

The ``supervised_ceiling`` method (:data:`pipeline.methods.SUPERVISED_CEILING`) is the Plain
Student's recipe (Stage I, ``epochs_stage1``, ``lr_stage1``, L_raw, best validation IoU) trained on
the training split's reference masks instead of the teacher's voted pseudo-masks.  It is NOT
annotation-free: it measures how far this student and recipe can go with perfect labels, so that a
reader can tell whether the pseudo-labels or the student bound the quality.  It runs only with
``protocol.supervised_ceiling: true`` and is never part of the annotation-free comparisons.

Every other method gets its targets from :func:`pipeline.training.loop.training_data`, which refuses
reference masks; :func:`ceiling_training_data` refuses every method but the ceiling
(:func:`require_supervised_ceiling`).  Plumbing on opened artifacts; opens no file.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from pipeline.runtime.errors import InputError
from pipeline.methods import SUPERVISED_CEILING, Method
from pipeline.training.streaming import LazyRows, row_means
from pipeline.training.loop import TrainData, _check_order, _rows, _train_rows


def require_supervised_ceiling(method: Method) -> None:
    """The guard of the boundary: ValueError unless ``method`` is the supervised ceiling (the only
    method allowed to train on reference masks)."""
    if method.name != SUPERVISED_CEILING or method.annotation_free:
        raise ValueError(f"--method {method.name}: reference masks enter a loss only for {SUPERVISED_CEILING!r} "
                         f"(annotation-free methods train on pseudo-targets: pipeline.training.loop.training_data)")


def ceiling_training_data(method: Method, inputs: Mapping[str, Any], reference) -> Any:
    """The supervised ceiling's training arrays: images and REFERENCE masks of the ``split == "train"``
    rows that have a mask (manifest order), as a :class:`pipeline.training.loop.TrainData` whose images and
    masks are read per batch (:class:`pipeline.training.streaming.LazyRows`).

    ``inputs``: opened ``manifest`` and ``images``; ``reference``: the opened reference.zarr.
    ``area`` is each mask's foreground fraction and ``gate`` is 1 (L_raw uses neither).  Raises
    ValueError for any other method, InputError when no training row has a reference mask.
    """
    require_supervised_ceiling(method)
    ids, train_idx = _train_rows(inputs["manifest"])
    for art in (inputs["images"], reference):
        _check_order(art, ids, art.meta.schema)
    n_rows = int(len(train_idx))
    train_idx = train_idx[_rows(reference, "has_mask", train_idx).astype(bool)]
    if len(train_idx) == 0:
        raise InputError(f"{reference.path}: no training image has a reference mask; "
                         f"the supervised ceiling needs them")
    mask = LazyRows(reference["mask"], train_idx, bool)  # read per batch, as every method's targets
    data = TrainData(image_ids=[ids[i] for i in train_idx], images=LazyRows(inputs["images"]["image"], train_idx),
                     mask=mask, area=row_means(mask), gate=np.ones(len(mask), dtype=np.float32),
                     stats={"n_train_rows": n_rows, "targets": "reference masks (NOT annotation-free)"})
    data.stats["n_train"] = len(data)
    return data
