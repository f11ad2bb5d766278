"""Training data that stays on disk: rows of Zarr arrays read per batch (:class:`RowSource`), one batch ahead
(:func:`prefetch`), so a run's memory does not grow with the number of images.
"""

from __future__ import annotations

import queue
import threading
from typing import Callable, Iterable, Iterator, Sequence

import numpy as np

from pipeline.artifacts.store import read_chunk_rows

__all__ = ["RowSource", "LazyRows", "MappedRows", "select_rows", "row_means", "spill_rows", "prefetch"]


class RowSource:
    """Rows read only when indexed: ``x[i]`` reads rows, ``x.select(sel)`` narrows without reading, ``np.asarray(x)``
    reads all.
    """

    dtype: np.dtype

    @property
    def shape(self) -> tuple[int, ...]:
        raise NotImplementedError

    @property
    def ndim(self) -> int:
        return len(self.shape)

    def __len__(self) -> int:
        return self.shape[0]

    def select(self, sel) -> "RowSource":
        raise NotImplementedError

    def read(self, key) -> np.ndarray:
        """The rows ``key`` (an index array or slice over this subset), as ``dtype``."""
        raise NotImplementedError

    def __getitem__(self, key) -> np.ndarray:
        if isinstance(key, (int, np.integer)):
            return self[np.array([key])][0]
        return self.read(key)

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        out = self[np.arange(len(self))]
        return out if dtype is None else out.astype(dtype, copy=False)


class LazyRows(RowSource):
    """Rows ``rows`` (unique) of the Zarr array ``arr``, as ``dtype`` when read."""

    def __init__(self, arr, rows: np.ndarray, dtype=None):
        self.arr = arr
        self.rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        self.dtype = np.dtype(dtype if dtype is not None else arr.dtype)

    @property
    def shape(self) -> tuple[int, ...]:
        return (len(self.rows),) + tuple(self.arr.shape[1:])

    def select(self, sel) -> "LazyRows":
        return LazyRows(self.arr, self.rows[sel], self.dtype)

    def read(self, key) -> np.ndarray:
        picked = self.rows[key]
        if picked.size == 0:
            return np.zeros((0,) + self.shape[1:], dtype=self.dtype)
        return read_chunk_rows(self.arr, picked).astype(self.dtype, copy=False)


class MappedRows(RowSource):
    """``fn`` of the same rows of several row sources, per read (``fn`` must work row by row): a target derived from
    stored arrays, such as the AFS control's fused mask.
    """

    def __init__(self, fn: Callable[..., np.ndarray], sources: Sequence[RowSource], dtype, shape: tuple[int, ...]):
        self.fn = fn
        self.sources = tuple(sources)
        self.dtype = np.dtype(dtype)
        self._row_shape = tuple(shape)
        if len({len(s) for s in self.sources}) != 1:
            raise ValueError("MappedRows: sources of different lengths")

    @property
    def shape(self) -> tuple[int, ...]:
        return (len(self.sources[0]),) + self._row_shape

    def select(self, sel) -> "MappedRows":
        return MappedRows(self.fn, [s.select(sel) for s in self.sources], self.dtype, self._row_shape)

    def read(self, key) -> np.ndarray:
        parts = [s[key] for s in self.sources]
        if len(parts[0]) == 0:
            return np.zeros((0,) + self._row_shape, dtype=self.dtype)
        return np.asarray(self.fn(*parts)).astype(self.dtype, copy=False)


def select_rows(x, sel):
    """``x[sel]`` for an array, ``x.select(sel)`` (nothing read) for a :class:`RowSource`."""
    return x.select(sel) if isinstance(x, RowSource) else x[sel]


def row_means(x, block: int = 64) -> np.ndarray:
    """Each row's mean as float32 (a mask's foreground fraction), reading ``block`` rows at a time."""
    out = np.empty(len(x), dtype=np.float32)
    for s in range(0, len(x), block):
        part = np.asarray(x[s:s + block])
        out[s:s + len(part)] = part.reshape(len(part), -1).mean(1)
    return out


def spill_rows(path, blocks: Iterable[np.ndarray], shape: tuple[int, ...], dtype) -> LazyRows:
    """Row blocks written to a scratch Zarr array at ``path`` (the caller removes it), read as :class:`LazyRows`."""
    import zarr

    shape = tuple(int(v) for v in shape)
    arr = zarr.create_array(store=str(path), shape=shape, chunks=(1,) + shape[1:], dtype=np.dtype(dtype))
    start = 0
    for block in blocks:
        arr[start:start + len(block)] = block
        start += len(block)
    if start != shape[0]:
        raise ValueError(f"spill_rows: {start} rows written, {shape[0]} expected")
    return LazyRows(arr, np.arange(shape[0]))


_DONE = object()


def prefetch(items: Iterable, depth: int = 2) -> Iterator:
    """``items`` in order, produced by a thread up to ``depth`` ahead (its exception raised here; closing stops it)."""
    q: queue.Queue = queue.Queue(maxsize=max(1, depth))
    stop = threading.Event()

    def produce() -> None:
        try:
            for item in items:
                q.put((True, item))  # a full queue blocks until the consumer (or its closing drain) takes one
                if stop.is_set():
                    return
            q.put((True, _DONE))
        except BaseException as e:  # handed to the consumer
            q.put((False, e))

    t = threading.Thread(target=produce, name="prefetch", daemon=True)
    t.start()
    try:
        while True:
            ok, item = q.get()
            if not ok:
                raise item
            if item is _DONE:
                return
            yield item
    finally:
        stop.set()
        while t.is_alive():  # unblock a producer waiting on a full queue
            try:
                q.get_nowait()
            except queue.Empty:
                pass
            t.join(timeout=0.05)
