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
"""

from __future__ import annotations

import numpy as np
from pycocotools import mask as mask_utils

from pipeline.errors import InputError

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
