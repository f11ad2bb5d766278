"""Content-addressed cache of teacher answers on any fsspec location: one file per (image, prompt, view).

Each is ``<teacher.cache_dir>/v2/<key[:2]>/<key>.tce``, keyed by the sha256 of {image sha256, teacher
fingerprint, prompt, view} (docs/decisions.md, "The teacher cache").
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import logging
import os
import struct
import uuid
from pathlib import Path

import numpy as np
from fsspec.core import url_to_fs
from fsspec.implementations.local import LocalFileSystem

from pipeline.artifacts.lineage import canonical_json

__all__ = ["MAGIC", "SUFFIX", "LAYOUT_VERSION", "entry_key", "encode_entry", "CorruptEntry", "decode_entry",
           "CacheStats", "TeacherCache"]

log = logging.getLogger(__name__)

#: the first bytes of an entry (its format's version)
MAGIC = b"GDTCE02\n"
#: an entry's file suffix
SUFFIX = ".tce"
#: the cache's folder under ``teacher.cache_dir``: a new entry layout gets a new one
LAYOUT_VERSION = "v2"
_KEY_BYTES = 32
_HEADER = struct.Struct("<IIf")


def entry_key(image_sha256: str, teacher_fingerprint: str, prompt: str, view: str = "identity") -> str:
    """Return the key of one (image, teacher, prompt, view) answer.

    Parameters
    ----------
    image_sha256 : str
        The image's pixel sha256.
    teacher_fingerprint : str
        :func:`pipeline.teachers.teacher_fingerprint`.
    prompt : str
        The prompt.
    view : str, optional
        One of :data:`pipeline.teachers.base.VIEWS` (default ``identity``).

    Returns
    -------
    str
        The sha256 hex digest of their canonical JSON.
    """
    payload = canonical_json({"image": image_sha256, "teacher": teacher_fingerprint,
                              "prompt": prompt, "view": view})
    return hashlib.sha256(payload.encode()).hexdigest()


def _key_bytes(key: str) -> bytes:
    """Return ``key``'s 32 bytes; ValueError when it is no sha256 hex digest."""
    try:
        raw = bytes.fromhex(key)
    except ValueError:
        raw = b""
    if len(raw) != _KEY_BYTES:
        raise ValueError(f"cache key must be a sha256 hex digest, got {key!r}")
    return raw


def encode_entry(mask: np.ndarray, score: float, key: str) -> bytes:
    """Serialise one answer with its own ``key`` and a checksum.

    Parameters
    ----------
    mask : array_like
        bool [H,W].
    score : float
        The answer's score.
    key : str
        Its key (:func:`entry_key`), stored in the entry.

    Returns
    -------
    bytes
        :data:`MAGIC`, the payload's sha256, then the key, (H, W, score) and the mask's packed bits.

    Raises
    ------
    ValueError
        The mask is not 2-D, or ``key`` is no sha256 hex digest.
    """
    mask = np.asarray(mask, dtype=bool)
    if mask.ndim != 2:
        raise ValueError(f"cache entry mask must be 2-D, got shape {mask.shape}")
    payload = (_key_bytes(key) + _HEADER.pack(mask.shape[0], mask.shape[1], float(score))
               + np.packbits(mask, axis=None).tobytes())
    return MAGIC + hashlib.sha256(payload).digest() + payload


class CorruptEntry(ValueError):
    """A cache entry whose bytes do not match its checksum or layout."""


def decode_entry(data: bytes, key: str | None = None) -> tuple[np.ndarray, float]:
    """Read one answer: the inverse of :func:`encode_entry`.

    Parameters
    ----------
    data : bytes
        An entry's bytes.
    key : str, optional
        The key it must hold; None: not checked.

    Returns
    -------
    tuple of (numpy.ndarray, float)
        The mask bool [H,W] and the score.

    Raises
    ------
    CorruptEntry
        Any mismatch: the magic, the length, the checksum, the mask's size, or a stored key other than ``key``.
    """
    if len(data) < len(MAGIC) + 32 + _KEY_BYTES + _HEADER.size or not data.startswith(MAGIC):
        raise CorruptEntry("bad magic or truncated header")
    digest, payload = data[len(MAGIC):len(MAGIC) + 32], data[len(MAGIC) + 32:]
    if hashlib.sha256(payload).digest() != digest:
        raise CorruptEntry("checksum mismatch")
    stored = payload[:_KEY_BYTES].hex()
    if key is not None and stored != key:
        raise CorruptEntry(f"entry holds the answer for key {stored[:12]}..., not {key[:12]}...")
    h, w, score = _HEADER.unpack_from(payload, _KEY_BYTES)
    bits = np.frombuffer(payload, dtype=np.uint8, offset=_KEY_BYTES + _HEADER.size)
    if bits.size != (h * w + 7) // 8:
        raise CorruptEntry("mask size does not match header")
    mask = np.unpackbits(bits, count=h * w).astype(bool).reshape(h, w)
    return mask, float(score)


@dataclasses.dataclass
class CacheStats:
    """What a :class:`TeacherCache` did.

    Attributes
    ----------
    hits : int
        Entries read.
    misses : int
        Entries asked for and absent (or corrupt).
    corrupt : int
        Corrupt entries, removed.
    written : int
        Entries written.
    """

    hits: int = 0
    misses: int = 0
    corrupt: int = 0
    written: int = 0


class TeacherCache:
    """Answers of one teacher fingerprint under ``root`` (a local path or an fsspec URL).

    Parameters
    ----------
    root : str or Path
        ``teacher.cache_dir``: a local path or an fsspec URL.
    teacher_fingerprint : str
        :func:`pipeline.teachers.teacher_fingerprint`.

    Attributes
    ----------
    root : str
        ``root`` as given.
    fs : fsspec.AbstractFileSystem
        Its file system.
    local : bool
        Whether it is a local folder.
    teacher_fingerprint : str
        The teacher's fingerprint.
    stats : CacheStats
        What the cache did.
    """

    def __init__(self, root: str | Path, teacher_fingerprint: str):
        self.root = str(root)
        self.fs, self._base = url_to_fs(self.root)
        self.local = isinstance(self.fs, LocalFileSystem)
        self.teacher_fingerprint = teacher_fingerprint
        self.stats = CacheStats()

    def key(self, image_sha256: str, prompt: str, view: str = "identity") -> str:
        """Return the key of this teacher's answer (:func:`entry_key`).

        Parameters
        ----------
        image_sha256 : str
            The image's pixel sha256.
        prompt : str
            The prompt.
        view : str, optional
            One of :data:`pipeline.teachers.base.VIEWS` (default ``identity``).

        Returns
        -------
        str
            The key.
        """
        return entry_key(image_sha256, self.teacher_fingerprint, prompt, view)

    @property
    def location(self) -> str:
        """``root`` as another process (a Ray worker elsewhere) must name it: absolute when local."""
        return self._base if self.local else self.root

    def _layout(self) -> str:
        """Return the folder of this layout's entries (:data:`LAYOUT_VERSION`)."""
        return f"{self._base.rstrip('/')}/{LAYOUT_VERSION}"

    def path(self, key: str) -> Path | str:
        """Return where ``key``'s entry lives.

        Parameters
        ----------
        key : str
            An entry key.

        Returns
        -------
        Path or str
            A :class:`~pathlib.Path` for a local cache, else the store's path.
        """
        p = f"{self._layout()}/{key[:2]}/{key}{SUFFIX}"
        return Path(p) if self.local else p

    def listed(self) -> set[str]:
        """List the keys that have an entry, from one recursive listing (names only; nothing is read).

        Returns
        -------
        set of str
            The keys; empty when the cache has no folder yet.
        """
        try:
            names = self.fs.find(self._layout())
        except FileNotFoundError:
            return set()
        bases = (name.rsplit("/", 1)[-1] for name in names)
        return {b[:-len(SUFFIX)] for b in bases if b.endswith(SUFFIX) and not b.startswith(".")}

    def get(self, key: str) -> tuple[np.ndarray, float] | None:
        """Read an answer; a corrupt entry is reported (a warning), removed and missed.

        Parameters
        ----------
        key : str
            An entry key.

        Returns
        -------
        tuple of (numpy.ndarray, float) or None
            The cached (mask, score), or None on a miss.
        """
        p = self.path(key)
        try:
            data = self.fs.cat_file(str(p))
        except FileNotFoundError:
            self.stats.misses += 1
            return None
        try:
            out = decode_entry(data, key)
        except CorruptEntry as e:
            log.warning("teacher cache: corrupt entry %s (%s); it will be recomputed", p, e)
            self.stats.corrupt += 1
            self.stats.misses += 1
            with contextlib.suppress(FileNotFoundError):
                self.fs.rm_file(str(p))
            return None
        self.stats.hits += 1
        return out

    def put(self, key: str, mask: np.ndarray, score: float) -> None:
        """Write one entry atomically: temp file + rename locally, a single PUT on a remote store.

        Parameters
        ----------
        key : str
            Its key (:meth:`key`).
        mask : numpy.ndarray
            bool [H,W].
        score : float
            The answer's score.
        """
        p = self.path(key)
        data = encode_entry(mask, score, key)
        if self.local:
            p.parent.mkdir(parents=True, exist_ok=True)
            tmp = p.with_name(f".{p.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp")
            try:
                tmp.write_bytes(data)
                os.replace(tmp, p)
            finally:
                if tmp.exists():
                    tmp.unlink()
        else:
            self.fs.pipe_file(p, data)
        self.stats.written += 1
