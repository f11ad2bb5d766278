"""One image/mask loader for every source.

RGB uint8 images, bool masks by ``foreground = value > 0`` unless a protocol sets a threshold, the header's size
checked against ``max_pixels`` before decoding, and a decode cache keyed by (sha256, kind, resolution)
(docs/decisions.md, "Image and mask decoding").  The prepare stage reads its manifest rows here: every file
decoded once (:func:`decode_rows`, :func:`content_digest`), then the working-resolution arrays
(:func:`iter_arrays`).  A file's width, height and EXIF orientation come from its header (PNG, JPEG, TIFF classic
and BigTIFF, BMP; :func:`header_size`, :func:`jpeg_orientation`), the format told by the content as OpenCV does (why
not Pillow: docs/dependencies.md).
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import os
import struct
import uuid
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from pipeline.runtime.errors import BIT_DEPTH, MAX_PIXELS, InputError, Option, caller, literal
from pipeline.params import AUTO_BIT_DEPTH, BIT_DEPTHS, PAPER, SPLITS

__all__ = ["SUPPORTED_SUFFIXES", "header_size", "jpeg_orientation", "BadFileError", "broken_link_reason", "pixel_limit",
           "check_bit_depth", "to_rgb8", "read_rgb", "reset_frame_warnings", "read_mask", "ColorTable", "resize_image",
           "probs_to_size", "resize_nearest", "DecodeCache", "Loaded", "load_rgb", "mask_kind", "load_mask",
           "load_labels", "has_file", "load_row", "decode_rows", "content_digest", "iter_arrays"]

log = logging.getLogger(__name__)

SUPPORTED_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
DEFAULT_CACHE_DIR = ".cache/decode"
MASK_RULE = "foreground = value > 0"
#: the pixel limit's default: the params schema's ``data.max_pixels``
DEFAULT_MAX_PIXELS = PAPER.data.max_pixels
UNDECODABLE = "corrupt or undecodable image"


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers: C0..CF except C4 (DHT), C8 (JPG, reserved) and CC (DAC)
_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def _png(data: bytes) -> tuple[int, int] | None:
    if len(data) < 24 or data[12:16] != b"IHDR":
        return None
    return struct.unpack(">II", data[16:24])


def _jpeg_segments(data: bytes):
    """Yield (marker, offset, length) of a JPEG's marker segments with a length field, in file order.

    Stop at bytes that are not a marker, or at a segment shorter than its length field.
    """
    i, n = 2, len(data)
    while i + 4 <= n:
        if data[i] != 0xFF:
            return
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD9)):  # TEM, RSTn, SOI, EOI: no length
            i += 2
            continue
        length = struct.unpack(">H", data[i + 2:i + 4])[0]
        yield marker, i, length
        if length < 2:
            return
        i += 2 + length


def _jpeg(data: bytes) -> tuple[int, int] | None:
    for marker, i, length in _jpeg_segments(data):
        if marker in _SOF:
            if i + 9 > len(data):
                return None
            h, w = struct.unpack(">HH", data[i + 5:i + 9])
            return w, h
        if marker == 0xDA or length < 2:  # start of scan before any frame header: not a valid file
            return None
    return None


def _tiff(data: bytes) -> tuple[int, int] | None:
    e = "<" if data[:2] == b"II" else ">"
    version = struct.unpack(e + "H", data[2:4])[0]
    if version == 42:
        head, count_fmt, entry_fmt, entry_size, off_fmt = 8, "H", "HHI", 12, "I"
    elif version == 43 and len(data) >= 16:
        head, count_fmt, entry_fmt, entry_size, off_fmt = 16, "Q", "HHQ", 20, "Q"
    else:
        return None
    size = lambda fmt: struct.calcsize(e + fmt)  # noqa: E731 -- standard sizes, no alignment
    ifd = struct.unpack(e + off_fmt, data[head - size(off_fmt):head])[0]
    csize = size(count_fmt)
    if ifd + csize > len(data):
        return None
    count = struct.unpack(e + count_fmt, data[ifd:ifd + csize])[0]
    dims: dict[int, int] = {}
    value_at = size(entry_fmt)
    for k in range(count):
        at = ifd + csize + k * entry_size
        if at + entry_size > len(data):
            return None
        tag, typ, n = struct.unpack(e + entry_fmt, data[at:at + value_at])
        if tag in (256, 257) and n == 1:
            fmt = {3: "H", 4: "I", 16: "Q"}.get(typ)
            if fmt is None:
                return None
            dims[tag] = struct.unpack(e + fmt, data[at + value_at:at + value_at + size(fmt)])[0]
    if 256 not in dims or 257 not in dims:
        return None
    return dims[256], dims[257]


def _bmp(data: bytes) -> tuple[int, int] | None:
    if len(data) < 26:
        return None
    dib = struct.unpack("<I", data[14:18])[0]
    if dib == 12:
        return struct.unpack("<HH", data[18:22])
    w, h = struct.unpack("<ii", data[18:26])
    return (w, abs(h)) if w > 0 else None


def header_size(data: bytes) -> tuple[int, int] | None:
    """Read the size a PNG, JPEG, TIFF or BMP file's header declares, without decoding the pixels.

    Parameters
    ----------
    data : bytes
        The file's bytes (its header at least).

    Returns
    -------
    tuple of int or None
        ``(width, height)``; None when the bytes start with none of these formats, or the header is cut short,
        malformed or declares a zero size.
    """
    try:
        if data.startswith(PNG_SIGNATURE):
            size = _png(data)
        elif data.startswith(b"\xff\xd8\xff"):
            size = _jpeg(data)
        elif data[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
            size = _tiff(data)
        elif data.startswith(b"BM"):
            size = _bmp(data)
        else:
            return None
    except struct.error:  # cut short inside a field
        return None
    if size is None or size[0] <= 0 or size[1] <= 0:
        return None
    return int(size[0]), int(size[1])


#: the EXIF (TIFF) tag of the orientation a viewer applies before showing the stored pixels
ORIENTATION_TAG = 0x0112


def _exif_orientation(tiff: bytes) -> int:
    """Read the Orientation tag of IFD0 of an EXIF block's TIFF structure (1 when absent or malformed)."""
    e = {b"II": "<", b"MM": ">"}.get(tiff[:2])
    if e is None or struct.unpack(e + "H", tiff[2:4])[0] != 42:
        return 1
    ifd = struct.unpack(e + "I", tiff[4:8])[0]
    count = struct.unpack(e + "H", tiff[ifd:ifd + 2])[0]
    for k in range(count):
        at = ifd + 2 + 12 * k
        tag, typ, n = struct.unpack(e + "HHI", tiff[at:at + 8])
        if tag == ORIENTATION_TAG and typ == 3 and n == 1:  # one SHORT, held in the entry's value field
            value = struct.unpack(e + "H", tiff[at + 8:at + 10])[0]
            return value if 1 <= value <= 8 else 1
    return 1


def jpeg_orientation(data: bytes) -> int:
    """Read a JPEG file's EXIF orientation: how a viewer turns or flips the stored pixels to show them.

    Parameters
    ----------
    data : bytes
        The file's bytes.

    Returns
    -------
    int
        1-8 (the TIFF/EXIF convention); 1 (shown as stored) for any other format, a JPEG without EXIF or with a
        value outside 1-8, or a malformed header.
    """
    if not data.startswith(b"\xff\xd8\xff"):
        return 1
    try:
        for marker, i, length in _jpeg_segments(data):
            if marker == 0xE1 and data[i + 4:i + 10] == b"Exif\x00\x00":  # APP1 with EXIF
                return _exif_orientation(data[i + 10:i + 2 + length])
            if marker == 0xDA or marker in _SOF or length < 2:  # EXIF comes first: none before the frame
                return 1
    except struct.error:  # cut short inside a field
        return 1
    return 1


class BadFileError(InputError):
    """A file that cannot be used: ``{path}: {reason} ({fix})``.

    Parameters
    ----------
    path : str or Path
        The file.
    reason : str
        Why it cannot be used; names no option (the skipped-file listings hold it).
    fix : str
        What would let the file in, naming ``options`` with ``{}``; empty: nothing.
    *options : Option
        The options ``fix`` names, spelled in the caller's terms (``--max-pixels`` or ``max_pixels=``).
    """

    def __init__(self, path: str | Path, reason: str, fix: str = "", *options: Option):
        self.path = str(path)
        self.reason = reason
        self.fix = fix
        text = f"{literal(path)}: {literal(reason)}" if options else f"{path}: {reason}"
        super().__init__(text + (f" ({fix})" if fix else ""), *options)

    def __reduce__(self):  # noqa: D105 -- pickled across Ray workers: rebuilt from its own arguments
        return type(self), (self.path, self.reason, self.fix, *self.options)


def broken_link_reason(p: Path) -> str:
    """Word a broken symbolic link's reason once (the folder scan and the decode pass say the same).

    Parameters
    ----------
    p : Path
        The link.

    Returns
    -------
    str
        The reason, naming the missing target when it can be read.
    """
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
    """Check a pixel limit: a whole number >= 1.

    Parameters
    ----------
    max_pixels : int, optional
        Width x height above which a file is refused; None: ``data.max_pixels``'s schema default
        (:data:`DEFAULT_MAX_PIXELS`).

    Returns
    -------
    int
        The limit.

    Raises
    ------
    InputError
        Not a whole number >= 1, naming ``--max-pixels`` / ``max_pixels=``.
    """
    if max_pixels is None:
        return DEFAULT_MAX_PIXELS
    if isinstance(max_pixels, bool) or not isinstance(max_pixels, (int, np.integer)) or max_pixels < 1:
        raise InputError("{}: must be a whole number of pixels >= 1 (width x height; default "
                         f"{DEFAULT_MAX_PIXELS:,})", MAX_PIXELS(max_pixels))
    return int(max_pixels)


def check_header(data: bytes, path: str | Path, max_pixels: int | None = None) -> tuple[int, int]:
    """Read ``(width, height)`` from the file header and check it against ``max_pixels``.

    :class:`BadFileError` when there is no header or the image is above the limit.
    """
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


def as_displayed(arr: np.ndarray, orientation: int) -> np.ndarray:
    """Turn ``arr`` [H, W, ...] as a viewer shows it under EXIF ``orientation`` (1-8; 1: as stored).

    2 mirrored, 3 turned 180 degrees, 4 flipped top-bottom, 5 transposed, 6 turned 90 degrees clockwise,
    7 transposed across the other diagonal, 8 turned 90 degrees anticlockwise (what OpenCV's ``imread`` does by
    default).
    """
    o = int(orientation)
    if o in (5, 6, 7, 8):
        arr = arr.swapaxes(0, 1)  # 5; the others are the transpose flipped
        arr = {5: arr, 6: arr[:, ::-1], 7: arr[::-1, ::-1], 8: arr[::-1]}[o]
    else:
        arr = {2: arr[:, ::-1], 3: arr[::-1, ::-1], 4: arr[::-1]}.get(o, arr)
    return np.ascontiguousarray(arr)


def _decode(data: bytes, path: str | Path, orientation: int) -> np.ndarray:
    """Decode an image or mask file's bytes (the one decode of every file): its pixels as displayed.

    The JPEG EXIF ``orientation`` (read once, from the header) is applied here, since ``IMREAD_UNCHANGED`` keeps
    16 bits and alpha but ignores it.
    """
    arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if arr is None or arr.size == 0:
        raise BadFileError(path, UNDECODABLE)
    return as_displayed(arr, orientation)


def _read_displayed(path: str | Path, max_pixels: int | None) -> np.ndarray:
    """:func:`read_image_bytes`, then :func:`_decode` under the header's orientation: a file's pixels as shown."""
    data = read_image_bytes(path, max_pixels)
    return _decode(data, path, jpeg_orientation(data))


#: under ``auto``, a 16-bit frame darker than this is most likely a 10-14-bit sensor's: warned about
LOW_RANGE_16BIT = 1 << 13
#: spelled for the caller when warned, so the decode cache keeps one text
BIT_DEPTH_HINT = "<bit depth option>"
LOW_RANGE_NOTE = "16-bit frame whose brightest value is"


def check_bit_depth(bit_depth) -> str | int:
    """Check a bit depth against :data:`pipeline.params.BIT_DEPTHS` (the Python API's ``bit_depth=``).

    Parameters
    ----------
    bit_depth : str or int
        ``auto`` or the bits a 16-bit frame's sensor fills.

    Returns
    -------
    str or int
        ``bit_depth``.

    Raises
    ------
    InputError
        A value outside the list (a bool included), naming ``--bit-depth`` / ``bit_depth=``.
    """
    if not isinstance(bit_depth, bool) and bit_depth in BIT_DEPTHS:
        return bit_depth
    raise InputError(f"{{}}: expected one of {', '.join(map(str, BIT_DEPTHS))} (bits of a "
                     "16-bit frame's sensor; auto = the file's full range)", BIT_DEPTH(bit_depth))


def scale_16bit(arr: np.ndarray, bit_depth: str | int) -> tuple[np.ndarray, str | None]:
    """Scale a uint16 array to uint8: ``(array, warning or None)``.

    ``auto`` and 16: ``round(v / 257)``; 10/12/14: ``round(min(v, 2**bits - 1) * 255 / (2**bits - 1))``.
    """
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


def rgb8_and_note(arr: np.ndarray, path: str | Path, bit_depth: str | int) -> tuple[np.ndarray, str | None]:
    """Convert as :func:`to_rgb8` does, without its warning: ``(RGB uint8 [H, W, 3], note or None)``.

    The decode cache keeps the note, so a cached frame is warned about too.
    """
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
    a8 = a8[..., None] if a8.ndim == 2 else a8
    if a8.ndim != 3:
        raise BadFileError(path, f"unsupported image shape {arr.shape}")
    ch = a8.shape[2]
    if ch not in (1, 3, 4):
        raise BadFileError(path, f"unsupported channel count {ch}")
    return (np.repeat(a8, 3, axis=2) if ch == 1 else np.ascontiguousarray(a8[..., 2::-1])), note


def to_rgb8(arr: np.ndarray, path: str | Path = "<array>", bit_depth=PAPER.data.bit_depth) -> np.ndarray:
    """Convert a decoded OpenCV array (grey, BGR, BGRA; 8/16-bit or float) to RGB uint8 [H, W, 3].

    A 16-bit frame is scaled by ``bit_depth``; what is worth knowing about its values is warned once.

    Parameters
    ----------
    arr : numpy.ndarray
        The decoded pixels, OpenCV's channel order.
    path : str or Path
        The file the pixels came from, for the messages.
    bit_depth : str or int
        ``data.bit_depth``'s meaning: ``auto`` or the bits a 16-bit frame's sensor fills.

    Returns
    -------
    numpy.ndarray
        RGB uint8 [H, W, 3].

    Raises
    ------
    InputError
        ``bit_depth`` outside :data:`pipeline.params.BIT_DEPTHS`; a :class:`BadFileError` for an unsupported pixel
        type, shape or channel count.
    """
    rgb, note = rgb8_and_note(arr, path, bit_depth)
    warn_frame_once(path, note)
    return rgb


def read_rgb(path: str | Path, *, max_pixels: int | None = None, bit_depth=PAPER.data.bit_depth) -> np.ndarray:
    """Read any supported image file as RGB uint8 [H, W, 3] at native size.

    Parameters
    ----------
    path : str or Path
        The image file (:data:`SUPPORTED_SUFFIXES`).
    max_pixels : int, optional
        Refuse a file above this many pixels, read from its header (None: ``data.max_pixels``'s default).
    bit_depth : str or int
        ``auto`` or the bits a 16-bit frame's sensor fills (``data.bit_depth``).

    Returns
    -------
    numpy.ndarray
        RGB uint8 [H, W, 3], as displayed (EXIF orientation applied).

    Raises
    ------
    BadFileError
        A missing, unreadable, zero-byte, unsupported, corrupt or oversized file.
    """
    return to_rgb8(_read_displayed(path, max_pixels), path, bit_depth)


_warned: set[str] = set()
_warned_frames: set[tuple[str, str]] = set()


def warn_frame_once(path: str | Path, note: str | None) -> None:
    """Warn once per (absolute file path, note) about how a frame's values were read.

    A dark 16-bit frame is warned about once per run (:func:`reset_frame_warnings`).
    """
    dark = bool(note) and note.startswith(LOW_RANGE_NOTE)
    key = ("", LOW_RANGE_NOTE) if dark else (os.path.abspath(path), note)
    if note and key not in _warned_frames:
        _warned_frames.add(key)
        hint = (BIT_DEPTH(12) if dark else BIT_DEPTH).spell(caller())
        log.warning("%s: %s", path, note.replace(BIT_DEPTH_HINT, hint))


def reset_frame_warnings() -> None:
    """Forget the frames warned about, so that a new run's frames are warned about again."""
    _warned_frames.clear()


def warn_mask_once(path: str | Path, note: str | None) -> None:
    """Warn once per file (per process) about a multi-valued mask read with the default rule."""
    if note and str(path) not in _warned:
        _warned.add(str(path))
        log.warning("%s: %s: %s (set an explicit mask_threshold in the protocol file for another rule)",
                    path, note, MASK_RULE)


def binarize_mask(arr: np.ndarray, threshold: float | None = None) -> tuple[np.ndarray, str | None]:
    """Binarise a decoded mask: ``(bool mask, note)``, foreground = max over channels > ``threshold``.

    ``threshold`` None means > 0; ``note`` describes a multi-valued mask under that default rule (more than one
    non-zero value).
    """
    a = arr.max(axis=2) if arr.ndim == 3 else arr
    if threshold is not None:
        return a > threshold, None
    nz = a[a != 0]
    if nz.size == 0 or not (nz != nz.flat[0]).any():
        return a > 0, None
    values = np.unique(nz)
    shown = ", ".join(f"{v:g}" for v in values[:6].tolist()) + (", ..." if values.size > 6 else "")
    return a > 0, f"multi-valued label mask (non-zero values {shown}; {values.size} distinct)"


def read_mask(path: str | Path, threshold: float | None = None, *, max_pixels: int | None = None) -> np.ndarray:
    """Read a mask file as bool [H, W] at native size, warning once per file about a multi-valued mask.

    Parameters
    ----------
    path : str or Path
        The mask file.
    threshold : float, optional
        Foreground = max over channels > ``threshold``; None: > 0.
    max_pixels : int, optional
        Refuse a file above this many pixels, read from its header (None: ``data.max_pixels``'s default).

    Returns
    -------
    numpy.ndarray
        Bool [H, W], as displayed.

    Raises
    ------
    BadFileError
        A missing, unreadable, zero-byte, unsupported, corrupt or oversized file.
    """
    mask, note = binarize_mask(_read_displayed(path, max_pixels), threshold)
    warn_mask_once(path, note)
    return mask


#: the colour of background in every colour-coded part mask (label 0 unless a table maps it)
BACKGROUND_RGB = (0, 0, 0)


@dataclasses.dataclass(frozen=True)
class ColorTable:
    """A colour-coded part mask's class table ``{(r, g, b): label}``, black = background unless listed.

    Attributes
    ----------
    colors : dict
        ``{(r, g, b): label}``.
    tolerance : int
        Per channel, how far a pixel may be from a colour and take it.
    blends : bool
        Whether a pixel within ``tolerance`` of the line between two colours (a JPEG boundary between two
        classes) takes the nearer one's label.
    """

    colors: dict
    tolerance: int = 0
    blends: bool = False

    def __bool__(self) -> bool:  # noqa: D105 -- an empty table is no table: there are no part labels to read
        return bool(self.colors)

    def entries(self) -> dict[tuple[int, int, int], int]:
        """List the table with background.

        Returns
        -------
        dict
            ``{(r, g, b): label}``, black mapped to 0 unless the table maps it.
        """
        return {BACKGROUND_RGB: 0, **{tuple(int(v) for v in k): int(lbl) for k, lbl in self.colors.items()}}

    def kind(self) -> str:
        """Name the decode-cache kind of labels read by this table.

        Returns
        -------
        str
            ``parts<10 hex digits>``: a hash of the table, its tolerance, blending and the rule
            ("refuse-unknown").
        """
        key = repr((sorted(self.entries().items()), int(self.tolerance), bool(self.blends), "refuse-unknown"))
        return f"parts{hashlib.sha256(key.encode()).hexdigest()[:10]}"


def as_color_table(colors: dict | ColorTable) -> ColorTable:
    return colors if isinstance(colors, ColorTable) else ColorTable(dict(colors))


def parts_from_colors(rgb: np.ndarray, colors: dict | ColorTable, path: str | Path = "<array>") -> np.ndarray:
    """Map a colour-coded part mask (RGB uint8) to part labels uint8 by the table (a dict: exact colours).

    A colour outside the table is a :class:`BadFileError` naming the most frequent one.
    """
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
        raise BadFileError(path, f"seg colour ({r}, {g}, {b}) is outside the class table "
                                 f"({int(counts[unmatched].sum())} pixel(s) match no part_colors entry{within}; "
                                 "black is background)")
    return ulab[inverse].reshape(rgb.shape[:2])


def letterbox_box(height: int, width: int) -> tuple[int, int, int]:
    """``(side, top, left)`` of a frame centred in its padded square (the odd pixel of pad below / right)."""
    side = max(int(height), int(width))
    return side, (side - int(height)) // 2, (side - int(width)) // 2


def pad_to_square(img: np.ndarray) -> np.ndarray:
    """``img`` [H, W, ...] padded with zeros to its square (:func:`letterbox_box`)."""
    side, top, left = letterbox_box(*img.shape[:2])
    if img.shape[0] == img.shape[1]:
        return img
    pad = [(top, side - img.shape[0] - top), (left, side - img.shape[1] - left)] + [(0, 0)] * (img.ndim - 2)
    return np.pad(img, pad)


def resize_image(img: np.ndarray, size: int, letterbox: bool = PAPER.data.letterbox, interpolation: int = cv2.INTER_AREA
                 ) -> np.ndarray:
    """Resize an image to the square working resolution, area interpolation by default.

    Parameters
    ----------
    img : numpy.ndarray
        [H, W, ...] at native size.
    size : int
        The working resolution R.
    letterbox : bool
        Pad to a square with zeros first (aspect kept, ``data.letterbox``); else squash.
    interpolation : int
        The OpenCV interpolation flag.

    Returns
    -------
    numpy.ndarray
        [R, R, ...]; ``img`` itself when it is already R x R (and not padded).
    """
    if letterbox:
        img = pad_to_square(img)
    if img.shape[0] == size and img.shape[1] == size:
        return img
    return cv2.resize(img, (size, size), interpolation=interpolation)


def _frame_samples(n: int, offset: int, side: int, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Place bilinear taps ``(i0, i1, weight of i1)`` along one axis of a frame in its padded square.

    The frame's ``n`` pixels lie at ``offset``; the taps are clamped to the working pixels holding some of the
    frame (no tap on pure pad).
    """
    scale = size / side
    lo = int(np.floor(offset * scale))
    hi = max(lo, int(np.ceil((offset + n) * scale)) - 1)
    c = np.clip((np.arange(n) + offset + 0.5) * scale - 0.5, lo, hi)
    i0 = np.floor(c).astype(np.intp)
    i1 = np.minimum(i0 + 1, hi)
    return i0, i1, (c - i0).astype(np.float32)


def probs_to_size(probs: np.ndarray, height: int, width: int, letterbox: bool = PAPER.data.letterbox) -> np.ndarray:
    """Resize a probability map [R, R] back to its frame's [height, width], bilinearly.

    Parameters
    ----------
    probs : numpy.ndarray
        Probabilities [R, R] at the working resolution.
    height, width : int
        The frame's size as displayed.
    letterbox : bool
        Whether the frame was letterboxed (``data.letterbox``): the pad is then cropped and never sampled
        (:func:`_frame_samples`).

    Returns
    -------
    numpy.ndarray
        Probabilities [height, width], clipped to [0, 1].
    """
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


def resize_nearest(lbl: np.ndarray, size: int, letterbox: bool = PAPER.data.letterbox) -> np.ndarray:
    """Resize a label or mask array to size x size, nearest neighbour.

    Parameters
    ----------
    lbl : numpy.ndarray
        Labels or a mask [H, W].
    size : int
        The working resolution.
    letterbox : bool
        Pad to a square first, as :func:`resize_image` does.

    Returns
    -------
    numpy.ndarray
        [size, size], of ``lbl``'s dtype.
    """
    return resize_image(lbl.astype(np.uint8), size, letterbox, cv2.INTER_NEAREST).astype(lbl.dtype)


class DecodeCache:
    """Content-addressed cache of decoded, resized arrays (``<sha[:2]>/<sha>-<kind>-<size>.npz``).

    Parameters
    ----------
    root : str or Path, optional
        The cache folder (``data.cache_dir``); None disables the cache.
    """

    def __init__(self, root: str | Path | None = DEFAULT_CACHE_DIR):
        self.root = Path(root) if root is not None else None
        self.hits = 0
        self.misses = 0

    @staticmethod
    def key(sha: str, kind: str, size: int) -> str:
        """Name an entry: ``<sha>-<kind>-<size>``, also stored inside it.

        Parameters
        ----------
        sha : str
            sha256 of the file's bytes.
        kind : str
            How the file was read (``rgb``, ``maskgt0``, ``parts...``, with ``-letterbox``/``-exif<n>``).
        size : int
            The working resolution.

        Returns
        -------
        str
            The key.
        """
        return f"{sha}-{kind}-{int(size)}"

    def path(self, sha: str, kind: str, size: int) -> Path:
        """Locate an entry's file under the root.

        Parameters
        ----------
        sha : str
            sha256 of the file's bytes.
        kind : str
            How the file was read.
        size : int
            The working resolution.

        Returns
        -------
        Path
            ``<root>/<sha[:2]>/<key>.npz``.
        """
        return self.root / sha[:2] / f"{self.key(sha, kind, size)}.npz"

    def get(self, sha: str, kind: str, size: int) -> tuple[np.ndarray, tuple[int, int], str | None] | None:
        """Look an entry up.

        Parameters
        ----------
        sha : str
            sha256 of the file's bytes.
        kind : str
            How the file was read.
        size : int
            The working resolution.

        Returns
        -------
        tuple or None
            ``(array, native_hw, note or None)``; None on a miss, an unreadable entry, or an entry of another key
            (the cache disabled included).
        """
        if self.root is None:
            return None
        hit = None
        try:
            with np.load(self.path(sha, kind, size), allow_pickle=False) as z:
                if str(z["k"]) == self.key(sha, kind, size):  # else an entry of another key, misplaced: a miss
                    hit = z["a"], tuple(int(v) for v in z["hw"]), str(z["w"]) or None
        except Exception:  # noqa: BLE001 -- a missing, torn or foreign entry is a miss; it is rewritten
            pass
        if hit is None:
            self.misses += 1
        else:
            self.hits += 1
        return hit

    def put(self, sha: str, kind: str, size: int, arr: np.ndarray, native_hw: tuple[int, int],
            note: str | None = None) -> None:
        """Store an entry atomically (a temporary file, then a rename); nothing when the cache is disabled.

        Parameters
        ----------
        sha : str
            sha256 of the file's bytes.
        kind : str
            How the file was read.
        size : int
            The working resolution.
        arr : numpy.ndarray
            The array at the working resolution.
        native_hw : tuple of int
            ``(height, width)`` of the file as displayed.
        note : str, optional
            What the reader would warn about (kept, so a cached read warns too).
        """
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
    """One file read at the working resolution.

    Attributes
    ----------
    array : numpy.ndarray
        The pixels, labels or mask at the working resolution.
    sha256 : str
        sha256 of the file's bytes.
    native_hw : tuple of int
        ``(height, width)`` of the file as displayed (EXIF orientation applied).
    orientation : int
        The file's EXIF orientation (1: shown as stored).
    """

    array: np.ndarray
    sha256: str
    native_hw: tuple[int, int]
    orientation: int = 1

    @property
    def content_sha256(self) -> str:
        """The key of the pixels a model sees: :attr:`sha256`, or a hash over it and the orientation.

        A file shown turned or flipped (EXIF orientation other than 1) gets the latter, so answers cached before
        the orientation was applied are not reused.
        """
        if self.orientation == 1:
            return self.sha256
        return hashlib.sha256(f"{self.sha256}-exif-orientation-{self.orientation}".encode()).hexdigest()


def _load(path, size: int, kind: str, cache: DecodeCache | None, decode, max_pixels: int | None,
          letterbox: bool = PAPER.data.letterbox) -> Loaded:
    """Read ``path`` through the cache: ``decode(array)`` returns an array or ``(array, note)``.

    The note is cached with the entry and warned about once per file.  The pixel limit is checked first, so a
    cached entry made under a higher limit is refused.
    """
    data = read_image_bytes(path, max_pixels)
    sha = hashlib.sha256(data).hexdigest()
    rgb = kind.startswith("rgb")
    warn = warn_frame_once if rgb else warn_mask_once
    kind = f"{kind}-letterbox" if letterbox else kind
    orientation = jpeg_orientation(data)
    if orientation != 1:  # entries decoded before the orientation was applied are not this one's
        kind = f"{kind}-exif{orientation}"
    if cache is not None:
        hit = cache.get(sha, kind, size)
        if hit is not None:
            warn(path, hit[2])
            return Loaded(hit[0], sha, hit[1], orientation)
    full = decode(_decode(data, path, orientation))
    full, note = full if isinstance(full, tuple) else (full, None)
    warn(path, note)
    hw = (int(full.shape[0]), int(full.shape[1]))
    arr = resize_image(full, size, letterbox) if rgb else resize_nearest(full, size, letterbox)
    if cache is not None:
        cache.put(sha, kind, size, arr, hw, note)
    return Loaded(arr, sha, hw, orientation)


def load_rgb(path, size: int, cache: DecodeCache | None = None, *, max_pixels: int | None = None,
             bit_depth=PAPER.data.bit_depth, letterbox: bool = PAPER.data.letterbox) -> Loaded:
    """Read an image file at the working resolution (area interpolation), through the decode cache.

    Parameters
    ----------
    path : str or Path
        The image file.
    size : int
        The working resolution S (``data.resolution``).
    cache : DecodeCache, optional
        The decode cache (kind ``rgb``, or ``rgb<bits>bit`` under a stated bit depth); None: none.
    max_pixels : int, optional
        Refuse a file above this many pixels, read from its header (None: ``data.max_pixels``'s default).
    bit_depth : str or int
        ``auto`` or the bits a 16-bit frame's sensor fills (``data.bit_depth``).
    letterbox : bool
        Pad to a square before resizing (``data.letterbox``); else squash.

    Returns
    -------
    Loaded
        RGB uint8 [S, S, 3], the file's sha256, its size as displayed and its EXIF orientation.

    Raises
    ------
    InputError
        ``bit_depth`` outside :data:`pipeline.params.BIT_DEPTHS`; a :class:`BadFileError` for a bad file.
    """
    bit_depth = check_bit_depth(bit_depth)
    kind = "rgb" if bit_depth == AUTO_BIT_DEPTH else f"rgb{int(bit_depth)}bit"
    return _load(path, size, kind, cache, lambda a: rgb8_and_note(a, path, bit_depth), max_pixels,
                 letterbox)


def mask_kind(threshold: float | None) -> str:
    """Name the decode-cache kind of a mask read with ``threshold``.

    Parameters
    ----------
    threshold : float or None
        The mask's threshold (None: the loader's rule, > 0).

    Returns
    -------
    str
        ``maskgt0`` or ``mask<threshold>``.
    """
    return "maskgt0" if threshold is None else f"mask{threshold}"


def load_mask(path, size: int, cache: DecodeCache | None = None, threshold: float | None = None, *,
              max_pixels: int | None = None, letterbox: bool = PAPER.data.letterbox) -> Loaded:
    """Read a mask file at the working resolution (nearest), binarised by :func:`binarize_mask`.

    Parameters
    ----------
    path : str or Path
        The mask file.
    size : int
        The working resolution S.
    cache : DecodeCache, optional
        The decode cache (one entry per threshold); None: none.
    threshold : float, optional
        Foreground = max over channels > ``threshold``; None: > 0.
    max_pixels : int, optional
        Refuse a file above this many pixels, read from its header (None: ``data.max_pixels``'s default).
    letterbox : bool
        Pad to a square before resizing, as its image is (``data.letterbox``).

    Returns
    -------
    Loaded
        Bool [S, S], the file's sha256, size as displayed and EXIF orientation.

    Raises
    ------
    BadFileError
        A missing, unreadable, zero-byte, unsupported, corrupt or oversized file.
    """
    return _load(path, size, mask_kind(threshold), cache, lambda a: binarize_mask(a, threshold), max_pixels,
                 letterbox)


def load_labels(path, size: int, cache: DecodeCache | None = None,
                colors: dict | ColorTable | None = None, *, max_pixels: int | None = None,
                letterbox: bool = PAPER.data.letterbox) -> Loaded:
    """Read a part-label file at the working resolution (nearest).

    Parameters
    ----------
    path : str or Path
        A label image (value = label) or a colour-coded part mask.
    size : int
        The working resolution S.
    cache : DecodeCache, optional
        The decode cache; None: none.
    colors : dict or ColorTable, optional
        The colour table of a colour-coded mask; None or empty: a label image.
    max_pixels : int, optional
        Refuse a file above this many pixels, read from its header (None: ``data.max_pixels``'s default).
    letterbox : bool
        Pad to a square before resizing, as its image is (``data.letterbox``).

    Returns
    -------
    Loaded
        Labels uint8 [S, S], the file's sha256, size as displayed and EXIF orientation.

    Raises
    ------
    BadFileError
        A bad file, or a colour outside the table.
    """
    if colors:
        table = as_color_table(colors)
        return _load(path, size, table.kind(), cache,
                     lambda a: parts_from_colors(rgb8_and_note(a, path, AUTO_BIT_DEPTH)[0], table, path), max_pixels, letterbox)
    return _load(path, size, "labels", cache, lambda a: np.clip(a[..., 0] if a.ndim == 3 else a, 0, 255)
                 .astype(np.uint8), max_pixels, letterbox)


def has_file(value) -> bool:
    """Tell whether a manifest cell names a file (a non-empty string; None, NaN or ``""``: none).

    Parameters
    ----------
    value : object
        A ``mask_path`` or ``part_path`` cell.

    Returns
    -------
    bool
        True when it names a file.
    """
    return isinstance(value, str) and value != ""


def load_row(image_path, mask_path, part_path, size: int, cache: DecodeCache | None, frames,
             mask_threshold: float | None = None, part_colors: dict | ColorTable | None = None
             ) -> tuple[Loaded, Loaded | None, Loaded | None]:
    """Read one manifest row's files at the working resolution: its image, then its mask and part labels.

    Parameters
    ----------
    image_path : str or Path
        The image file.
    mask_path, part_path : str, Path or None
        The mask and part-label files; none when :func:`has_file` says so.
    size : int
        The working resolution S (``data.resolution``).
    cache : DecodeCache or None
        The decode cache (None: none).
    frames : pipeline.datasets.params.FrameSettings
        How a frame file is read (``data.bit_depth``, ``data.letterbox``, ``data.max_pixels``); not imported here,
        so a stage that reads files does not depend on the params module.
    mask_threshold : float, optional
        The source's mask threshold (:func:`load_mask`).
    part_colors : dict or ColorTable, optional
        The source's part colour table (:func:`load_labels`).

    Returns
    -------
    tuple
        ``(image, mask or None, parts or None)``, each a :class:`Loaded`.

    Raises
    ------
    BadFileError
        A bad file, or a mask or part file whose size as displayed differs from the image's.
    """
    kw = {"max_pixels": frames.max_pixels, "letterbox": frames.letterbox}
    img = load_rgb(image_path, size, cache, bit_depth=frames.bit_depth, **kw)
    mask = load_mask(mask_path, size, cache, mask_threshold, **kw) if has_file(mask_path) else None
    _same_size(mask, "mask", mask_path, img, image_path)  # checked before the part file is read
    parts = load_labels(part_path, size, cache, part_colors, **kw) if has_file(part_path) else None
    _same_size(parts, "part", part_path, img, image_path)
    return img, mask, parts


def _same_size(got: Loaded | None, what: str, path, img: Loaded, image_path) -> None:
    """Refuse a mask or part file whose size as displayed differs from its image's (:class:`BadFileError`)."""
    if got is not None and got.native_hw != img.native_hw:
        raise BadFileError(path, f"{what} size {got.native_hw[1]}x{got.native_hw[0]} differs from image "
                                 f"{image_path} size {img.native_hw[1]}x{img.native_hw[0]}")


def decode_rows(rows, spec, frames, size: int, cache: DecodeCache | None, policy, bar=None):
    """Decode every file of the manifest rows once (into the cache) and fill the width, height and sha256 columns.

    A row with a bad file, or a mask or part file of another size than its image, goes through the policy, which
    lists its other files as not used (``BadInputPolicy.report_error``).  The rows, spec and policy are
    :mod:`pipeline.datasets.manifest`'s and the bar :mod:`pipeline.runtime.progress`'s, not imported here, so
    that a stage that reads files does not depend on them (as ``frames`` in :func:`load_row`).

    Parameters
    ----------
    rows : pandas.DataFrame
        The checked manifest rows (:func:`pipeline.datasets.manifest.check_manifest`).
    spec : pipeline.datasets.manifest.DatasetSpec
        The source's reading rules (mask threshold, part colours).
    frames : pipeline.datasets.params.FrameSettings
        How a frame file is read (``data.bit_depth``, ``data.letterbox``, ``data.max_pixels``).
    size : int
        The working resolution (``data.resolution``).
    cache : DecodeCache or None
        The decode cache (None: none).
    policy : pipeline.datasets.manifest.BadInputPolicy
        Refuses a bad file or lists it.
    bar : callable, optional
        Wraps the rows as they are decoded in a progress bar, called as
        :func:`pipeline.runtime.progress.progress` is (``bar(iterable, total=, desc=)``); None: no bar.

    Returns
    -------
    pandas.DataFrame
        The rows kept, with ``width``, ``height`` (as displayed) and ``sha256`` (of the pixels as shown).

    Raises
    ------
    BadFileError
        A mask or part file whose size differs from its image's, when the policy refuses it.
    InputError
        When no image is left, or a bad file the policy refuses.
    """
    kept: dict[int, Loaded] = {}   # row -> its image
    listed = rows.itertuples(index=False)
    for i, r in enumerate(listed if bar is None else bar(listed, total=len(rows), desc="decode")):
        try:
            img = load_row(r.image_path, r.mask_path, r.part_path, size, cache, frames, spec.mask_threshold,
                           spec.part_colors)[0]
        except BadFileError as e:  # the policy also lists the row's other files as not used
            policy.report_error(r.image_id, e, [f for f in (r.image_path, r.mask_path, r.part_path) if has_file(f)])
            continue
        kept[i] = img
    out = rows.iloc[list(kept)].reset_index(drop=True).copy()
    out["width"] = np.asarray([im.native_hw[1] for im in kept.values()], np.int64)
    out["height"] = np.asarray([im.native_hw[0] for im in kept.values()], np.int64)
    out["sha256"] = [im.content_sha256 for im in kept.values()]  # an EXIF-turned file: its pixels as shown
    for col in ("mask_path", "part_path"):
        out[col] = [p if has_file(p) else None for p in out[col]]
    if out.empty:
        raise InputError("no usable images left after skipping bad files (see the skipped-files table)")
    for split in SPLITS:
        if not (out["split"] == split).any():
            log.warning("split %r has no images", split)
    return out


def content_digest(rows) -> str:
    """Hash the data's identity for the fingerprint: (image_id, split, group, file sha256) in manifest order.

    Parameters
    ----------
    rows : pandas.DataFrame
        Decoded manifest rows (:func:`decode_rows`).

    Returns
    -------
    str
        The sha256 hex digest.
    """
    h = hashlib.sha256()
    for iid, split, group, s in zip(rows["image_id"], rows["split"], rows["group"], rows["sha256"]):
        h.update(f"{iid}\0{split}\0{group}\0{s}\n".encode())
    return h.hexdigest()


def iter_arrays(rows, spec, frames, size: int, cache: DecodeCache | None
                ) -> Iterator[tuple[int, np.ndarray, np.ndarray | None, np.ndarray | None]]:
    """Read each row's arrays at the working resolution, in manifest order.

    Parameters
    ----------
    rows : pandas.DataFrame
        Decoded manifest rows (:func:`decode_rows`).
    spec : pipeline.datasets.manifest.DatasetSpec
        The source's reading rules.
    frames : pipeline.datasets.params.FrameSettings
        How a frame file is read.
    size : int
        The working resolution S.
    cache : DecodeCache or None
        The decode cache (None: none).

    Yields
    ------
    tuple
        ``(row index, image uint8 [S,S,3], mask bool [S,S] or None, parts uint8 [S,S] or None)``.
    """
    for i, r in enumerate(rows.itertuples(index=False)):
        files = load_row(r.image_path, r.mask_path, r.part_path, size, cache, frames, spec.mask_threshold,
                         spec.part_colors)
        yield i, *(None if f is None else f.array for f in files)
