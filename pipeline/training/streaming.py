"""Training data that stays on disk, so a run's memory does not grow with the number of images.

Rows of Zarr arrays are read per batch (:class:`RowSource`), one batch ahead (:func:`prefetch`).
"""

from __future__ import annotations

import queue
import threading
from typing import Callable, Iterable, Iterator, Sequence

import numpy as np

from pipeline.artifacts.store import read_chunk_rows

__all__ = ["RowSource", "LazyRows", "MappedRows", "select_rows", "row_means", "spill_rows", "prefetch"]


class RowSource:
    """Rows read only when indexed: the base of the row sources.

    ``x[i]`` reads rows, ``x.select(sel)`` narrows without reading, ``np.asarray(x)`` reads all.  A subclass
    defines ``dtype``, :attr:`shape`, :meth:`select` and :meth:`read`.
    """

    dtype: np.dtype

    @property
    def shape(self) -> tuple[int, ...]:
        """The shape the rows have when read: ``(rows, ...)``.

        Raises
        ------
        NotImplementedError
            In the base class.
        """
        raise NotImplementedError

    @property
    def ndim(self) -> int:
        """The number of dimensions of :attr:`shape`."""
        return len(self.shape)

    def __len__(self) -> int:  # noqa: D105 -- the rows
        return self.shape[0]

    def select(self, sel) -> "RowSource":
        """Narrow to the rows ``sel``, reading nothing.

        Parameters
        ----------
        sel : array_like or slice
            Row positions within this source.

        Raises
        ------
        NotImplementedError
            In the base class; a subclass returns a row source of its kind.
        """
        raise NotImplementedError

    def read(self, key) -> np.ndarray:
        """Read the rows ``key`` as ``dtype``.

        Parameters
        ----------
        key : array_like or slice
            An index array or slice over this source's rows.

        Raises
        ------
        NotImplementedError
            In the base class; a subclass returns the rows.
        """
        raise NotImplementedError

    def __getitem__(self, key) -> np.ndarray:  # noqa: D105 -- one row by an int, else :meth:`read`
        if isinstance(key, (int, np.integer)):
            return self[np.array([key])][0]
        return self.read(key)

    def __array__(self, dtype=None, copy=None) -> np.ndarray:  # noqa: D105 -- every row read
        out = self[np.arange(len(self))]
        return out if dtype is None else out.astype(dtype, copy=False)


class LazyRows(RowSource):
    """Some rows of a Zarr array, read when indexed.

    Parameters
    ----------
    arr : zarr array or numpy.ndarray
        The stored array [N, ...].
    rows : numpy.ndarray
        Its rows this source holds, unique, in their order here.
    dtype : numpy.dtype, optional
        What the rows are read as; None: ``arr``'s dtype.
    """

    def __init__(self, arr, rows: np.ndarray, dtype=None):
        self.arr = arr
        self.rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        self.dtype = np.dtype(dtype if dtype is not None else arr.dtype)

    @property
    def shape(self) -> tuple[int, ...]:
        """``(len(rows),) + arr.shape[1:]``."""
        return (len(self.rows),) + tuple(self.arr.shape[1:])

    def select(self, sel) -> "LazyRows":
        """Narrow to the rows ``sel``, reading nothing.

        Parameters
        ----------
        sel : array_like or slice
            Row positions within this source.

        Returns
        -------
        LazyRows
            The same array, fewer rows.
        """
        return LazyRows(self.arr, self.rows[sel], self.dtype)

    def read(self, key) -> np.ndarray:
        """Read the rows ``key`` as ``dtype``, one slice per contiguous run of stored rows.

        Parameters
        ----------
        key : array_like or slice
            An index array or slice over this source's rows.

        Returns
        -------
        numpy.ndarray
            The rows, in ``key``'s order.
        """
        picked = self.rows[key]
        if picked.size == 0:
            return np.zeros((0,) + self.shape[1:], dtype=self.dtype)
        return read_chunk_rows(self.arr, picked).astype(self.dtype, copy=False)


class MappedRows(RowSource):
    """A row source computed per read from the same rows of several row sources.

    A target derived from stored arrays, such as the AFS control's fused mask.

    Parameters
    ----------
    fn : callable
        ``fn(*rows of each source) -> rows``; it must work row by row.
    sources : sequence of RowSource
        Sources of one length.
    dtype : numpy.dtype
        What the rows are read as.
    shape : tuple of int
        The shape of one row of ``fn``'s result.
    """

    def __init__(self, fn: Callable[..., np.ndarray], sources: Sequence[RowSource], dtype, shape: tuple[int, ...]):
        """Hold the sources, which must have one length.

        Raises
        ------
        ValueError
            Sources of different lengths.
        """
        self.fn = fn
        self.sources = tuple(sources)
        self.dtype = np.dtype(dtype)
        self._row_shape = tuple(shape)
        if len({len(s) for s in self.sources}) != 1:
            raise ValueError("MappedRows: sources of different lengths")

    @property
    def shape(self) -> tuple[int, ...]:
        """``(rows,) + shape`` of one row."""
        return (len(self.sources[0]),) + self._row_shape

    def select(self, sel) -> "MappedRows":
        """Narrow every source to the rows ``sel``, reading nothing.

        Parameters
        ----------
        sel : array_like or slice
            Row positions within this source.

        Returns
        -------
        MappedRows
            The same ``fn`` over the narrowed sources.
        """
        return MappedRows(self.fn, [s.select(sel) for s in self.sources], self.dtype, self._row_shape)

    def read(self, key) -> np.ndarray:
        """Read the rows ``key`` of every source and apply ``fn``.

        Parameters
        ----------
        key : array_like or slice
            An index array or slice over this source's rows.

        Returns
        -------
        numpy.ndarray
            ``fn``'s rows as ``dtype``.
        """
        parts = [s[key] for s in self.sources]
        if len(parts[0]) == 0:
            return np.zeros((0,) + self._row_shape, dtype=self.dtype)
        return np.asarray(self.fn(*parts)).astype(self.dtype, copy=False)


def select_rows(x, sel):
    """Select rows of an array or a row source: ``x[sel]``, or ``x.select(sel)`` (nothing read).

    Parameters
    ----------
    x : numpy.ndarray or RowSource
        The rows.
    sel : array_like or slice
        Row positions.

    Returns
    -------
    numpy.ndarray or RowSource
        Of ``x``'s kind.
    """
    return x.select(sel) if isinstance(x, RowSource) else x[sel]


def row_means(x, block: int = 64) -> np.ndarray:
    """Average each row (a mask's foreground fraction), reading ``block`` rows at a time.

    Parameters
    ----------
    x : numpy.ndarray or RowSource
        Rows [N, ...].
    block : int
        Rows read at a time.

    Returns
    -------
    numpy.ndarray
        float32 [N].
    """
    out = np.empty(len(x), dtype=np.float32)
    for s in range(0, len(x), block):
        part = np.asarray(x[s:s + block])
        out[s:s + len(part)] = part.reshape(len(part), -1).mean(1)
    return out


def spill_rows(path, blocks: Iterable[np.ndarray], shape: tuple[int, ...], dtype) -> LazyRows:
    """Write row blocks to a scratch Zarr array, read back as :class:`LazyRows`.

    Parameters
    ----------
    path : str or Path
        Where the array is written; the caller removes it.
    blocks : iterable of numpy.ndarray
        Consecutive row blocks, ``shape[0]`` rows in all.
    shape : tuple of int
        The array's shape.
    dtype : numpy.dtype
        The array's dtype.

    Returns
    -------
    LazyRows
        Every row of the array.

    Raises
    ------
    ValueError
        The blocks hold another number of rows than ``shape[0]``.
    """
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
    """Iterate ``items`` in order, produced by a thread up to ``depth`` ahead.

    The producer's exception is raised here; closing the generator stops the producer.

    Parameters
    ----------
    items : iterable
        What to produce (batches read from disk).
    depth : int
        How many items may wait ready (at least 1).

    Yields
    ------
    object
        Each item of ``items``.
    """
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
