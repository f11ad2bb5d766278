"""Pseudo-mask export formats: the registry of ``label``'s formats, and pure functions on arrays.

:class:`LabelFormat` and :data:`LABEL_FORMATS` (extended with :func:`register_format`) are the formats that
``label`` plans, writes and summarises.  The functions build COCO compressed RLE and instance records (one
spacecraft instance per image), YOLO segmentation lines and the YOLO dataset's text files, chosen to load in
pycocotools and Ultralytics (docs/decisions.md, "label's export formats").
"""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
from pycocotools import mask as mask_utils

from pipeline.catalog import OUTPUT_FILES, OutputFile
from pipeline.runtime.errors import InputError
from pipeline.teacher_table import FORMAT_GROUP, plugin

__all__ = ["LabelFormat", "LABEL_FORMATS", "register_format", "unregister_format", "find_format",
           "SPACECRAFT_CATEGORY", "rle_encode", "mask_bbox", "coco_annotation", "coco_document", "yolo_polygons",
           "yolo_lines", "yolo_split", "yolo_image_list", "yolo_data_yaml", "yolo_readme"]


@dataclasses.dataclass(frozen=True)
class LabelFormat:
    """One output format of ``label``: the files it plans, its per-image write and its finishing step.

    Parameters
    ----------
    name : str
        The word of ``--format`` and of ``pipeline.label(formats=...)``.
    files : callable
        ``files(ids, paths) -> list[str]``: the files it writes for the images ``ids`` (``paths``: each
        input's path relative to the input folder), relative POSIX paths under the output folder.
    write_image : callable
        ``write_image(job, row, mask) -> object``: image ``row``'s files of its voted mask, bool [H,W] at the
        image's own size (``job``: the :class:`pipeline.labeling.reading.LabelJob`); what it returns is
        handed to ``finish``.
    finish : callable
        ``finish(job, per_image, table)``: its other files, after the gates: ``per_image`` lists what
        ``write_image`` returned, ``table`` is label's table (one row per image, the gate in column ``g``).
    image_folders : tuple of str
        The folders (``"masks/"``) of its per-image files: a rerun removes those of images gone from the
        input folder only with ``--overwrite``.
    outputs : tuple of OutputFile
        Catalogue rows it adds to label's folder (``pipeline.catalog.OUTPUT_FILES["label"]``).
    mask_file : callable or None
        ``mask_file(id)``: the image's mask as an image file under the output folder
        (``LabelResult.masks``).
    summary : callable or None
        ``summary(out, n) -> str``: its part of the command's summary line.
    default : bool
        Written when no format is named.
    """

    name: str
    files: Callable[[Sequence[str], Sequence[str]], list[str]]
    write_image: Callable[[Any, int, np.ndarray], Any]
    finish: Callable[[Any, list, Any], None] = lambda job, per_image, table: None
    image_folders: tuple[str, ...] = ()
    outputs: tuple[OutputFile, ...] = ()
    mask_file: Callable[[str], str] | None = None
    summary: Callable[[Path, int], str] | None = None
    default: bool = True


#: name -> format, in the canonical order of the formats; extend with :func:`register_format`
LABEL_FORMATS: dict[str, LabelFormat] = {}


def register_format(fmt: LabelFormat) -> LabelFormat:
    """Add ``fmt`` to :data:`LABEL_FORMATS` and its ``outputs`` to the catalogue.

    Parameters
    ----------
    fmt : LabelFormat
        The format; its name and its catalogue keys must be new.

    Returns
    -------
    LabelFormat
        ``fmt``.

    Raises
    ------
    ValueError
        When its name or one of its catalogue keys is taken.
    """
    taken = [f.key for f in fmt.outputs if f.key in OUTPUT_FILES["label"]]
    if fmt.name in LABEL_FORMATS or taken:
        raise ValueError(f"label format {fmt.name!r}: name or catalogue key {taken} registered already")
    OUTPUT_FILES["label"].update({f.key: f for f in fmt.outputs})
    LABEL_FORMATS[fmt.name] = fmt
    return fmt


def unregister_format(name: str) -> None:
    """Remove format ``name`` and its catalogue rows (the inverse of :func:`register_format`).

    Parameters
    ----------
    name : str
        The format's name; an unknown name removes nothing.
    """
    fmt = LABEL_FORMATS.pop(name, None)
    for f in fmt.outputs if fmt is not None else ():
        OUTPUT_FILES["label"].pop(f.key, None)


def find_format(name: str) -> LabelFormat | None:
    """Return format ``name``, a plug-in's registered now (entry-point group ``geodistill.label_formats``).

    Parameters
    ----------
    name : str
        The format's name.

    Returns
    -------
    LabelFormat or None
        The format; None when neither the registry nor an installed package has it.

    Raises
    ------
    InputError
        From :func:`pipeline.teacher_table.plugin`, or the plug-in's name or catalogue keys are not its own.
    """
    if name not in LABEL_FORMATS and (found := plugin(FORMAT_GROUP, name, LABEL_FORMATS, LabelFormat)) is not None:
        fmt, where = found[0], f"plug-in {name!r} of {found[1]} ({FORMAT_GROUP})"
        if fmt.name != name:
            raise InputError(f"{where}: its LabelFormat is named {fmt.name!r}")
        try:
            register_format(fmt)
        except ValueError as e:  # a catalogue key taken
            raise InputError(f"{where}: {e}") from None
    return LABEL_FORMATS.get(name)


SPACECRAFT_CATEGORY = {"id": 1, "name": "spacecraft", "supercategory": "object"}
YOLO_CLASS = 0  # the one class of the YOLO labels (data.yaml names it "spacecraft")
YOLO_DECIMALS = 6


def _as_mask(mask: np.ndarray) -> np.ndarray:
    """Return ``mask`` as a bool [H,W] array; InputError naming its shape when it is not 2-D."""
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise InputError(f"mask: expected [H,W], got shape {mask.shape}")
    return mask.astype(bool, copy=False)


def rle_encode(mask: np.ndarray) -> dict:
    """Encode a mask as compressed COCO RLE (pycocotools' encoder).

    Parameters
    ----------
    mask : array_like
        A mask [H,W] (non-zero is foreground).

    Returns
    -------
    dict
        ``{"size": [h, w], "counts": str}``.

    Raises
    ------
    InputError
        The mask is not 2-D.
    """
    mask = _as_mask(mask)
    rle = mask_utils.encode(np.asfortranarray(mask.astype(np.uint8)))
    return {"size": [int(mask.shape[0]), int(mask.shape[1])], "counts": rle["counts"].decode("ascii")}


def mask_bbox(mask: np.ndarray) -> list[float]:
    """Return the tight box of the foreground in pixels.

    Parameters
    ----------
    mask : array_like
        A mask [H,W].

    Returns
    -------
    list of float
        ``[x, y, width, height]``; ``[0, 0, 0, 0]`` when the mask is empty.

    Raises
    ------
    InputError
        The mask is not 2-D.
    """
    mask = _as_mask(mask)
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return [0.0, 0.0, 0.0, 0.0]
    return [float(cols[0]), float(rows[0]), float(cols[-1] - cols[0] + 1), float(rows[-1] - rows[0] + 1)]


def coco_annotation(mask: np.ndarray, annotation_id: int, image_id: int, segment=rle_encode, iscrowd: int = 0,
                    **extra) -> dict | None:
    """Build one COCO instance record of an image's voted mask.

    Parameters
    ----------
    mask : array_like
        The mask [H,W] at the image's own size.
    annotation_id : int
        The record's id.
    image_id : int
        The COCO image id.
    segment : callable, optional
        mask -> segmentation (default :func:`rle_encode`).
    iscrowd : int, optional
        COCO's ``iscrowd`` (default 0).
    **extra
        Further fields of the record.

    Returns
    -------
    dict or None
        The record (category spacecraft, ``area`` in pixels, ``bbox``); None for an empty mask.

    Raises
    ------
    InputError
        The mask is not 2-D.
    """
    mask = _as_mask(mask)
    area = int(np.count_nonzero(mask))
    if area == 0:
        return None
    return {"id": int(annotation_id), "image_id": int(image_id), "category_id": SPACECRAFT_CATEGORY["id"],
            "segmentation": segment(mask), "area": area, "bbox": mask_bbox(mask), "iscrowd": iscrowd, **extra}


def coco_document(images: list[dict], annotations: list[dict], **info) -> dict:
    """Build a COCO instances file of ``images``, ``annotations`` and the one spacecraft category.

    Parameters
    ----------
    images : list of dict
        COCO image records.
    annotations : list of dict
        COCO instance records.
    **info
        Fields of the ``info`` record besides ``version``.

    Returns
    -------
    dict
        The document.
    """
    return {"info": {"version": "1.0", **info}, "licenses": [], "images": images, "annotations": annotations,
            "categories": [dict(SPACECRAFT_CATEGORY)]}


def yolo_polygons(mask: np.ndarray) -> list[np.ndarray]:
    """Return the outer contours of the connected foreground regions, normalised.

    Parameters
    ----------
    mask : array_like
        A mask [H,W].

    Returns
    -------
    list of numpy.ndarray
        float64 [P,2] of (x / width, y / height) per region, P >= 3; empty for an empty mask.

    Raises
    ------
    InputError
        The mask is not 2-D.
    """
    import cv2

    mask = _as_mask(mask)
    h, w = mask.shape
    if not mask.any():
        return []
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    return [c.reshape(-1, 2).astype(np.float64) / np.array([w, h], np.float64) for c in contours if len(c) >= 3]


def yolo_lines(mask: np.ndarray, class_id: int = YOLO_CLASS) -> list[str]:
    """Return the YOLO label file's lines for one image: ``class x1 y1 x2 y2 ...`` per region.

    Parameters
    ----------
    mask : array_like
        A mask [H,W].
    class_id : int, optional
        The class (default :data:`YOLO_CLASS`, 0).

    Returns
    -------
    list of str
        One line per region, coordinates with :data:`YOLO_DECIMALS` decimals; empty for an empty mask.
    """
    return [f"{int(class_id)} " + " ".join(f"{v:.{YOLO_DECIMALS}f}" for v in poly.ravel())
            for poly in yolo_polygons(mask)]


#: the share of the images ``yolo/val.txt`` holds out (at least one of two or more; none of one)
YOLO_VAL_SHARE = 0.2


def yolo_split(ids: Sequence[str], seed: int, share: float = YOLO_VAL_SHARE) -> tuple[list[int], list[int]]:
    """Split images into YOLO train and val rows, stable under adding or removing images.

    The first ``max(1, round(share * n))`` images ranked by ``sha256("<seed>:<id>")`` are held out (at most
    n - 1, none when n < 2); an image keeps its side when others are added or removed, unless it sits at the cut.

    Parameters
    ----------
    ids : sequence of str
        The image ids.
    seed : int
        ``data.seed``.
    share : float, optional
        The share held out (default :data:`YOLO_VAL_SHARE`, 0.2).

    Returns
    -------
    tuple of list of int
        (train rows, val rows), each in input order.
    """
    n = len(ids)
    n_val = 0 if n < 2 else min(max(1, round(share * n)), n - 1)
    ranked = sorted(range(n), key=lambda i: hashlib.sha256(f"{int(seed)}:{ids[i]}".encode()).hexdigest())
    val = sorted(ranked[:n_val])
    chosen = set(val)
    return [i for i in range(n) if i not in chosen], val


def yolo_image_list(image_paths: Sequence[str]) -> str:
    """Write an image-list file: ``./images/<path>`` lines, relative to the list's own folder.

    Parameters
    ----------
    image_paths : sequence of str
        Posix paths relative to the input folder.

    Returns
    -------
    str
        The file's text.
    """
    return "".join(f"./images/{p}\n" for p in image_paths)


def yolo_data_yaml(n_train: int, n_val: int, seed: int, share: float = YOLO_VAL_SHARE) -> str:
    """Write ``data.yaml``: the image lists relative to the file (no ``path:`` key), no ``val:`` without a split.

    Parameters
    ----------
    n_train : int
        Training images.
    n_val : int
        Validation images (0: no split).
    seed : int
        The split's seed (stated in a comment).
    share : float, optional
        The share held out (stated in a comment).

    Returns
    -------
    str
        The file's text.
    """
    head = ("# Ultralytics dataset of geodistill label pseudo-masks (README.txt beside this file).\n"
            "# No `path:` key: the paths below are relative to this file's folder.\n")
    split = (f"# val: {n_val} of {n_train + n_val} images held out ({share:.0%}, ranked by sha256 of seed {seed} "
             f"and the image id), never in train\ntrain: train.txt\nval: val.txt\n") if n_val else (
        f"# no val: {n_train} image(s), too few to hold one out (README.txt); add a `val:` list of your own\n"
        "train: train.txt\n")
    return head + split + f"names:\n  {YOLO_CLASS}: {SPACECRAFT_CATEGORY['name']}\n"


def yolo_readme(n_train: int, n_val: int, seed: int, copies: bool, share: float = YOLO_VAL_SHARE) -> str:
    """Write ``yolo/README.txt``: the layout, how the images are linked, and the split.

    Parameters
    ----------
    n_train : int
        Training images.
    n_val : int
        Validation images (0: no split).
    seed : int
        The split's seed.
    copies : bool
        Whether yolo/images holds copies (else relative links).
    share : float, optional
        The share held out.

    Returns
    -------
    str
        The file's text.
    """
    images = ("copies of the input images (--copy-images)" if copies else
              "relative symbolic links to the input images: move the label folder and the input folder "
              "together (their common parent), or label again with --copy-images to get copies that go "
              "anywhere")
    split = (f"val.txt holds out {n_val} of the {n_train + n_val} images ({share:.0%}, at least one): the "
             f"images are ranked by sha256 of '<seed>:<image id>' (seed {seed}, params data.seed) and the "
             "first go to val.txt, the rest to train.txt; the two lists never share an image.  These are "
             "pseudo-masks, not reference masks: validation scores measure agreement with the teacher."
             if n_val else
             f"No validation split: {n_train} image(s), too few to hold one out and still train.  "
             "data.yaml has no val: key; Ultralytics needs one, so add a list of your own images.")
    return ("YOLO segmentation dataset written by geodistill label (Ultralytics layout).\n\n"
            "  data.yaml           train/val lists and the class name (paths relative to this folder)\n"
            "  train.txt, val.txt  image lists, one ./images/<path> per line\n"
            "  images/<path>       " + images + "\n"
            "  labels/<path>.txt   one line per object: class x1 y1 x2 y2 ... (normalised polygon)\n\n"
            + split + "\n")
