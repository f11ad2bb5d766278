"""Width and height of a PNG, JPEG, TIFF (classic and BigTIFF) or BMP file from its header.

The format is told by the content, as OpenCV does (why not Pillow: docs/dependencies.md).
"""

from __future__ import annotations

import struct

__all__ = ["header_size", "jpeg_orientation"]

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
