"""One image/mask loader for every source, with a content-addressed decode cache.

``read_rgb(path)``
    Any supported file (png, jpg/jpeg, tif/tiff, bmp) -> RGB uint8 [H, W, 3] at native size.
    Grey is replicated to three channels; RGBA drops alpha (spacecraft imagery has no meaningful
    transparency; compositing on black would equal dropping it for premultiplied black
    backgrounds); 16-bit is scaled to 8-bit by rounding ``v / 257`` (the exact 65535 -> 255 map);
    float images are taken as [0, 1] and clipped.  OpenCV decodes BGR, so channels are reversed.
    Raises :class:`InputError` naming the file for a missing, zero-byte, corrupt or unsupported file,
    a broken symbolic link or a directory.

The pixel limit (every reader below, ``max_pixels``; params ``data.max_pixels``, default
:data:`DEFAULT_MAX_PIXELS` = 2**26, an 8192 x 8192 image)
    Width and height are read from the file header (:func:`pipeline.datasets.image_header.header_size`)
    before anything is decoded or looked up in the cache; above ``max_pixels`` the file is a bad file
    (:class:`BadFileError` naming it, its size and the option), so a few-megabyte PNG whose header
    declares 30,000 x 30,000 pixels never reaches the decoder.  Bytes that carry no PNG, JPEG, TIFF or
    BMP header are "corrupt or undecodable" before decoding too.

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
from pipeline.errors import MAX_PIXELS, InputError, Option, literal
from pipeline.params import PAPER

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
    in the caller's terms (:class:`pipeline.errors.InputError`): ``{path}: {reason} ({fix})``."""

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


def read_rgb(path: str | Path, *, max_pixels: int | None = None) -> np.ndarray:
    """Read any supported image file as RGB uint8 [H, W, 3] at native size (see module docstring);
    refused before decoding above ``max_pixels`` (None: :data:`DEFAULT_MAX_PIXELS`)."""
    return to_rgb8(_decode(read_image_bytes(path, max_pixels), path), path)


_warned: set[str] = set()


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
def resize_image(img: np.ndarray, size: int) -> np.ndarray:
    """Square working resolution, area interpolation (the paper resizes every image to 384 x 384)."""
    if img.shape[0] == size and img.shape[1] == size:
        return img
    return cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA)


def probs_to_size(probs: np.ndarray, height: int, width: int) -> np.ndarray:
    """Bilinear resize of a probability map [R,R] back to the original [height, width] (values stay in
    [0,1]): the way back from :func:`resize_image`'s working resolution."""
    if probs.shape == (height, width):
        return probs
    return np.clip(cv2.resize(probs, (width, height), interpolation=cv2.INTER_LINEAR), 0.0, 1.0)


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


def _load(path, size: int, kind: str, cache: DecodeCache | None, decode, max_pixels: int | None) -> Loaded:
    """``decode(array) -> array`` or ``(array, note)``; a note (multi-valued mask) is cached with the
    entry and warned about once per file, whether decoded now or read from the cache.  The pixel limit
    is checked on the header first, so a cached entry made under a higher limit is refused too."""
    data = read_image_bytes(path, max_pixels)
    sha = hashlib.sha256(data).hexdigest()
    if cache is not None:
        hit = cache.get_entry(sha, kind, size)
        if hit is not None:
            warn_mask_once(path, hit[2])
            return Loaded(hit[0], sha, hit[1])
    full = decode(_decode(data, path))
    full, note = full if isinstance(full, tuple) else (full, None)
    warn_mask_once(path, note)
    hw = (int(full.shape[0]), int(full.shape[1]))
    arr = resize_image(full, size) if kind == "rgb" else resize_nearest(full, size)
    if cache is not None:
        cache.put(sha, kind, size, arr, hw, note)
    return Loaded(arr, sha, hw)


def load_rgb(path, size: int, cache: DecodeCache | None = None, *, max_pixels: int | None = None) -> Loaded:
    """RGB uint8 [size, size, 3] (area interpolation), its sha256 and native size; cached.  Refused
    above ``max_pixels`` (None: :data:`DEFAULT_MAX_PIXELS`) before decoding."""
    return _load(path, size, "rgb", cache, lambda a: to_rgb8(a, path), max_pixels)


def mask_kind(threshold: float | None) -> str:
    """Decode-cache kind of a mask read with ``threshold`` (``maskgt0`` for the default rule; the old
    ``maskauto`` entries, made under an earlier rule, are never read)."""
    return "maskgt0" if threshold is None else f"mask{threshold}"


def load_mask(path, size: int, cache: DecodeCache | None = None, threshold: float | None = None, *,
              max_pixels: int | None = None) -> Loaded:
    """bool [size, size] (nearest), binarised by :func:`binarize_mask`; cached per threshold."""
    return _load(path, size, mask_kind(threshold), cache, lambda a: binarize_mask(a, threshold), max_pixels)


def load_labels(path, size: int, cache: DecodeCache | None = None,
                colors: dict | ColorTable | None = None, *, max_pixels: int | None = None) -> Loaded:
    """Part labels uint8 [size, size] (nearest): a label image, or a colour-coded one mapped by ``colors``
    (:func:`parts_from_colors`: a colour outside the table refuses the file)."""
    if colors:
        table = as_color_table(colors)
        return _load(path, size, table.kind(), cache,
                     lambda a: parts_from_colors(to_rgb8(a, path), table, path), max_pixels)

    def as_labels(a):
        if a.ndim == 3:
            a = a[..., 0]
        if a.dtype != np.uint8:
            a = np.clip(a, 0, 255).astype(np.uint8)
        return a

    return _load(path, size, "labels", cache, as_labels, max_pixels)
