"""Stage ``corrections``: a ``corrections`` artifact checked against this run's manifest (training images of
the right size) -> the ``corrected`` artifact at the working resolution, which the train stage reads.
"""

from __future__ import annotations

import numpy as np

from pipeline.artifacts.store import write_zarr
from pipeline.datasets.loading import resize_nearest
from pipeline.runtime.errors import InputError, Option
from pipeline.review.corrections import correction_masks
from pipeline.training.inputs import MODE_KEY, MODES

__all__ = ["MODE_KEY", "CORRECTIONS", "corrected_masks", "write_corrected"]

STAGE = "corrections"
#: the data sources whose validation split comes from the training pool (``validate`` is meant for them)
OWN_FOLDER_SOURCES = ("folder",)
CORRECTIONS = Option("--corrections", "corrections")


def corrected_masks(corrections, manifest, resolution: int, mode: str, source: str
                    ) -> tuple[list[str], np.ndarray, np.ndarray]:
    """(image ids, manifest rows int64 [M], masks bool [M,R,R]) of a ``corrections`` artifact checked against
    the ``manifest`` and resized to ``resolution`` (nearest, as prepare sizes the reference masks).
    """
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
    """Write the ``corrected`` artifact (``mask`` [M,R,R], ``row`` [M]; attrs image_ids, mode); its path."""
    return write_zarr(out, {"mask": masks, "row": rows}, meta, attrs={"image_ids": list(ids), "mode": mode})

