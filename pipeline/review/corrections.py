"""``geodistill review import SOURCE --review DIR``: corrected masks -> the ``corrections`` artifact.

The corrected masks come as a Label Studio JSON export, a CVAT COCO 1.0 export or a folder of
``<image id>.png``; the artifact holds one row per corrected image.  These are MANUAL masks: like reference
masks they may select, calibrate and evaluate, never enter an annotation-free method's loss.
"""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path

import numpy as np

from pipeline.artifacts.lineage import make_meta
from pipeline.artifacts.store import open_artifact, write_parquet
from pipeline.datasets.loading import SUPPORTED_SUFFIXES, read_mask
from pipeline.datasets.scan import scan_inputs
from pipeline.runtime.errors import ArtifactError, InputError, Option, literal
from pipeline.labeling.formats import rle_encode
from pipeline.metrics import image_iou
from pipeline.artifacts.ownership import read_record, refuse_unowned
from pipeline.review.export import COMMAND as EXPORT_COMMAND
from pipeline.review.export import EXPORT_FIELD, OUTPUTS as EXPORT_OUTPUTS
from pipeline.teachers.base import files_digest
from pipeline.review.formats import (LS_FROM_NAME, FormatError, coco_segmentation_mask, ls_rle_decode,
                                     polygon_mask)

__all__ = ["FORMATS", "read_review", "import_corrections", "coco_decode", "correction_masks"]

log = logging.getLogger(__name__)

STAGE = "review import"
SOURCE = Option("SOURCE", "source")
REVIEW = Option("--review", "review")
FROM = Option("--from", "fmt")
FORMATS = ("auto", "labelstudio", "cvat", "png")


def read_review(review_dir: str | Path) -> dict:
    """Read the record of a complete ``review export`` folder.

    Parameters
    ----------
    review_dir : str or Path
        The folder ``geodistill review export`` (or the DAG stage ``review_export``) wrote.

    Returns
    -------
    dict
        The export's record: ``export_id``, ``images`` (image id, file, size, voted mask, rank per image), ...

    Raises
    ------
    pipeline.runtime.errors.InputError
        Naming ``--review`` when the folder holds no complete record of an export.
    """
    d = Path(review_dir)
    rec = read_record(d / EXPORT_OUTPUTS["record"], EXPORT_COMMAND)
    if rec is None or not rec.get("complete"):
        raise InputError(f"{{}}: not a finished export of geodistill {literal(EXPORT_COMMAND)} (no complete "
                         f"{literal(EXPORT_OUTPUTS['record'])} of it there)", REVIEW(d))
    return rec


def detect_format(source: Path) -> str:
    """Tell the format of ``source``: ``png`` for a folder, ``labelstudio`` for a JSON list, ``cvat`` for COCO."""
    if source.is_dir():
        return "png"
    doc = _read_json(source)
    if isinstance(doc, list):
        return "labelstudio"
    if isinstance(doc, dict) and "images" in doc and "annotations" in doc:
        return "cvat"
    raise InputError(f"{source}: neither a Label Studio JSON export (a list of tasks) nor a COCO file (images, "
                     f"annotations)")


def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError("{}: file not found", SOURCE(path)) from None
    except (ValueError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: not JSON ({e})") from None


def _check(mask: np.ndarray, image: dict, where: str) -> np.ndarray:
    h, w = image["height"], image["width"]
    if mask.shape != (h, w):
        raise InputError(f"{where}: mask size {mask.shape[1]}x{mask.shape[0]} differs from image "
                         f"{image['image_id']!r} size {w}x{h}")
    if not mask.any():
        raise InputError(f"{where}: the corrected mask of image {image['image_id']!r} is empty")
    return mask


def _labelstudio(path: Path, review: dict) -> dict[str, np.ndarray]:
    tasks = _read_json(path)
    if not isinstance(tasks, list):
        raise InputError(f"{path}: not a Label Studio JSON export (expected a list of tasks)")
    by_id = {im["image_id"]: im for im in review["images"]}
    out, untouched = {}, 0
    for k, task in enumerate(tasks):
        task = task if isinstance(task, dict) else {}
        data, where = task.get("data", {}), f"{path}: task {task.get('id', k)}"
        if data.get(EXPORT_FIELD) != review["export_id"]:
            raise InputError(f"{where}: from another export ({EXPORT_FIELD}={data.get(EXPORT_FIELD)!r}, this "
                             f"export is {review['export_id']!r})")
        image = by_id.get(data.get("image_id"))
        if image is None:
            raise InputError(f"{where}: unknown image {data.get('image_id')!r} (not in this export)")
        done = [a for a in task.get("annotations", []) if not a.get("was_cancelled") and a.get("result")]
        if not done:
            untouched += 1
            continue
        h, w = image["height"], image["width"]
        mask = np.zeros((h, w), bool)
        for res in done[-1]["result"]:
            if res.get("from_name") not in (None, LS_FROM_NAME):
                continue
            size = (res.get("original_height", h), res.get("original_width", w))
            if tuple(size) != (h, w):
                raise InputError(f"{where}: result size {size[1]}x{size[0]} differs from image "
                                 f"{image['image_id']!r} size {w}x{h}")
            value = res.get("value", {})
            try:
                if res.get("type") == "brushlabels" or "rle" in value:
                    mask |= ls_rle_decode(value.get("rle"), h, w)
                elif "points" in value:
                    mask |= polygon_mask([value["points"]], h, w, scale=(w / 100.0, h / 100.0))
            except FormatError as e:
                raise InputError(f"{where}: {e}") from None
        out[image["image_id"]] = _check(mask, image, where)
    if untouched:
        log.info("review import: %d of %d tasks have no annotation (not corrected): left out", untouched, len(tasks))
    return out


def _cvat(path: Path, review: dict) -> dict[str, np.ndarray]:
    doc = _read_json(path)
    if not isinstance(doc, dict):
        raise InputError(f"{path}: not a COCO 1.0 file (expected an object with images and annotations)")
    by_file = {im["file"]: im for im in review["images"]}
    drawn: dict = {}
    for ann in doc.get("annotations", []):
        drawn.setdefault(ann.get("image_id"), []).append(ann)
    listed = {im.get("id") for im in doc.get("images", [])}
    stray = next((a for i, a in drawn.items() if i not in listed), None)
    if stray is not None:
        raise InputError(f"{path}: annotation {stray[0].get('id')} names image id {stray[0].get('image_id')}, "
                         f"not in the file")
    out, undrawn, foreign = {}, 0, 0
    for im in doc.get("images", []):
        anns = drawn.get(im.get("id"), [])
        image = by_file.get(im.get("file_name"))
        if not anns:   # CVAT lists every image of its task; nobody drew on this one: not a correction
            undrawn += image is not None
            foreign += image is None
            continue
        if image is None:
            raise InputError(f"{path}: unknown image {im.get('file_name')!r} (not in this export)")
        if (im.get("height"), im.get("width")) != (image["height"], image["width"]):
            raise InputError(f"{path}: image {im.get('file_name')!r} size {im.get('width')}x{im.get('height')} "
                             f"differs from {image['width']}x{image['height']}")
        mask = np.zeros((image["height"], image["width"]), bool)
        for ann in anns:
            try:
                mask |= coco_segmentation_mask(ann.get("segmentation"), image["height"], image["width"])
            except FormatError as e:
                raise InputError(f"{path}: annotation {ann.get('id')} of {image['file']!r}: {e}") from None
        out[image["image_id"]] = _check(mask, image, f"{path}")
    if undrawn or foreign:
        log.info("review import: %d images of the export have no annotation (not corrected) and %d not in the "
                 "export have none: left out", undrawn, foreign)
    return out


def _png(folder: Path, review: dict) -> dict[str, np.ndarray]:
    by_id = {im["image_id"]: im for im in review["images"]}
    out = {}
    for f in scan_inputs(folder).files:
        iid = f.relative_to(folder).with_suffix("").as_posix()
        image = by_id.get(iid)
        if image is None:
            raise InputError(f"{f}: unknown image {iid!r} (not in this export; masks are named <image id>"
                             f"{SUPPORTED_SUFFIXES[0]})")
        if iid in out:
            raise InputError(f"{f}: a second mask for image {iid!r}")
        out[iid] = _check(read_mask(f), image, str(f))   # a bad file: its own one-line InputError
    return out


READERS = {"labelstudio": _labelstudio, "cvat": _cvat, "png": _png}


def source_digest(source: Path) -> str:
    """Hash the source's bytes with sha256 (a folder: its files' relative paths and bytes, sorted)."""
    if source.is_dir():
        return files_digest(source, sorted(p for p in source.rglob("*") if p.is_file()))
    return hashlib.sha256(source.read_bytes()).hexdigest()


def import_corrections(source: str | Path, review_dir: str | Path, out: str | Path, *, fmt: str = "auto",
                       code_version: str = "", overwrite: bool = False):
    """Read the corrections in ``source``, check them against the export in ``review_dir``, write the artifact.

    The ``corrections`` artifact at ``out`` replaces only an earlier corrections artifact (anything else only with
    ``overwrite``).  Its rows follow the export's order (its rank); tasks or images nobody annotated are left out.

    Parameters
    ----------
    source : str or Path
        A Label Studio JSON export, a CVAT COCO 1.0 file, or a folder of ``<image id>.png`` masks.
    review_dir : str or Path
        The ``review export`` folder the corrections were made from.
    out : str or Path
        The ``corrections`` artifact (a parquet file).
    fmt : str
        One of :data:`FORMATS`; ``auto`` tells it from ``source``.
    code_version : str
        The code version recorded in the artifact's metadata.
    overwrite : bool
        Replace ``out`` even when it is not a corrections artifact.

    Returns
    -------
    artifact
        The written artifact, opened: per image ``image_id``, ``file``, ``width``, ``height``, ``rle`` (COCO
        counts), ``pixels``, ``source``, ``iou_to_voted`` (against the voted mask, eq:majority-vote) and ``rank``.

    Raises
    ------
    pipeline.runtime.errors.InputError
        For an unknown ``fmt``, a missing ``source``, a ``fmt`` that does not read that kind of ``source``, or
        a ``source`` holding no corrected mask; the readers raise one line naming the bad task, image or file.
    """
    import pandas as pd

    source, out = Path(source), Path(out)
    if fmt not in FORMATS:
        raise InputError(f"{{}}: expected one of {', '.join(FORMATS)}", FROM(fmt))
    if not source.exists():
        raise InputError("{}: not found", SOURCE(source))
    review = read_review(review_dir)
    fmt = detect_format(source) if fmt == "auto" else fmt
    if (fmt == "png") != source.is_dir():
        raise InputError(f"{{}}: {literal(fmt)} reads a {'folder' if fmt == 'png' else 'JSON file'}", SOURCE(source))
    try:   # a missing or foreign one is not ours
        owned = [open_artifact(out, "corrections").path]
    except ArtifactError:
        owned = []
    refuse_unowned([out], owned, command=STAGE, option="--out", where=out,
                   why="not a corrections artifact", overwrite=overwrite)
    masks = READERS[fmt](source, review)
    if not masks:
        raise InputError(f"{{}}: no corrected mask in it ({literal(fmt)})", SOURCE(source))
    rows = [{"image_id": im["image_id"], "file": im["file"], "width": im["width"], "height": im["height"],
             "rle": rle_encode(m)["counts"], "pixels": int(np.count_nonzero(m)), "source": fmt,
             "iou_to_voted": image_iou(m, coco_decode(im["voted_rle"])), "rank": im["rank"]}
            for im in review["images"] if (m := masks.get(im["image_id"])) is not None]   # the export's order: rank
    params = {"format": fmt, "export_id": review["export_id"], "source_sha256": source_digest(source)}
    meta = make_meta("corrections", STAGE, code_version, params, export_id=review["export_id"],
                     simulator=bool(review.get("simulator")))
    out.parent.mkdir(parents=True, exist_ok=True)
    write_parquet(out, pd.DataFrame(rows), meta)
    return open_artifact(out, "corrections")


def coco_decode(rle: dict) -> np.ndarray:
    """Decode a compressed COCO RLE into a mask.

    Parameters
    ----------
    rle : dict
        ``{"size": [H, W], "counts": str}``.

    Returns
    -------
    numpy.ndarray
        bool [H,W].
    """
    return coco_segmentation_mask(rle, *rle["size"])


def correction_masks(artifact) -> dict[str, np.ndarray]:
    """Decode every corrected mask of a ``corrections`` artifact.

    Parameters
    ----------
    artifact : artifact
        The opened ``corrections`` artifact (:func:`import_corrections`).

    Returns
    -------
    dict
        Image id -> its corrected mask, bool [H,W] at the image's own size, in the artifact's order.
    """
    return {r.image_id: coco_decode({"size": [int(r.height), int(r.width)], "counts": r.rle})
            for r in artifact.table.itertuples(index=False)}
