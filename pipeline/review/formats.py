"""The review formats, pure functions on arrays.

Label Studio brush RLE (thi.ng ``rle-pack`` bits, as label-studio-converter writes them) and polygons; COCO 1.0
for CVAT (uncompressed RLE with ``iscrowd: 1``, as CVAT exports masks).  A polygon is each region's outer
contour, so its round trip is not pixel-exact.
"""

from __future__ import annotations

import numpy as np
from pycocotools import mask as mask_utils

from pipeline.labeling.formats import SPACECRAFT_CATEGORY, coco_annotation, yolo_polygons

__all__ = ["LS_FROM_NAME", "LS_TO_NAME", "LABEL", "FormatError", "ls_brush_rgba", "ls_rle_encode_values",
           "ls_rle_decode", "ls_label_config", "ls_results", "polygon_mask", "coco_review_annotation",
           "coco_segmentation_mask"]

LS_WORD_SIZE = 8
LS_RLE_SIZES = (3, 4, 8, 16)
LS_OPAQUE = 255   # alpha 1 would be drawn invisible: why pre-annotations often "do not render"
LS_FROM_NAME, LS_TO_NAME = "mask", "image"   # the control and object tag names of :func:`ls_label_config`
LABEL = SPACECRAFT_CATEGORY["name"]


class FormatError(ValueError):
    """A corrupt or inconsistent annotation (the importer turns it into a one-line InputError)."""


def _run_bits(length: int, value: int) -> str:
    """Write one run segment as label-studio-converter's ``encode_rle`` does.

    The narrowest length field that holds it, else 16-bit fields in pieces of 2**16 values.
    """
    word = format(value, f"0{LS_WORD_SIZE}b")
    for index, width in enumerate(LS_RLE_SIZES[:3]):
        if length <= 2 ** width:
            return "1" + format(index, "02b") + format(length - 1, f"0{width}b") + word
    out = []
    while length > 2 ** 16:
        out.append("111" + format(2 ** 16 - 1, "016b") + word)
        length -= 2 ** 16
    out.append("111" + format(length - 1, "016b") + word)
    return "".join(out)


def ls_rle_encode(mask: np.ndarray) -> list[int]:
    """Encode a bool [H,W] mask as Label Studio brush RLE (byte values), opaque in all four channels."""
    return ls_rle_encode_values(ls_brush_rgba(np.asarray(mask, bool).astype(np.uint8) * LS_OPAQUE))


def ls_brush_rgba(alpha: np.ndarray) -> np.ndarray:
    """Give the RGBA values Label Studio's editor encodes for a brush layer of ``alpha``.

    Parameters
    ----------
    alpha : numpy.ndarray
        The layer's alpha, [H,W] (cast to uint8); it is copied into R, G and B.

    Returns
    -------
    numpy.ndarray
        uint8 [4 H W]: R, G, B, A per pixel, row-major.

    Raises
    ------
    FormatError
        When ``alpha`` is not two-dimensional.
    """
    alpha = np.asarray(alpha, np.uint8)
    if alpha.ndim != 2:
        raise FormatError(f"alpha: expected [H,W], got shape {alpha.shape}")
    return np.repeat(alpha.ravel(), 4)


def ls_rle_encode_values(values: np.ndarray) -> list[int]:
    """Pack uint8 values as rle-pack bytes, runs only: byte for byte label-studio-converter's ``brush.encode_rle``.

    Parameters
    ----------
    values : numpy.ndarray
        The values (flattened; RGBA of :func:`ls_brush_rgba` for a brush).

    Returns
    -------
    list of int
        The RLE's byte values: the header (count, word size, the four run-length field sizes), then one segment
        per run, zero-padded to whole bytes.
    """
    flat = np.asarray(values, np.uint8).ravel()
    n = flat.size
    bits = [format(n, "032b"), format(LS_WORD_SIZE - 1, "05b"), "".join(format(s - 1, "04b") for s in LS_RLE_SIZES)]
    if n:
        change = np.flatnonzero(flat[1:] != flat[:-1]) + 1
        starts = np.concatenate([[0], change])
        lengths = np.diff(np.concatenate([starts, [n]]))
        bits += [_run_bits(int(length), int(flat[s])) for s, length in zip(starts, lengths)]
    text = "".join(bits)
    text += "0" * (8 - len(text) % 8)  # as label-studio-converter: a whole extra zero byte when aligned
    packed = np.packbits(np.frombuffer(text.encode("ascii"), np.uint8) - ord("0"))
    return packed.tolist()


def ls_rle_decode(rle, height: int, width: int) -> np.ndarray:
    """Decode a Label Studio brush RLE, literal stretches included, into a mask (alpha > 0).

    Parameters
    ----------
    rle : list of int
        The RLE's byte values (a brush result's ``value.rle``).
    height, width : int
        The image's size; the RLE must hold 4 x height x width values.

    Returns
    -------
    numpy.ndarray
        bool [H,W].

    Raises
    ------
    FormatError
        When ``rle`` is not a list of byte values, ends early, or holds another number of values.
    ValueError
        Only as :class:`FormatError`, its subclass (a malformed list's own ValueError is turned into one).
    """
    try:
        data = np.asarray(rle, np.int64)
        if data.ndim != 1 or data.size < 5 or (data < 0).any() or (data > 255).any():
            raise ValueError
    except (TypeError, ValueError):
        raise FormatError("brush rle is not a list of byte values") from None
    bits = (np.unpackbits(data.astype(np.uint8)) + ord("0")).tobytes().decode("ascii")
    pos = 0

    def read(k: int) -> int:
        nonlocal pos
        if pos + k > len(bits):
            raise FormatError("brush rle ends early")
        v = int(bits[pos:pos + k], 2) if k else 0
        pos += k
        return v

    num = read(32)
    if num != 4 * height * width:
        raise FormatError(f"brush rle holds {num} values, expected {4 * height * width} (= {width}x{height}x4)")
    word = read(5) + 1
    sizes = [read(4) + 1 for _ in range(4)]
    out = np.zeros(num, np.uint32)
    i = 0
    while i < num:
        run = read(1)
        j = min(i + 1 + read(sizes[read(2)]), num)
        if run:
            out[i:j] = read(word)
        else:
            out[i:j] = [read(word) for _ in range(j - i)]
        i = j
    return out.reshape(height, width, 4)[:, :, 3] > 0


def ls_label_config(shape: str = "brush") -> str:
    """Write the Label Studio labelling interface (XML): an image and one label.

    Parameters
    ----------
    shape : str
        ``brush`` (BrushLabels) or ``polygon`` (PolygonLabels).

    Returns
    -------
    str
        The XML, its tags named :data:`LS_TO_NAME` and :data:`LS_FROM_NAME`, its label :data:`LABEL`.
    """
    tag = {"brush": "BrushLabels", "polygon": "PolygonLabels"}[shape]
    return (f'<View>\n  <Image name="{LS_TO_NAME}" value="$image" zoom="true"/>\n'
            f'  <{tag} name="{LS_FROM_NAME}" toName="{LS_TO_NAME}">\n'
            f'    <Label value="{LABEL}" background="#ff3b30"/>\n  </{tag}>\n</View>\n')


def ls_results(mask: np.ndarray, shape: str = "brush", result_id: str = "r0") -> list[dict]:
    """Write the ``result`` list of one Label Studio prediction of ``mask``.

    Parameters
    ----------
    mask : numpy.ndarray
        bool [H,W] at the image's own size.
    shape : str
        ``brush``: one brush result; ``polygon``: one polygon per region, its outer contour (holes filled), in
        per cent of the image size.
    result_id : str
        The result's id (a polygon's: ``<result_id>p<k>``).

    Returns
    -------
    list of dict
        The results; empty for an empty mask.
    """
    mask = np.asarray(mask, bool)
    h, w = mask.shape
    common = {"from_name": LS_FROM_NAME, "to_name": LS_TO_NAME, "original_width": int(w), "original_height": int(h),
              "image_rotation": 0, "origin": "prediction"}
    if not mask.any():
        return []
    if shape == "brush":
        return [{"id": result_id, "type": "brushlabels", **common,
                 "value": {"format": "rle", "rle": ls_rle_encode(mask), "brushlabels": [LABEL]}}]
    return [{"id": f"{result_id}p{k}", "type": "polygonlabels", **common,
             "value": {"points": np.round(poly * 100.0, 4).tolist(), "closed": True, "polygonlabels": [LABEL]}}
            for k, poly in enumerate(yolo_polygons(mask))]


def polygon_mask(polygons, height: int, width: int, scale=(1.0, 1.0)) -> np.ndarray:
    """Fill polygons into a mask: their union.

    Parameters
    ----------
    polygons : iterable of array_like
        Each a sequence of (x, y) points (flat or paired); one with under 3 points is skipped.
    height, width : int
        The mask's size.
    scale : tuple of float
        (x, y) factors applied to the coordinates: (W/100, H/100) for Label Studio's per cent.

    Returns
    -------
    numpy.ndarray
        bool [H,W].
    """
    import cv2

    out = np.zeros((height, width), np.uint8)
    for poly in polygons:
        pts = np.asarray(poly, np.float64).reshape(-1, 2) * np.asarray(scale, np.float64)
        if len(pts) >= 3:
            cv2.fillPoly(out, [np.round(pts).astype(np.int32)], 1)
    return out.astype(bool)


def coco_uncompressed_rle(mask: np.ndarray) -> dict:
    """Encode a mask as COCO's uncompressed RLE, ``{"size": [h, w], "counts": [...]}``, column-major runs.

    The runs start with background (a leading 0 when the first pixel is foreground).
    """
    mask = np.asarray(mask, bool)
    flat = mask.ravel(order="F")
    change = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    bounds = np.concatenate([[0], change, [flat.size]])
    counts = np.diff(bounds).tolist()
    if flat.size and flat[0]:
        counts = [0] + counts
    return {"size": [int(mask.shape[0]), int(mask.shape[1])], "counts": [int(c) for c in counts]}


def coco_review_annotation(mask: np.ndarray, annotation_id: int, image_id: int, shape: str = "rle",
                           **extra) -> dict | None:
    """Build one COCO annotation of a mask for CVAT.

    Parameters
    ----------
    mask : numpy.ndarray
        bool [H,W] at the image's own size.
    annotation_id : int
        The annotation's id.
    image_id : int
        The COCO image id.
    shape : str
        ``rle``: uncompressed RLE with ``iscrowd: 1`` (as CVAT exports masks); else one polygon per region
        (``iscrowd: 0``).
    **extra
        Further fields of the annotation.

    Returns
    -------
    dict or None
        The annotation (:func:`pipeline.labeling.formats.coco_annotation`); None for an empty mask.
    """
    if shape == "rle":
        return coco_annotation(mask, annotation_id, image_id, coco_uncompressed_rle, 1, **extra)
    return coco_annotation(mask, annotation_id, image_id, lambda m: [
        np.round(p * m.shape[::-1], 2).ravel().tolist() for p in yolo_polygons(m)], 0, **extra)


def coco_segmentation_mask(segmentation, height: int, width: int) -> np.ndarray:
    """Decode a COCO segmentation (polygons, uncompressed or compressed RLE) into a mask.

    Parameters
    ----------
    segmentation : list or dict
        Polygons (flat coordinate lists; one with under 3 points is skipped), or an RLE ``{"size", "counts"}``.
    height, width : int
        The image's size; an RLE must have it.

    Returns
    -------
    numpy.ndarray
        bool [H,W]; all False for polygons that are all too short.

    Raises
    ------
    FormatError
        When the segmentation is neither polygons nor RLE, its RLE size is not the image's, or it cannot be
        decoded.
    """
    try:
        if isinstance(segmentation, list):
            polys = [p for p in segmentation if len(p) >= 6]
            if not polys:
                return np.zeros((height, width), bool)
            rle = mask_utils.merge(mask_utils.frPyObjects(polys, height, width))
        elif isinstance(segmentation, dict) and isinstance(counts := segmentation.get("counts"), (list, str, bytes)):
            if list(segmentation.get("size", [])) != [height, width]:
                raise FormatError(f"RLE size {segmentation.get('size')} is not the image's [{height}, {width}]")
            rle = (mask_utils.frPyObjects(segmentation, height, width) if isinstance(counts, list) else
                   {"size": [height, width], "counts": counts.encode("ascii") if isinstance(counts, str) else counts})
        else:
            raise FormatError("segmentation is neither polygons nor RLE")
        return mask_utils.decode(rle).astype(bool)
    except FormatError:
        raise
    except (TypeError, ValueError, KeyError) as e:
        raise FormatError(f"segmentation cannot be decoded ({e})") from None
