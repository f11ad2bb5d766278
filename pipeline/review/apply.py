"""Apply a ``corrections`` artifact to a run (stage ``corrections``; params ``review``).

The stage (:func:`corrected_masks`, :func:`write_corrected`) checks the corrections against this run's
manifest and brings them to the working resolution: the ``corrected`` artifact (Zarr: ``mask`` bool
[M,R,R] and ``row`` int [M], the manifest rows; attrs ``image_ids`` and ``mode``).  Refused, one line
(exit 2): an image the manifest does not hold (a corrections artifact from another run), a size that
is not the manifest's for that image, an image outside the training split (a validation or test
image's mask is already a reference mask, or is evaluation), and ``validate`` on a benchmark source.

The train stage then reads it in the mode ``review.mode`` (:func:`pipeline.training.inputs.apply_to_training`,
:func:`~pipeline.training.inputs.apply_to_validation`, called by its ``load_inputs``; they live there so
that the training stages' code deps -- and the default dvc.yaml -- do not move):

``validate``  the corrected images leave the training set and become validation images with the
              corrected masks -- checkpoint selection (the train stage), tau (the calibrate stage,
              :func:`pipeline.evaluation.inference.validation_corrections`) and the report, which says how many --
              so the student stays annotation-free: a person's masks select and calibrate, never enter
              the loss.  The test split is untouched (corrections of test images are refused).  Meant for a folder of one's own
              (``data.source: folder``), whose validation split is drawn from the same pool; on a
              benchmark source the validation split is spacecraft-disjoint from training, and moving
              training spacecraft into it would select checkpoints on spacecraft the student trains on
              -- refused.
``replace``   the corrected masks replace those images' voted masks as the region target; their gate
              is g = 1 (the gate measures the teacher's reliability, and the mask is no longer the
              teacher's), their pseudo-area a and, for the geometry methods, their SDF and skeleton are
              recomputed from the corrected mask exactly as the geometry stage computes them
              (:func:`pipeline.augment.recompute_geometry`).  Those students are NOT annotation-free:
              ``review.human_targets: true`` must allow it, and the checkpoint records it
              (:func:`pipeline.methods.run_annotation_free`, :data:`pipeline.methods.HUMAN_TARGETS_LABEL`).
              A corrected image a method's data filter drops stays dropped (counted in the stats).
"""

from __future__ import annotations

import numpy as np

from pipeline.artifacts.store import write_zarr
from pipeline.datasets.loading import resize_nearest
from pipeline.runtime.errors import InputError, Option
from pipeline.review.corrections import correction_masks
from pipeline.training.inputs import MODE_KEY, MODES

STAGE = "corrections"
#: the data sources whose validation split is drawn from the same pool as training (validate is meant for them)
OWN_FOLDER_SOURCES = ("folder",)
CORRECTIONS = Option("--corrections", "corrections")


def corrected_masks(corrections, manifest, resolution: int, mode: str, source: str
                    ) -> tuple[list[str], np.ndarray, np.ndarray]:
    """(image ids, manifest rows int64 [M], masks bool [M,R,R]) of an opened ``corrections`` artifact
    checked against an opened ``manifest`` (module docstring) and resized to ``resolution`` by nearest
    neighbour, as prepare sizes the reference masks; in the artifact's order (the export's rank)."""
    if mode not in MODES:
        raise InputError(f"params: {MODE_KEY}={mode!r}: expected one of {', '.join(MODES)}")
    if mode == "validate" and source not in OWN_FOLDER_SOURCES:
        raise InputError(f"params: {MODE_KEY}=validate on data.source={source!r}: its validation split is "
                         f"spacecraft-disjoint from training, so corrected training images would put training "
                         f"spacecraft into checkpoint selection; use it on a folder of your own, or "
                         f"{MODE_KEY}=replace (not annotation-free)")
    df = manifest.df
    index = {iid: i for i, iid in enumerate(df["image_id"].astype(str))}
    where = corrections.path
    ids, rows, masks = [], [], []
    for iid, mask in correction_masks(corrections).items():
        row = index.get(iid)
        if row is None:
            raise InputError(f"{where}: unknown image {iid!r}: not in this run's manifest {manifest.path} "
                             f"(corrections of another run or folder?)")
        r = df.iloc[row]
        h, w = int(r["height"]), int(r["width"])
        if mask.shape != (h, w):
            raise InputError(f"{where}: image {iid!r}: corrected mask size {mask.shape[1]}x{mask.shape[0]} differs "
                             f"from the manifest's {w}x{h} (corrections of another run or folder?)")
        if r["split"] != "train":
            raise InputError(f"{where}: image {iid!r} is a {r['split']!r} image; only training images are "
                             f"corrected (validation and test images are scored against their reference masks)")
        ids.append(iid)
        rows.append(row)
        masks.append(resize_nearest(mask, resolution))
    if not ids:
        raise InputError("{}: holds no corrected mask", CORRECTIONS(where))
    return ids, np.asarray(rows, np.int64), np.stack(masks).astype(bool)


def write_corrected(out, ids: list[str], rows: np.ndarray, masks: np.ndarray, mode: str, meta):
    """Write the ``corrected`` artifact (module docstring) to ``out``; returns its path."""
    return write_zarr(out, {"mask": masks, "row": rows}, meta, attrs={"image_ids": list(ids), "mode": mode})

