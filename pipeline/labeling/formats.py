"""Pseudo-mask export formats: COCO run-length encoding, COCO instance records, YOLO segmentation lines.

Pure functions on arrays (no I/O).  Conventions, chosen to load in the standard readers:

COCO (``pycocotools``)
    ``rle_encode(mask)`` is COCO's *compressed* RLE (``{"size": [h, w], "counts": str}``) as
    ``pycocotools.mask.encode`` writes it (on the Fortran-order uint8 mask; the counts bytes decoded
    to a JSON string), so ``COCO.annToMask`` and ``maskUtils.area`` read it back.
    One annotation per image: the whole voted pseudo-mask is one spacecraft instance (``iscrowd`` 0;
    a mask split into several parts, e.g. panels cut off by a thin strut, stays one object).  ``area``
    is the pixel count of the mask, ``bbox`` ``[x, y, width, height]`` its tight box in pixels.
YOLO segmentation (Ultralytics' ``labels/*.txt``)
    One line per object, ``class x1 y1 x2 y2 ...`` with coordinates normalised by the image width and
    height.  An object is a connected foreground region: its outer contour (OpenCV
    ``findContours(RETR_EXTERNAL, CHAIN_APPROX_SIMPLE)``: boundary pixel indices, corners only on
    straight runs) divided by (width, height) -- Ultralytics' own mask-to-polygon convention, so its
    ``polygon2mask`` (``fillPoly`` of the denormalised points) gives the region back.  Regions whose
    contour has fewer than 3 points (1-2 px specks) are left out, as Ultralytics' converter does;
    holes cannot be expressed in the format and are filled.  An empty mask gives no line (an empty
    label file: a background image).
YOLO dataset files (``data.yaml``, ``train.txt``, ``val.txt``, ``README.txt``)
    Text only: the image lists hold ``./images/<path>`` lines (relative to the list file), ``data.yaml``
    has no ``path:`` key (Ultralytics then takes its folder as the root), so the folder can be moved; the
    validation split is a seeded, hash-ranked share of the images (:func:`yolo_split`).
"""

from __future__ import annotations

import hashlib
from typing import Sequence

import numpy as np
from pycocotools import mask as mask_utils

from pipeline.runtime.errors import InputError

SPACECRAFT_CATEGORY = {"id": 1, "name": "spacecraft", "supercategory": "object"}
YOLO_CLASS = 0  # the one class of the YOLO labels (data.yaml names it "spacecraft")
YOLO_DECIMALS = 6


def _as_mask(mask: np.ndarray) -> np.ndarray:
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise InputError(f"mask: expected [H,W], got shape {mask.shape}")
    return mask.astype(bool, copy=False)


# --------------------------------------------------------------------------------------------------
# COCO
# --------------------------------------------------------------------------------------------------
def rle_encode(mask: np.ndarray) -> dict:
    """Compressed COCO RLE ``{"size": [h, w], "counts": str}`` of a bool [H,W] mask, by pycocotools'
    own encoder (``pycocotools.mask.encode`` of the Fortran-order uint8 mask)."""
    mask = _as_mask(mask)
    rle = mask_utils.encode(np.asfortranarray(mask.astype(np.uint8)))
    return {"size": [int(mask.shape[0]), int(mask.shape[1])], "counts": rle["counts"].decode("ascii")}


def mask_bbox(mask: np.ndarray) -> list[float]:
    """Tight box ``[x, y, width, height]`` (pixels) of the foreground; ``[0, 0, 0, 0]`` when empty."""
    mask = _as_mask(mask)
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return [0.0, 0.0, 0.0, 0.0]
    return [float(cols[0]), float(rows[0]), float(cols[-1] - cols[0] + 1), float(rows[-1] - rows[0] + 1)]


def coco_annotation(mask: np.ndarray, annotation_id: int, image_id: int, **extra) -> dict | None:
    """One COCO instance record for the voted mask of an image (None for an empty mask: no object).

    ``extra`` fields (e.g. the reliability gate) are stored alongside; COCO readers ignore them."""
    mask = _as_mask(mask)
    area = int(np.count_nonzero(mask))
    if area == 0:
        return None
    return {"id": int(annotation_id), "image_id": int(image_id), "category_id": SPACECRAFT_CATEGORY["id"],
            "segmentation": rle_encode(mask), "area": area, "bbox": mask_bbox(mask), "iscrowd": 0, **extra}


def coco_document(images: list[dict], annotations: list[dict], **info) -> dict:
    """A COCO instances file: ``images`` (id, file_name, width, height), ``annotations``
    (:func:`coco_annotation`), the one spacecraft category, ``info`` fields (description, backend...)."""
    return {"info": {"version": "1.0", **info}, "licenses": [], "images": images, "annotations": annotations,
            "categories": [dict(SPACECRAFT_CATEGORY)]}


# --------------------------------------------------------------------------------------------------
# YOLO segmentation
# --------------------------------------------------------------------------------------------------
def yolo_polygons(mask: np.ndarray) -> list[np.ndarray]:
    """Outer contours of the connected foreground regions as float64 [P,2] arrays of normalised
    (x / width, y / height) points, P >= 3 (module docstring)."""
    import cv2

    mask = _as_mask(mask)
    h, w = mask.shape
    if not mask.any():
        return []
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    out = []
    for c in contours:
        pts = c.reshape(-1, 2).astype(np.float64)
        if len(pts) >= 3:
            out.append(pts / np.array([w, h], np.float64))
    return out


def yolo_lines(mask: np.ndarray, class_id: int = YOLO_CLASS) -> list[str]:
    """The label file's lines for one image: ``class x1 y1 x2 y2 ...`` per region (module docstring)."""
    lines = []
    for poly in yolo_polygons(mask):
        coords = " ".join(f"{v:.{YOLO_DECIMALS}f}" for v in poly.ravel())
        lines.append(f"{int(class_id)} {coords}")
    return lines


# --------------------------------------------------------------------------------------------------
# YOLO dataset files (data.yaml, image lists, README.txt): text only, written by pipeline.labeling.run
# --------------------------------------------------------------------------------------------------
#: the share of the images ``yolo/val.txt`` holds out for validation (at least one image, when there are
#: two or more; none of a single image)
YOLO_VAL_SHARE = 0.2


def yolo_split(ids: Sequence[str], seed: int, share: float = YOLO_VAL_SHARE) -> tuple[list[int], list[int]]:
    """(train rows, val rows) of the images ``ids``, disjoint and deterministic: the images are ranked by
    ``sha256("<seed>:<id>")`` and the first ``max(1, round(share * n))`` are held out for validation
    (none when ``n < 2``: nothing would be left to train on).  Ranking by the id's hash, not by position,
    keeps an image's side when other images are added or removed, unless it sits at the cut."""
    n = len(ids)
    n_val = 0 if n < 2 else min(max(1, round(share * n)), n - 1)
    ranked = sorted(range(n), key=lambda i: hashlib.sha256(f"{int(seed)}:{ids[i]}".encode()).hexdigest())
    val = sorted(ranked[:n_val])
    chosen = set(val)
    return [i for i in range(n) if i not in chosen], val


def yolo_image_list(image_paths: Sequence[str]) -> str:
    """An Ultralytics image-list file (``train.txt`` / ``val.txt``): one ``./images/<path>`` per line --
    Ultralytics reads a leading ``./`` relative to the list file's own folder, so the list survives the
    folder being moved."""
    return "".join(f"./images/{p}\n" for p in image_paths)


def yolo_data_yaml(n_train: int, n_val: int, seed: int, share: float = YOLO_VAL_SHARE) -> str:
    """``data.yaml``: train/val image lists relative to the file (no ``path:`` key, so Ultralytics takes the
    file's own folder as the dataset root); without a validation split no ``val:`` key, and the reason
    (:func:`yolo_split`) in a comment and in README.txt."""
    head = ("# Ultralytics dataset of geodistill label pseudo-masks (README.txt beside this file).\n"
            "# No `path:` key: the paths below are relative to this file's folder.\n")
    split = (f"# val: {n_val} of {n_train + n_val} images held out ({share:.0%}, ranked by sha256 of seed {seed} "
             f"and the image id), never in train\ntrain: train.txt\nval: val.txt\n") if n_val else (
        f"# no val: {n_train} image(s), too few to hold one out (README.txt); add a `val:` list of your own\n"
        "train: train.txt\n")
    return head + split + f"names:\n  {YOLO_CLASS}: {SPACECRAFT_CATEGORY['name']}\n"


def yolo_readme(n_train: int, n_val: int, seed: int, copies: bool, share: float = YOLO_VAL_SHARE) -> str:
    """``yolo/README.txt``: the layout, how the images got there and the validation split or why none."""
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
