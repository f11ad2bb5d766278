"""One image/mask loader for every source, with a content-addressed decode cache.

``read_rgb(path)``
    Any supported file (png, jpg/jpeg, tif/tiff, bmp) -> RGB uint8 [H, W, 3] at native size.
    Grey is replicated to three channels; RGBA drops alpha (spacecraft imagery has no meaningful
    transparency; compositing on black would equal dropping it for premultiplied black
    backgrounds); 16-bit is scaled to 8-bit by rounding ``v / 257`` (the exact 65535 -> 255 map);
    float images are taken as [0, 1] and clipped.  OpenCV decodes BGR, so channels are reversed.
    Raises :class:`InputError` naming the file for a missing, zero-byte, corrupt or unsupported file.

``read_mask(path, threshold)``
    Any mask file -> bool [H, W]; foreground = max over channels > ``threshold`` (``None``: auto,
    > 0 for 0/1 label files, otherwise > half the dtype range, i.e. > 127 for 8-bit).

``load_rgb / load_mask / load_labels`` (the pipeline's entry points)
    Read the file bytes once, hash them (sha256), and return the array resized to the working
    resolution -- area interpolation for images, nearest for masks and labels -- through a decode
    cache keyed by ``(sha256, kind, resolution)`` under ``.cache/decode/`` so no stage decodes the
    same file twice.  Cache entries are ``.npz`` files (array + native height/width) written to a
    temp name then renamed (atomic; survive a kill); an unreadable entry is treated as a miss.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import uuid
from pathlib import Path

import cv2
import numpy as np

from pipeline.errors import InputError

SUPPORTED_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
DEFAULT_CACHE_DIR = ".cache/decode"


class BadFileError(InputError):
    """A file that cannot be used (missing, zero-byte, corrupt, unsupported, size mismatch); ``.path`` names it."""

    def __init__(self, path: str | Path, reason: str):
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{path}: {reason}")


# ---------------------------------------------------------------------------------------------------
# Decoding (no resizing, no cache)
# ---------------------------------------------------------------------------------------------------
def read_bytes(path: str | Path) -> bytes:
    """File bytes; InputError naming the file when missing, unreadable, zero-byte or unsupported."""
    p = Path(path)
    if p.suffix.lower() not in SUPPORTED_SUFFIXES:
        raise BadFileError(p, f"unsupported image type {p.suffix or '(no suffix)'!r} "
                              f"(supported: {', '.join(SUPPORTED_SUFFIXES)})")
    if not p.is_file():
        raise BadFileError(p, "file not found")
    try:
        data = p.read_bytes()
    except OSError as e:
        raise BadFileError(p, f"cannot read ({e.strerror or e})") from None
    if not data:
        raise BadFileError(p, "zero-byte file")
    return data


def _decode(data: bytes, path: str | Path) -> np.ndarray:
    arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if arr is None or arr.size == 0:
        raise BadFileError(path, "corrupt or undecodable image")
    return arr


def to_rgb8(arr: np.ndarray, path: str | Path = "<array>") -> np.ndarray:
    """Decoded OpenCV array (grey, BGR, BGRA; 8/16-bit or float) -> RGB uint8 [H, W, 3]."""
    if arr.dtype == np.uint8:
        a8 = arr
    elif arr.dtype == np.uint16:
        a8 = ((arr.astype(np.uint32) + 128) // 257).astype(np.uint8)
    elif arr.dtype.kind == "f":
        a8 = (np.clip(np.nan_to_num(arr), 0, 1) * 255 + 0.5).astype(np.uint8)
    elif arr.dtype.kind in "iu":
        a8 = np.clip(arr, 0, 255).astype(np.uint8)
    else:
        raise BadFileError(path, f"unsupported pixel type {arr.dtype}")
    if a8.ndim == 2:
        return np.repeat(a8[..., None], 3, axis=2)
    if a8.ndim != 3:
        raise BadFileError(path, f"unsupported image shape {arr.shape}")
    ch = a8.shape[2]
    if ch == 1:
        return np.repeat(a8, 3, axis=2)
    if ch == 3:
        return np.ascontiguousarray(a8[..., ::-1])
    if ch == 4:
        return np.ascontiguousarray(a8[..., 2::-1])
    raise BadFileError(path, f"unsupported channel count {ch}")


def read_rgb(path: str | Path) -> np.ndarray:
    """Read any supported image file as RGB uint8 [H, W, 3] at native size (see module docstring)."""
    return to_rgb8(_decode(read_bytes(path), path), path)


def mask_from_array(arr: np.ndarray, threshold: float | None = None) -> np.ndarray:
    """Foreground = max over channels > ``threshold``; ``None`` = auto (> 0 for 0/1 data, else > half range)."""
    a = arr.max(axis=2) if arr.ndim == 3 else arr
    if threshold is None:
        if a.size and a.max() <= 1:
            threshold = 0
        elif a.dtype.kind == "f":
            threshold = 0.5
        else:
            threshold = np.iinfo(a.dtype).max // 2 if a.dtype.kind in "iu" else 0
    return a > threshold


def read_mask(path: str | Path, threshold: float | None = None) -> np.ndarray:
    """Read a mask file as bool [H, W] at native size; InputError naming the file on bad input."""
    return mask_from_array(_decode(read_bytes(path), path), threshold)


def parts_from_colors(rgb: np.ndarray, colors: dict[tuple[int, int, int], int]) -> np.ndarray:
    """Colour-coded part mask (RGB uint8) -> part labels uint8; colours not in the table -> 0."""
    key = (rgb[..., 0].astype(np.uint32) << 16) | (rgb[..., 1].astype(np.uint32) << 8) | rgb[..., 2]
    out = np.zeros(rgb.shape[:2], np.uint8)
    for (r, g, b), label in colors.items():
        out[key == ((r << 16) | (g << 8) | b)] = label
    return out


# ---------------------------------------------------------------------------------------------------
# Resizing
# ---------------------------------------------------------------------------------------------------
def resize_image(img: np.ndarray, size: int) -> np.ndarray:
    """Square working resolution, area interpolation (the paper resizes every image to 384 x 384)."""
    if img.shape[0] == size and img.shape[1] == size:
        return img
    return cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA)


def resize_nearest(lbl: np.ndarray, size: int) -> np.ndarray:
    """Nearest-neighbour resize of a label/mask array (bool or uint8) to size x size."""
    if lbl.shape[0] == size and lbl.shape[1] == size:
        return lbl
    out = cv2.resize(lbl.astype(np.uint8), (size, size), interpolation=cv2.INTER_NEAREST)
    return out.astype(lbl.dtype)


# ---------------------------------------------------------------------------------------------------
# Decode cache
# ---------------------------------------------------------------------------------------------------
class DecodeCache:
    """Content-addressed cache of decoded, resized arrays: ``<root>/<sha[:2]>/<sha>-<kind>-<size>.npz``.

    ``root=None`` disables caching (every call decodes).
    """

    def __init__(self, root: str | Path | None = DEFAULT_CACHE_DIR):
        self.root = Path(root) if root is not None else None
        self.hits = 0
        self.misses = 0

    def path(self, sha: str, kind: str, size: int) -> Path:
        return self.root / sha[:2] / f"{sha}-{kind}-{int(size)}.npz"

    def get(self, sha: str, kind: str, size: int) -> tuple[np.ndarray, tuple[int, int]] | None:
        if self.root is None:
            return None
        p = self.path(sha, kind, size)
        if not p.exists():
            self.misses += 1
            return None
        try:
            with np.load(p) as z:
                arr, hw = z["a"], tuple(int(v) for v in z["hw"])
        except Exception:  # noqa: BLE001 -- a torn or foreign entry is a miss; it is rewritten
            self.misses += 1
            return None
        self.hits += 1
        return arr, hw

    def put(self, sha: str, kind: str, size: int, arr: np.ndarray, native_hw: tuple[int, int]) -> None:
        if self.root is None:
            return
        p = self.path(sha, kind, size)
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp = p.with_name(f".{p.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp.npz")
        try:
            np.savez(tmp, a=arr, hw=np.asarray(native_hw, np.int64))
            os.replace(tmp, p)
        finally:
            if tmp.exists():
                tmp.unlink()


@dataclasses.dataclass
class Loaded:
    array: np.ndarray            # at the working resolution
    sha256: str                  # of the file bytes
    native_hw: tuple[int, int]   # (height, width) of the file


def _load(path, size: int, kind: str, cache: DecodeCache | None, decode) -> Loaded:
    data = read_bytes(path)
    sha = hashlib.sha256(data).hexdigest()
    if cache is not None:
        hit = cache.get(sha, kind, size)
        if hit is not None:
            return Loaded(hit[0], sha, hit[1])
    full = decode(_decode(data, path))
    hw = (int(full.shape[0]), int(full.shape[1]))
    arr = resize_image(full, size) if kind == "rgb" else resize_nearest(full, size)
    if cache is not None:
        cache.put(sha, kind, size, arr, hw)
    return Loaded(arr, sha, hw)


def load_rgb(path, size: int, cache: DecodeCache | None = None) -> Loaded:
    """RGB uint8 [size, size, 3] (area interpolation), its sha256 and native size; cached."""
    return _load(path, size, "rgb", cache, lambda a: to_rgb8(a, path))


def load_mask(path, size: int, cache: DecodeCache | None = None, threshold: float | None = None) -> Loaded:
    """bool [size, size] (nearest), thresholded as :func:`mask_from_array`; cached per threshold."""
    kind = "maskauto" if threshold is None else f"mask{threshold}"
    return _load(path, size, kind, cache, lambda a: mask_from_array(a, threshold))


def load_labels(path, size: int, cache: DecodeCache | None = None,
                colors: dict[tuple[int, int, int], int] | None = None) -> Loaded:
    """Part labels uint8 [size, size] (nearest): a label image, or a colour-coded one mapped by ``colors``."""
    if colors:
        digest = hashlib.sha256(repr(sorted(colors.items())).encode()).hexdigest()[:10]
        return _load(path, size, f"parts{digest}", cache,
                     lambda a: parts_from_colors(to_rgb8(a, path), colors))

    def as_labels(a):
        if a.ndim == 3:
            a = a[..., 0]
        if a.dtype != np.uint8:
            a = np.clip(a, 0, 255).astype(np.uint8)
        return a

    return _load(path, size, "labels", cache, as_labels)
