"""One image/mask loader for every source, with a content-addressed decode cache.

``read_rgb(path)``
    Any supported file (png, jpg/jpeg, tif/tiff, bmp) -> RGB uint8 [H, W, 3] at native size.
    Grey is replicated to three channels; RGBA drops alpha (spacecraft imagery has no meaningful
    transparency; compositing on black would equal dropping it for premultiplied black
    backgrounds); 16-bit is scaled to 8-bit by :func:`scale_16bit` under the stated bit depth
    (``bit_depth``); float images are taken as [0, 1] and clipped.  OpenCV decodes BGR, so channels are reversed.
    Raises :class:`InputError` naming the file for a missing, zero-byte, corrupt or unsupported file,
    a broken symbolic link or a directory.

The pixel limit (every reader below, ``max_pixels``; params ``data.max_pixels``, default
:data:`DEFAULT_MAX_PIXELS` = 2**26, an 8192 x 8192 image)
    Width and height are read from the file header (:func:`pipeline.datasets.image_header.header_size`)
    before anything is decoded or looked up in the cache; above ``max_pixels`` the file is a bad file
    (:class:`BadFileError` naming it, its size and the option), so a few-megabyte PNG whose header
    declares 30,000 x 30,000 pixels never reaches the decoder.  Bytes that carry no PNG, JPEG, TIFF or
    BMP header are "corrupt or undecodable" before decoding too.

Bit depth (params ``data.bit_depth``; every reader below takes ``bit_depth``, the one helper is
:func:`scale_16bit`)
    ``auto`` (the default) takes a 16-bit file as full range: rounding ``v / 257`` (the exact
    65535 -> 255 map).  A sensor of 10, 12 or 14 bits stored in 16-bit files fills only the low bits, and
    its frames come out nearly black that way: under ``auto`` a 16-bit frame whose brightest value is
    below 1/8 of the range (< 8192) gets one warning per file naming it and the option.  ``bit_depth`` =
    10/12/14/16 maps ``v * 255 / (2**bits - 1)`` (rounded; values above ``2**bits - 1`` clip to 255, with
    one warning per file).  8-bit and float files are not affected.

Aspect ratio (params ``data.letterbox``; ``letterbox=`` of the resizers below)
    False (the paper): every frame is squashed to the square working resolution.  True: the frame is
    first padded with black to a square (centred: :func:`letterbox_box`), then resized; the way back
    (:func:`probs_to_size`) samples only working pixels that hold some of the frame and crops the pad, so
    a prediction comes back at the frame's own size and the pad never reaches it.

``read_mask(path, threshold)``
    Any mask file -> bool [H, W].  THE rule (this module is the only place a mask file is binarised:
    the dataset adapters and the imported teacher all come here): foreground = max over channels
    > ``threshold``, and the default ``threshold=None`` means **foreground = value > 0** -- 0/1,
    0/255 and 0/65535 masks, float probability masks and multi-valued label masks (0 = background,
    1..K = classes or instances) alike.  A multi-valued mask (non-zero pixels with more than one
    value, e.g. labels 0..3 or an anti-aliased 0..255 edge) gets one warning naming the file, since
    "value > 0" may not be what its author meant; a protocol that knows better sets an explicit
    ``mask_threshold`` (SPEED+ 128, TANGO 127), which is used as given without a warning.

``parts_from_colors(rgb, table)`` (colour-coded part masks: SpaceSense-Bench, SPARK)
    Each pixel takes the label of the :class:`ColorTable` colour it matches within the table's
    tolerance (black = background); with ``blends`` a JPEG blend of two table colours takes the nearer
    one's.  A colour outside the table refuses the file (:class:`BadFileError`, so ``--skip-bad``
    leaves it out), never silently background.

``load_rgb / load_mask / load_labels`` (the pipeline's entry points)
    Read the file bytes once, hash them (sha256), and return the array resized to the working
    resolution -- area interpolation for images, nearest for masks and labels -- through a decode
    cache keyed by ``(sha256, kind, resolution)`` under ``.cache/decode/`` so no stage decodes the
    same file twice.  Cache entries are ``.npz`` files (array + native height/width + their own key +
    the mask warning, if any) written to a temp name then renamed (atomic; survive a kill); they are
    read with ``allow_pickle=False``, and an unreadable entry, or one whose stored key is not the key
    asked for (e.g. a file copied over another), is treated as a miss and rewritten.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import os
import uuid
from pathlib import Path

import cv2
import numpy as np

from pipeline.datasets.image_header import header_size
from pipeline.runtime.errors import BIT_DEPTH, MAX_PIXELS, InputError, Option, caller, literal
from pipeline.params import AUTO_BIT_DEPTH, BIT_DEPTHS, PAPER

log = logging.getLogger(__name__)

SUPPORTED_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
DEFAULT_CACHE_DIR = ".cache/decode"
MASK_RULE = "foreground = value > 0"
#: the pixel limit's default: the params schema's ``data.max_pixels``
DEFAULT_MAX_PIXELS = PAPER.data.max_pixels
UNDECODABLE = "corrupt or undecodable image"


class BadFileError(InputError):
    """A file that cannot be used (missing, zero-byte, corrupt, unsupported, too large, size mismatch).

    ``.path`` names it and ``.reason`` says why in words that name no option (what the skipped-file
    listings hold); ``fix`` is a template naming the ``options`` that would let the file in, spelled
    in the caller's terms (:class:`pipeline.runtime.errors.InputError`): ``{path}: {reason} ({fix})``."""

    def __init__(self, path: str | Path, reason: str, fix: str = "", *options: Option):
        self.path = str(path)
        self.reason = reason
        self.fix = fix
        text = f"{literal(path)}: {literal(reason)}" if options else f"{path}: {reason}"
        super().__init__(text + (f" ({fix})" if fix else ""), *options)

    def __reduce__(self):  # pickled across Ray workers: rebuilt from its own arguments
        return type(self), (self.path, self.reason, self.fix, *self.options)


# ---------------------------------------------------------------------------------------------------
# Decoding (no resizing, no cache)
# ---------------------------------------------------------------------------------------------------
def broken_link_reason(p: Path) -> str:
    """The one wording of a broken symbolic link (the folder scan and the decode pass say the same)."""
    try:
        return f"broken symbolic link (its target {os.readlink(p)} does not exist)"
    except OSError:
        return "broken symbolic link"


def read_bytes(path: str | Path) -> bytes:
    """File bytes; InputError naming the file when missing, unreadable, zero-byte or unsupported."""
    p = Path(path)
    if p.suffix.lower() not in SUPPORTED_SUFFIXES:
        raise BadFileError(p, f"unsupported image type {p.suffix or '(no suffix)'!r} "
                              f"(supported: {', '.join(SUPPORTED_SUFFIXES)})")
    if not p.is_file():
        if p.is_symlink():
            raise BadFileError(p, broken_link_reason(p))
        if p.is_dir():
            raise BadFileError(p, "is a directory, not an image file")
        raise BadFileError(p, "file not found")
    try:
        data = p.read_bytes()
    except OSError as e:
        raise BadFileError(p, f"cannot read ({e.strerror or e})") from None
    if not data:
        raise BadFileError(p, "zero-byte file")
    return data


def pixel_limit(max_pixels: int | None = None) -> int:
    """``max_pixels`` checked (a whole number >= 1; InputError naming the option in the caller's terms),
    or :data:`DEFAULT_MAX_PIXELS` when None."""
    if max_pixels is None:
        return DEFAULT_MAX_PIXELS
    if isinstance(max_pixels, bool) or not isinstance(max_pixels, (int, np.integer)) or max_pixels < 1:
        raise InputError("{}: must be a whole number of pixels >= 1 (width x height; default "
                         f"{DEFAULT_MAX_PIXELS:,})", MAX_PIXELS(max_pixels))
    return int(max_pixels)


def check_header(data: bytes, path: str | Path, max_pixels: int | None = None) -> tuple[int, int]:
    """``(width, height)`` from the file header (:func:`pipeline.datasets.image_header.header_size`),
    before any decoding; :class:`BadFileError` when there is no PNG/JPEG/TIFF/BMP header or the image
    is above ``max_pixels`` (None: :data:`DEFAULT_MAX_PIXELS`)."""
    limit = pixel_limit(max_pixels)
    size = header_size(data)
    if size is None:
        raise BadFileError(path, UNDECODABLE)  # no PNG/JPEG/TIFF/BMP header: the decoder's own wording
    w, h = size
    if w * h > limit:
        raise BadFileError(path, f"{w} x {h} = {w * h:,} pixels in its header, above the limit of {limit:,}",
                           "raise {} to read it", MAX_PIXELS)
    return size


def read_image_bytes(path: str | Path, max_pixels: int | None = None) -> bytes:
    """:func:`read_bytes`, then :func:`check_header`: the bytes of a file the decoder may take."""
    data = read_bytes(path)
    check_header(data, path, max_pixels)
    return data


def _decode(data: bytes, path: str | Path) -> np.ndarray:
    arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if arr is None or arr.size == 0:
        raise BadFileError(path, UNDECODABLE)
    return arr


#: under ``bit_depth="auto"``, a 16-bit frame whose brightest value is below this (1/8 of the range) is
#: warned about: it is most likely a 10-14-bit sensor's frame, which full range makes nearly black
LOW_RANGE_16BIT = 1 << 13
#: where a bit-depth note names the option: spelled for the caller when warned (:func:`warn_frame_once`:
#: ``--bit-depth 12`` on the command line, ``bit_depth=12`` in Python), so the decode cache keeps one text
BIT_DEPTH_HINT = "<bit depth option>"
#: the start of the note of a frame that uses under 1/8 of the 16-bit range (warned once per run)
LOW_RANGE_NOTE = "16-bit frame whose brightest value is"


def check_bit_depth(bit_depth) -> str | int:
    """``bit_depth`` checked against :data:`pipeline.params.BIT_DEPTHS` (params validate ``data.bit_depth``
    on load; this guards the Python API's ``bit_depth=``)."""
    if not isinstance(bit_depth, bool) and bit_depth in BIT_DEPTHS:
        return bit_depth
    raise InputError(f"{{}}: expected one of {', '.join(map(str, BIT_DEPTHS))} (bits of a "
                     "16-bit frame's sensor; auto = the file's full range)", BIT_DEPTH(bit_depth))


def scale_16bit(arr: np.ndarray, bit_depth="auto") -> tuple[np.ndarray, str | None]:
    """``(uint8 array, note)`` of a uint16 array under the stated ``bit_depth`` (module docstring):
    ``auto``/16 = ``round(v / 257)``; 10/12/14 = ``round(min(v, 2**bits - 1) * 255 / (2**bits - 1))``.
    ``note`` (None when there is nothing to say) is the warning's text: a frame under 1/8 of the range
    under ``auto``, or values above the stated depth."""
    bit_depth = check_bit_depth(bit_depth)
    peak = int(arr.max()) if arr.size else 0
    if bit_depth in (AUTO_BIT_DEPTH, 16):
        a8 = ((arr.astype(np.uint32) + 128) // 257).astype(np.uint8)
        note = None
        if bit_depth == AUTO_BIT_DEPTH and peak < LOW_RANGE_16BIT:
            note = (f"16-bit frame whose brightest value is {peak:,} of 65,535 (under 1/8 of the range): read as "
                    f"full range it comes out nearly black; if the sensor has fewer bits, say how many: "
                    f"{BIT_DEPTH_HINT} (10, 12 or 14)")
        return a8, note
    top = (1 << int(bit_depth)) - 1
    a = np.minimum(arr, top).astype(np.uint32)
    a8 = ((a * 510 + top) // (2 * top)).astype(np.uint8)      # round(v * 255 / top), exact integers
    note = (f"values up to {peak:,} above the stated {bit_depth}-bit maximum {top:,} (clipped to white); "
            f"check {BIT_DEPTH_HINT}") if peak > top else None
    return a8, note


def rgb8_and_note(arr: np.ndarray, path: str | Path = "<array>", bit_depth="auto") -> tuple[np.ndarray, str | None]:
    """:func:`to_rgb8` without its warning: ``(RGB uint8 [H, W, 3], note or None)`` (the decode cache
    keeps the note with the entry, so a cached frame is warned about too)."""
    note = None
    if arr.dtype == np.uint8:
        a8 = arr
    elif arr.dtype == np.uint16:
        a8, note = scale_16bit(arr, bit_depth)
    elif arr.dtype.kind == "f":
        a8 = (np.clip(np.nan_to_num(arr), 0, 1) * 255 + 0.5).astype(np.uint8)
    elif arr.dtype.kind in "iu":
        a8 = np.clip(arr, 0, 255).astype(np.uint8)
    else:
        raise BadFileError(path, f"unsupported pixel type {arr.dtype}")
    if a8.ndim == 2:
        return np.repeat(a8[..., None], 3, axis=2), note
    if a8.ndim != 3:
        raise BadFileError(path, f"unsupported image shape {arr.shape}")
    ch = a8.shape[2]
    if ch == 1:
        return np.repeat(a8, 3, axis=2), note
    if ch == 3:
        return np.ascontiguousarray(a8[..., ::-1]), note
    if ch == 4:
        return np.ascontiguousarray(a8[..., 2::-1]), note
    raise BadFileError(path, f"unsupported channel count {ch}")


def to_rgb8(arr: np.ndarray, path: str | Path = "<array>", bit_depth="auto") -> np.ndarray:
    """Decoded OpenCV array (grey, BGR, BGRA; 8/16-bit or float) -> RGB uint8 [H, W, 3]; a 16-bit array
    by :func:`scale_16bit` under ``bit_depth`` (its note warned once per ``path``)."""
    rgb, note = rgb8_and_note(arr, path, bit_depth)
    warn_frame_once(path, note)
    return rgb


def read_rgb(path: str | Path, *, max_pixels: int | None = None, bit_depth="auto") -> np.ndarray:
    """Read any supported image file as RGB uint8 [H, W, 3] at native size (see module docstring);
    refused before decoding above ``max_pixels`` (None: :data:`DEFAULT_MAX_PIXELS`); 16-bit files under
    ``bit_depth`` (``data.bit_depth``)."""
    return to_rgb8(_decode(read_image_bytes(path, max_pixels), path), path, bit_depth)


_warned: set[str] = set()
_warned_frames: set[tuple[str, str]] = set()


def warn_frame_once(path: str | Path, note: str | None) -> None:
    """The one warning per (file, note) about how a frame's pixel values were read -- the file by its
    absolute path, so a run reading it by two spellings warns once; a frame under 1/8 of the 16-bit range
    (no bit depth stated) once per run (:func:`reset_frame_warnings`).  The option is named in the
    caller's terms (:data:`BIT_DEPTH_HINT`)."""
    if not note:
        return
    key = ("", LOW_RANGE_NOTE) if note.startswith(LOW_RANGE_NOTE) else (os.path.abspath(path), note)
    if key in _warned_frames:
        return
    _warned_frames.add(key)
    hint = BIT_DEPTH(12) if note.startswith(LOW_RANGE_NOTE) else BIT_DEPTH
    log.warning("%s: %s", path, note.replace(BIT_DEPTH_HINT, hint.spell(caller())))


def reset_frame_warnings() -> None:
    """A new run (label, segment): its frames are warned about again (:func:`warn_frame_once`)."""
    _warned_frames.clear()


def multi_valued_note(a: np.ndarray) -> str | None:
    """None for a binary mask (one non-zero value at most), else a short description of its values."""
    nz = a[a != 0]
    if nz.size == 0 or not (nz != nz.flat[0]).any():
        return None
    values = np.unique(nz)
    shown = ", ".join(f"{v:g}" for v in values[:6].tolist()) + (", ..." if values.size > 6 else "")
    return f"multi-valued label mask (non-zero values {shown}; {values.size} distinct)"


def warn_mask_once(path: str | Path, note: str | None) -> None:
    """The one warning per file (per process) for a multi-valued mask read with the default rule."""
    if note and str(path) not in _warned:
        _warned.add(str(path))
        log.warning("%s: %s: %s (set an explicit mask_threshold in the protocol file for another rule)",
                    path, note, MASK_RULE)


def binarize_mask(arr: np.ndarray, threshold: float | None = None) -> tuple[np.ndarray, str | None]:
    """``(bool mask, note)``: foreground = max over channels > ``threshold`` (None: > 0, see module
    docstring); ``note`` describes a multi-valued mask under the default rule, else None."""
    a = arr.max(axis=2) if arr.ndim == 3 else arr
    if threshold is None:
        return a > 0, multi_valued_note(a)
    return a > threshold, None


def mask_from_array(arr: np.ndarray, threshold: float | None = None, path: str | Path | None = None) -> np.ndarray:
    """Foreground = max over channels > ``threshold``; ``None`` = value > 0 (warns once per ``path``
    for a multi-valued mask)."""
    mask, note = binarize_mask(arr, threshold)
    if path is not None:
        warn_mask_once(path, note)
    return mask


def read_mask(path: str | Path, threshold: float | None = None, *, max_pixels: int | None = None) -> np.ndarray:
    """Read a mask file as bool [H, W] at native size; InputError naming the file on bad input (and
    above ``max_pixels``, before decoding)."""
    return mask_from_array(_decode(read_image_bytes(path, max_pixels), path), threshold, path)


#: the colour of background in every colour-coded part mask (label 0 unless a table maps it)
BACKGROUND_RGB = (0, 0, 0)


@dataclasses.dataclass(frozen=True)
class ColorTable:
    """A colour-coded part mask's class table: ``colors`` ``{(r, g, b): label}`` (RGB), with black
    (:data:`BACKGROUND_RGB`) = background (label 0) unless listed.

    ``tolerance``: a pixel takes a colour's label when every channel is within ``tolerance`` of it
    (0: exact colours, for PNG masks; JPEG masks need more).  ``blends``: a pixel matching no colour
    that lies within ``tolerance`` (every channel) of the straight line between two table colours --
    what JPEG's chroma subsampling and ringing make of a boundary between two classes -- takes the
    label of the nearer of the two.  Any other pixel is a colour outside the class table: the file is
    refused (:func:`parts_from_colors`).  The adapters check that no two colours are within
    ``2 * tolerance`` of each other, so a pixel never matches two."""

    colors: dict
    tolerance: int = 0
    blends: bool = False

    def __bool__(self) -> bool:  # an empty table is no table: there are no part labels to read
        return bool(self.colors)

    def entries(self) -> dict[tuple[int, int, int], int]:
        return {BACKGROUND_RGB: 0, **{tuple(int(v) for v in k): int(lbl) for k, lbl in self.colors.items()}}

    def kind(self) -> str:
        """Decode-cache kind: the table, its tolerance and the rule (entries made under the former rule,
        which made unknown colours background, are never read)."""
        key = repr((sorted(self.entries().items()), int(self.tolerance), bool(self.blends), "refuse-unknown"))
        return f"parts{hashlib.sha256(key.encode()).hexdigest()[:10]}"


def as_color_table(colors: dict | ColorTable) -> ColorTable:
    return colors if isinstance(colors, ColorTable) else ColorTable(dict(colors))


def parts_from_colors(rgb: np.ndarray, colors: dict | ColorTable, path: str | Path = "<array>") -> np.ndarray:
    """Colour-coded part mask (RGB uint8) -> part labels uint8 by the :class:`ColorTable` (a plain
    dict: exact colours).  A pixel matching no colour (nor, with ``blends``, a blend of two) is a
    colour outside the class table: :class:`BadFileError` naming ``path`` and the most frequent such
    colour, never silently background."""
    table = as_color_table(colors)
    entries = table.entries()
    cols = np.array(list(entries), np.int32)                               # K, 3
    labels = np.array(list(entries.values()), np.uint8)
    key = (rgb[..., 0].astype(np.uint32) << 16) | (rgb[..., 1].astype(np.uint32) << 8) | rgb[..., 2]
    uniq, inverse, counts = np.unique(key.ravel(), return_inverse=True, return_counts=True)
    u = np.stack([(uniq >> 16) & 255, (uniq >> 8) & 255, uniq & 255], axis=1).astype(np.int32)   # U, 3
    dist = np.abs(u[:, None, :] - cols[None, :, :]).max(axis=2)            # U, K (every channel within)
    nearest = dist.argmin(axis=1)
    ulab = labels[nearest]
    unmatched = dist[np.arange(len(u)), nearest] > table.tolerance
    if table.blends and unmatched.any() and len(cols) > 1:
        i, j = np.triu_indices(len(cols), k=1)
        seg = (cols[j] - cols[i]).astype(np.float64)                      # P, 3
        rel = u[unmatched][:, None, :] - cols[i][None, :, :]               # M, P, 3
        a = np.clip((rel * seg[None]).sum(axis=2) / (seg * seg).sum(axis=1)[None], 0.0, 1.0)   # M, P
        off = np.abs(rel - a[..., None] * seg[None]).max(axis=2)           # M, P
        best = off.argmin(axis=1)
        ok = off[np.arange(len(best)), best] <= table.tolerance
        ab = a[np.arange(len(best)), best]
        blended = np.where(ab < 0.5, labels[i[best]], labels[j[best]])
        idx = np.flatnonzero(unmatched)
        ulab[idx[ok]] = blended[ok]
        unmatched[idx[ok]] = False
    if unmatched.any():
        worst = np.flatnonzero(unmatched)[counts[unmatched].argmax()]
        r, g, b = (int(v) for v in u[worst])
        within = f" within {table.tolerance}" if table.tolerance else ""
        raise BadFileError(path, f"seg colour ({r}, {g}, {b}) is outside the class table ({int(counts[unmatched].sum())} "
                                 f"pixel(s) match no part_colors entry{within}; black is background)")
    return ulab[inverse].reshape(rgb.shape[:2])


# ---------------------------------------------------------------------------------------------------
# Resizing
# ---------------------------------------------------------------------------------------------------
def letterbox_box(height: int, width: int) -> tuple[int, int, int]:
    """``(side, top, left)``: a [height, width] frame padded to the square ``side = max(height, width)``
    sits at rows ``top:top + height`` and columns ``left:left + width`` (centred, the odd pixel of pad
    below / right)."""
    side = max(int(height), int(width))
    return side, (side - int(height)) // 2, (side - int(width)) // 2


def pad_to_square(img: np.ndarray) -> np.ndarray:
    """``img`` [H, W, ...] padded with zeros (black; background) to [side, side, ...] (:func:`letterbox_box`)."""
    side, top, left = letterbox_box(*img.shape[:2])
    if img.shape[0] == img.shape[1]:
        return img
    pad = [(top, side - img.shape[0] - top), (left, side - img.shape[1] - left)] + [(0, 0)] * (img.ndim - 2)
    return np.pad(img, pad)


def resize_image(img: np.ndarray, size: int, letterbox: bool = False) -> np.ndarray:
    """Square working resolution, area interpolation (the paper resizes every image to 384 x 384);
    ``letterbox``: padded to a square with black first (:func:`pad_to_square`)."""
    if letterbox:
        img = pad_to_square(img)
    if img.shape[0] == size and img.shape[1] == size:
        return img
    return cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA)


def _frame_samples(n: int, offset: int, side: int, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bilinear taps along one axis from a frame's ``n`` pixels (at ``offset`` in the padded square of
    ``side``) into the working grid of ``size``: ``(i0, i1, weight of i1)``.  Sample positions are
    clamped to the working pixels that hold some of the frame, so no tap lands on pure pad."""
    scale = size / side
    lo = int(np.floor(offset * scale))
    hi = max(lo, int(np.ceil((offset + n) * scale)) - 1)
    c = np.clip((np.arange(n) + offset + 0.5) * scale - 0.5, lo, hi)
    i0 = np.floor(c).astype(np.intp)
    i1 = np.minimum(i0 + 1, hi)
    return i0, i1, (c - i0).astype(np.float32)


def probs_to_size(probs: np.ndarray, height: int, width: int, letterbox: bool = False) -> np.ndarray:
    """Bilinear resize of a probability map [R,R] back to the original [height, width] (values stay in
    [0,1]): the way back from :func:`resize_image`'s working resolution.  ``letterbox``: the pad is
    cropped -- each frame pixel is sampled bilinearly at its own place in the padded square, from the
    working pixels that hold some of the frame only (module docstring)."""
    if not letterbox:
        if probs.shape == (height, width):
            return probs
        return np.clip(cv2.resize(probs, (width, height), interpolation=cv2.INTER_LINEAR), 0.0, 1.0)
    side, top, left = letterbox_box(height, width)
    r0, r1, ry = _frame_samples(height, top, side, probs.shape[0])
    c0, c1, cx = _frame_samples(width, left, side, probs.shape[1])
    p = np.asarray(probs, np.float32)
    rows = p[r0] * (1 - ry)[:, None] + p[r1] * ry[:, None]                 # height x R
    out = rows[:, c0] * (1 - cx)[None, :] + rows[:, c1] * cx[None, :]     # height x width
    return np.clip(out, 0.0, 1.0)


def resize_nearest(lbl: np.ndarray, size: int, letterbox: bool = False) -> np.ndarray:
    """Nearest-neighbour resize of a label/mask array (bool or uint8) to size x size (``letterbox``:
    padded with background first, as :func:`resize_image`)."""
    if letterbox:
        lbl = pad_to_square(lbl)
    if lbl.shape[0] == size and lbl.shape[1] == size:
        return lbl
    out = cv2.resize(lbl.astype(np.uint8), (size, size), interpolation=cv2.INTER_NEAREST)
    return out.astype(lbl.dtype)


# ---------------------------------------------------------------------------------------------------
# Decode cache
# ---------------------------------------------------------------------------------------------------
class DecodeCache:
    """Content-addressed cache of decoded, resized arrays: ``<root>/<sha[:2]>/<sha>-<kind>-<size>.npz``,
    deflate-compressed (``np.savez_compressed``; uncompressed entries of earlier versions still read).

    ``root=None`` disables caching (every call decodes).
    """

    def __init__(self, root: str | Path | None = DEFAULT_CACHE_DIR):
        self.root = Path(root) if root is not None else None
        self.hits = 0
        self.misses = 0

    @staticmethod
    def key(sha: str, kind: str, size: int) -> str:
        return f"{sha}-{kind}-{int(size)}"

    def path(self, sha: str, kind: str, size: int) -> Path:
        return self.root / sha[:2] / f"{self.key(sha, kind, size)}.npz"

    def get(self, sha: str, kind: str, size: int) -> tuple[np.ndarray, tuple[int, int]] | None:
        hit = self.get_entry(sha, kind, size)
        return None if hit is None else hit[:2]

    def get_entry(self, sha: str, kind: str, size: int) -> tuple[np.ndarray, tuple[int, int], str | None] | None:
        """``(array, native_hw, note)`` or None (miss, unreadable entry, or an entry of another key)."""
        if self.root is None:
            return None
        p = self.path(sha, kind, size)
        if not p.exists():
            self.misses += 1
            return None
        try:
            with np.load(p, allow_pickle=False) as z:
                if str(z["k"]) != self.key(sha, kind, size):
                    raise ValueError("entry of another key")
                arr, hw = z["a"], tuple(int(v) for v in z["hw"])
                note = str(z["w"]) or None
        except Exception:  # noqa: BLE001 -- a torn, foreign or misplaced entry is a miss; it is rewritten
            self.misses += 1
            return None
        self.hits += 1
        return arr, hw, note

    def put(self, sha: str, kind: str, size: int, arr: np.ndarray, native_hw: tuple[int, int],
            note: str | None = None) -> None:
        if self.root is None:
            return
        p = self.path(sha, kind, size)
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp = p.with_name(f".{p.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp.npz")
        try:
            np.savez_compressed(tmp, a=arr, hw=np.asarray(native_hw, np.int64), k=np.str_(self.key(sha, kind, size)),
                     w=np.str_(note or ""))
            os.replace(tmp, p)
        finally:
            if tmp.exists():
                tmp.unlink()


@dataclasses.dataclass
class Loaded:
    array: np.ndarray            # at the working resolution
    sha256: str                  # of the file bytes
    native_hw: tuple[int, int]   # (height, width) of the file


def _load(path, size: int, kind: str, cache: DecodeCache | None, decode, max_pixels: int | None,
          letterbox: bool = False) -> Loaded:
    """``decode(array) -> array`` or ``(array, note)``; a note (multi-valued mask; a frame's bit depth)
    is cached with the entry and warned about once per file, whether decoded now or read from the
    cache.  The pixel limit is checked on the header first, so a cached entry made under a higher limit
    is refused too.  ``letterbox`` (:func:`resize_image`) gets its own cache kind."""
    data = read_image_bytes(path, max_pixels)
    sha = hashlib.sha256(data).hexdigest()
    rgb = kind.startswith("rgb")
    warn = warn_frame_once if rgb else warn_mask_once
    kind = f"{kind}-letterbox" if letterbox else kind
    if cache is not None:
        hit = cache.get_entry(sha, kind, size)
        if hit is not None:
            warn(path, hit[2])
            return Loaded(hit[0], sha, hit[1])
    full = decode(_decode(data, path))
    full, note = full if isinstance(full, tuple) else (full, None)
    warn(path, note)
    hw = (int(full.shape[0]), int(full.shape[1]))
    arr = resize_image(full, size, letterbox) if rgb else resize_nearest(full, size, letterbox)
    if cache is not None:
        cache.put(sha, kind, size, arr, hw, note)
    return Loaded(arr, sha, hw)


def rgb_kind(bit_depth="auto") -> str:
    """Decode-cache kind of a frame read under ``bit_depth`` (``rgb`` for ``auto``, as before)."""
    bit_depth = check_bit_depth(bit_depth)
    return "rgb" if bit_depth == AUTO_BIT_DEPTH else f"rgb{int(bit_depth)}bit"


def load_rgb(path, size: int, cache: DecodeCache | None = None, *, max_pixels: int | None = None,
             bit_depth="auto", letterbox: bool = False) -> Loaded:
    """RGB uint8 [size, size, 3] (area interpolation), its sha256 and native size; cached.  Refused
    above ``max_pixels`` (None: :data:`DEFAULT_MAX_PIXELS`) before decoding; 16-bit files read under
    ``bit_depth`` (:func:`scale_16bit`); ``letterbox``: padded to a square first (:func:`resize_image`)."""
    return _load(path, size, rgb_kind(bit_depth), cache, lambda a: rgb8_and_note(a, path, bit_depth), max_pixels,
                 letterbox)


def mask_kind(threshold: float | None) -> str:
    """Decode-cache kind of a mask read with ``threshold`` (``maskgt0`` for the default rule; the old
    ``maskauto`` entries, made under an earlier rule, are never read)."""
    return "maskgt0" if threshold is None else f"mask{threshold}"


def load_mask(path, size: int, cache: DecodeCache | None = None, threshold: float | None = None, *,
              max_pixels: int | None = None, letterbox: bool = False) -> Loaded:
    """bool [size, size] (nearest), binarised by :func:`binarize_mask`; cached per threshold;
    ``letterbox`` as :func:`load_rgb`'s."""
    return _load(path, size, mask_kind(threshold), cache, lambda a: binarize_mask(a, threshold), max_pixels,
                 letterbox)


def load_labels(path, size: int, cache: DecodeCache | None = None,
                colors: dict | ColorTable | None = None, *, max_pixels: int | None = None,
                letterbox: bool = False) -> Loaded:
    """Part labels uint8 [size, size] (nearest): a label image, or a colour-coded one mapped by ``colors``
    (:func:`parts_from_colors`: a colour outside the table refuses the file); ``letterbox`` as
    :func:`load_rgb`'s."""
    if colors:
        table = as_color_table(colors)
        return _load(path, size, table.kind(), cache,
                     lambda a: parts_from_colors(rgb8_and_note(a, path)[0], table, path), max_pixels, letterbox)

    def as_labels(a):
        if a.ndim == 3:
            a = a[..., 0]
        if a.dtype != np.uint8:
            a = np.clip(a, 0, 255).astype(np.uint8)
        return a

    return _load(path, size, "labels", cache, as_labels, max_pixels, letterbox)
