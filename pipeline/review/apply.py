"""Stage ``corrections``: a person's corrected masks, checked, at the working resolution.

A ``corrections`` artifact is checked against this run's manifest (training images of the right size) and
written as the ``corrected`` artifact at the working resolution, which the train stage reads.
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
    """Check a ``corrections`` artifact against the run's ``manifest`` and resize its masks to ``resolution``.

    The masks are resized nearest-neighbour, as prepare sizes the reference masks.

    Parameters
    ----------
    corrections : artifact
        The opened ``corrections`` artifact (``geodistill review import --out``; ``review.corrections``).
    manifest : artifact
        This run's opened manifest: ``image_id``, ``split``, ``width`` and ``height`` per image.
    resolution : int
        The working resolution (``data.resolution``).
    mode : str
        ``review.mode``: ``validate`` or ``replace``.
    source : str
        ``data.source``; ``validate`` is allowed only for a folder of one's own (:data:`OWN_FOLDER_SOURCES`).

    Returns
    -------
    tuple of (list of str, numpy.ndarray, numpy.ndarray)
        The corrected image ids, their manifest rows (int64 [M]) and their masks (bool [M,R,R]), in the
        artifact's order.

    Raises
    ------
    pipeline.runtime.errors.InputError
        For an unknown ``mode``; ``validate`` on a source whose validation split is spacecraft-disjoint from
        training; a corrected image not in the manifest, of another size or not a training image; or an
        artifact holding no mask.
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
    """Write the ``corrected`` artifact the train stage reads.

    Parameters
    ----------
    out : str or Path
        The artifact's path.
    ids : list of str
        The corrected image ids (attrs ``image_ids``).
    rows : numpy.ndarray
        Their manifest rows, int64 [M] (array ``row``).
    masks : numpy.ndarray
        Their masks at the working resolution, bool [M,R,R] (array ``mask``).
    mode : str
        ``review.mode`` (attrs ``mode``).
    meta : pipeline.artifacts.lineage.Meta
        The artifact's metadata.

    Returns
    -------
    Path
        The artifact's path (:func:`pipeline.artifacts.store.write_zarr`).
    """
    return write_zarr(out, {"mask": masks, "row": rows}, meta, attrs={"image_ids": list(ids), "mode": mode})

