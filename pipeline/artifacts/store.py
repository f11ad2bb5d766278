"""Write and read artifacts: Zarr v3 groups, Parquet tables and folders, atomic and checksummed.

Writers replace the artifact atomically (nothing is at the final path until the write succeeds) and record
its :class:`pipeline.artifacts.lineage.Meta`; readers validate the schema and raise a one-line
:class:`ArtifactError` naming the path (layout: docs/artifacts.md).  Nothing read executes code.
"""

from __future__ import annotations

import contextlib
import json
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from pipeline.artifacts.atomic import atomic_path
from pipeline.artifacts.lineage import PROGRAM, Meta
from pipeline.artifacts.schemas import check_kind, get_schema, missing_files
from pipeline.catalog import META_FILE, TRAINING_LOG_FILE
from pipeline.runtime.errors import ArtifactError

__all__ = ["SHARD_IMAGES", "ZarrWriter", "write_zarr", "write_parquet", "artifact_dir", "Artifact", "ZarrArtifact",
           "VerifiedArray", "TableArtifact", "DirArtifact", "open_artifact", "row_runs", "read_chunk_rows"]

META_KEY = PROGRAM
CHUNKS_KEY = "geodistill_chunk_files"  # array -> number of chunk files that must exist
#: images per shard file of a Zarr array (:class:`ZarrWriter`)
SHARD_IMAGES = 256


def _compressor(dtype):
    """Blosc/zstd (masks bit-shuffled, floats byte-shuffled at a fast level), then a CRC32C checksum per chunk."""
    from zarr.codecs import BloscCodec, Crc32cCodec

    if np.dtype(dtype).kind == "f":
        return [BloscCodec(cname="zstd", clevel=1, shuffle="shuffle"), Crc32cCodec()]
    return [BloscCodec(cname="zstd", clevel=3, shuffle="bitshuffle"), Crc32cCodec()]


def _expected_chunk_files(arr) -> int:
    """Count the chunk (or shard) files a fully written array has: every one is written, empty or not."""
    n = 1
    for size, c in zip(arr.shape, arr.shards or arr.chunks):
        n *= -(-size // c) if size else 0
    return n


class ZarrWriter:
    """Streamed, atomic writer of a Zarr v3 group.

    Use as a context manager: ``create`` arrays, ``write`` rows, fill ``attrs``.  Rows are buffered per shard;
    every chunk file is written, empty or not, and their number recorded, so a missing file is detected on
    read.  Nothing is at the final path until ``__exit__`` succeeds; on failure the temporary folder goes.

    Parameters
    ----------
    path : str or Path
        The group's final path.
    meta : pipeline.artifacts.lineage.Meta
        Its metadata; ``meta.schema`` must be a Zarr schema.
    shard_images : int, optional
        Images per shard file (default :data:`SHARD_IMAGES`).

    Raises
    ------
    ArtifactError
        On exit, when an array the schema requires was not created.
    """

    def __init__(self, path: str | Path, meta: Meta, shard_images: int = SHARD_IMAGES):
        self.path = Path(path)
        self.meta = meta
        self.schema = check_kind(meta.schema, "zarr")
        self.shard_images = shard_images
        self.attrs: dict[str, Any] = {}
        self._arrays: dict[str, Any] = {}
        self._buffers: dict[str, dict[int, np.ndarray]] = {}

    def __enter__(self) -> ZarrWriter:
        """Open the temporary group."""
        import zarr

        self._ctx = atomic_path(self.path, is_dir=True)
        self._group = zarr.open_group(store=str(self._ctx.__enter__()), mode="w", zarr_format=3)
        return self

    def create(self, name: str, shape: tuple[int, ...], dtype, fill_value=0) -> None:
        """Create array ``name`` (chunks of one image, shards of ``shard_images``).

        Parameters
        ----------
        name : str
            The array's name.
        shape : tuple of int
            Its shape; axis 0 is the image axis.
        dtype : numpy.dtype or type
            Its dtype.
        fill_value : scalar, optional
            Fill of unwritten entries (default 0).
        """
        shape = tuple(int(s) for s in shape)
        n = max(shape[0], 1) if shape else 1
        kw = {}
        if len(shape) > 1 and shape[0] > 0:
            kw["shards"] = (min(self.shard_images, n), *shape[1:])
        # write_empty_chunks: every chunk exists on disk, so a missing file is detectable (never read as zeros)
        self._arrays[name] = self._group.create_array(
            name=name, shape=shape, chunks=(1, *shape[1:]) if len(shape) > 1 else (min(n, 65536),),
            dtype=np.dtype(dtype), compressors=_compressor(dtype), fill_value=fill_value,
            config={"write_empty_chunks": True}, **kw)
        self._buffers[name] = {}

    def write(self, name: str, index: int, value: np.ndarray) -> None:
        """Write row ``index`` of array ``name``, buffered until its shard is complete.

        Parameters
        ----------
        name : str
            A created array.
        index : int
            The row (image) index.
        value : array_like
            The row, cast to the array's dtype.
        """
        arr, buf = self._arrays[name], self._buffers[name]
        buf[int(index)] = np.asarray(value, dtype=arr.dtype)
        if arr.ndim == 1:
            return
        start = int(index) // self.shard_images * self.shard_images
        stop = min(start + self.shard_images, arr.shape[0])
        if all(i in buf for i in range(start, stop)):
            arr[start:stop] = np.stack([buf.pop(i) for i in range(start, stop)])

    def write_all(self, name: str, value: np.ndarray) -> None:
        """Create array ``name`` from an in-memory array and write it whole.

        Parameters
        ----------
        name : str
            The array's name.
        value : array_like
            Its content.
        """
        value = np.asarray(value)
        self.create(name, value.shape, value.dtype)
        if value.size:
            self._arrays[name][...] = value

    def _flush(self) -> None:
        for name, arr in self._arrays.items():
            buf = self._buffers[name]
            if not buf:
                continue
            if arr.ndim == 1:
                idx = np.fromiter(buf.keys(), dtype=np.int64)
                full = arr[...] if len(idx) < arr.shape[0] else np.zeros(arr.shape, arr.dtype)
                full[idx] = np.array([buf[i] for i in idx.tolist()], dtype=arr.dtype)
                arr[...] = full
                buf.clear()
            else:
                for i in sorted(buf):
                    arr[i] = buf.pop(i)

    def __exit__(self, exc_type, exc, tb):
        """Flush the buffers, check the schema, record the attributes and move the group into place.

        Raises
        ------
        ArtifactError
            An array the schema requires was not created.
        """
        try:
            if exc_type is None:
                self._flush()
                missing = set(self.schema.arrays) - set(self._arrays)
                if missing:
                    raise ArtifactError(f"{self.path}: schema {self.meta.schema!r} needs arrays {sorted(missing)}")
                chunk_files = {n: _expected_chunk_files(a) for n, a in self._arrays.items()}
                self._group.attrs.update({**self.attrs, CHUNKS_KEY: chunk_files, META_KEY: self.meta.to_dict()})
        except BaseException as e:  # the temp dir must go, whatever failed
            self._ctx.__exit__(type(e), e, e.__traceback__)
            raise
        return self._ctx.__exit__(exc_type, exc, tb)


def write_zarr(path: str | Path, arrays: Mapping[str, np.ndarray], meta: Meta,
               attrs: Mapping[str, Any] | None = None) -> Path:
    """Write in-memory arrays as one atomic, fingerprinted Zarr v3 group.

    Parameters
    ----------
    path : str or Path
        The group's path, replaced atomically.
    arrays : mapping of str to numpy.ndarray
        Array name -> content.
    meta : pipeline.artifacts.lineage.Meta
        Its metadata (a Zarr schema).
    attrs : mapping, optional
        Extra group attributes.

    Returns
    -------
    Path
        ``path``.
    """
    with ZarrWriter(path, meta) as w:
        for name, value in arrays.items():
            w.write_all(name, value)
        w.attrs.update(attrs or {})
    return Path(path)


def write_parquet(path: str | Path, table, meta: Meta) -> Path:
    """Write a table atomically as Parquet (zstd, page checksums) with its metadata in the schema.

    Parameters
    ----------
    path : str or Path
        The file's path, replaced atomically.
    table : pandas.DataFrame or pyarrow.Table
        The table (a DataFrame's index is not written).
    meta : pipeline.artifacts.lineage.Meta
        Its metadata (a Parquet schema).

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    ArtifactError
        The table lacks a column the schema requires.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    schema = check_kind(meta.schema, "parquet")
    if not isinstance(table, pa.Table):
        table = pa.Table.from_pandas(table, preserve_index=False)
    missing = [c for c in schema.columns if c not in table.column_names]
    if missing:
        raise ArtifactError(f"{path}: schema {meta.schema!r} needs columns {missing}")
    md = {**(table.schema.metadata or {}), META_KEY.encode(): json.dumps(meta.to_dict()).encode()}
    with atomic_path(path) as tmp:
        # page checksums (CRC32): verified on every read, so a flipped byte is an error, not bad data
        pq.write_table(table.replace_schema_metadata(md), tmp, compression="zstd", write_page_checksum=True)
    return Path(path)


@contextlib.contextmanager
def artifact_dir(path: str | Path, meta: Meta) -> Iterator[Path]:
    """Yield a temporary folder to fill; on success add ``meta.json`` and rename it onto ``path``.

    Parameters
    ----------
    path : str or Path
        The folder artifact's final path, replaced whole.
    meta : pipeline.artifacts.lineage.Meta
        Its metadata (a folder schema).

    Yields
    ------
    Path
        The temporary folder.

    Raises
    ------
    ArtifactError
        The folder lacks a file the schema requires (nothing is moved into place).
    """
    schema = check_kind(meta.schema, "dir")
    with atomic_path(path, is_dir=True) as tmp:
        yield tmp
        missing = missing_files(tmp, schema.files)
        if missing:
            raise ArtifactError(f"{path}: schema {meta.schema!r} needs files {missing}")
        (tmp / META_FILE).write_text(json.dumps(meta.to_dict(), indent=1, sort_keys=True))


class Artifact:
    """A validated artifact opened for reading (:func:`open_artifact`).

    Parameters
    ----------
    path : Path
        Where it lies.
    meta : pipeline.artifacts.lineage.Meta
        Its schema, fingerprint and lineage.
    """

    def __init__(self, path: Path, meta: Meta):
        self.path = path
        self.meta = meta

    @property
    def fingerprint(self) -> str:
        """The artifact's content fingerprint (from its metadata)."""
        return self.meta.fingerprint

    def __repr__(self) -> str:
        """Return one line: kind, schema and version, path and short fingerprint."""
        m = self.meta
        return f"<{type(self).__name__} {m.schema} v{m.schema_version} {self.path} fp={self.fingerprint[:12]}>"


class ZarrArtifact(Artifact):
    """An opened Zarr group: ``art["voted"]`` is a lazy, verified array, ``art.numpy("voted")`` loads it.

    Parameters
    ----------
    path : Path
        Where it lies.
    meta : pipeline.artifacts.lineage.Meta
        Its metadata.
    group : zarr.Group
        The opened group; ``attrs`` holds its attributes without the metadata.
    """

    def __init__(self, path, meta, group):
        super().__init__(path, meta)
        self.group = group
        self.attrs = {k: v for k, v in group.attrs.items() if k != META_KEY}

    @property
    def arrays(self) -> dict:
        """Array name -> the raw zarr array (unverified reads)."""
        return dict(self.group.arrays())

    def __getitem__(self, name: str):
        """Return array ``name`` as a :class:`VerifiedArray` (lazy).

        Raises
        ------
        ArtifactError
            The group has no such array.
        """
        try:
            return VerifiedArray(self.group[name], f"{self.path}: array {name!r}")
        except KeyError:
            raise ArtifactError(f"{self.path}: no array {name!r}") from None

    def __contains__(self, name: str) -> bool:
        """Whether the group holds ``name``."""
        return name in self.group

    def numpy(self, name: str) -> np.ndarray:
        """Load array ``name`` whole.

        Parameters
        ----------
        name : str
            The array's name.

        Returns
        -------
        numpy.ndarray
            Its content.
        """
        return np.asarray(self[name][...])


class VerifiedArray:
    """A zarr array whose reads turn a checksum mismatch or an undecodable chunk into one ArtifactError line.

    Other attributes are the wrapped array's.

    Parameters
    ----------
    arr : zarr.Array
        The wrapped array.
    where : str
        The path and array name the error names.
    """

    def __init__(self, arr, where: str):
        self._arr = arr
        self._where = where

    def __getattr__(self, name):
        """Return the wrapped array's attribute ``name``."""
        return getattr(self._arr, name)

    def _read(self, fn, *args):
        try:
            return fn(*args)
        except ArtifactError:
            raise
        except Exception as e:  # crc32c mismatch, blosc/zstd decode error, truncated shard
            raise ArtifactError(f"{self._where}: corrupt chunk ({type(e).__name__}); rerun the producing "
                                "stage") from None

    def __getitem__(self, sel):
        """Read a selection.

        Raises
        ------
        ArtifactError
            A chunk is corrupt or truncated.
        """
        return self._read(self._arr.__getitem__, sel)

    def get_orthogonal_selection(self, sel):
        """Read an orthogonal selection (zarr's).

        Parameters
        ----------
        sel : tuple
            The selection.

        Returns
        -------
        numpy.ndarray
            The values.

        Raises
        ------
        ArtifactError
            A chunk is corrupt or truncated.
        """
        return self._read(self._arr.get_orthogonal_selection, sel)

    def __array__(self, dtype=None, copy=None):
        """Read the whole array (numpy protocol), cast to ``dtype`` when given."""
        out = self[...]
        return out if dtype is None else out.astype(dtype)

    def __len__(self):
        """Return the length of axis 0."""
        return len(self._arr)


class TableArtifact(Artifact):
    """An opened Parquet table: ``art.df`` (also ``art.table``) is a pandas DataFrame.

    Parameters
    ----------
    path : Path
        Where it lies.
    meta : pipeline.artifacts.lineage.Meta
        Its metadata.
    df : pandas.DataFrame
        The table.
    """

    def __init__(self, path, meta, df):
        super().__init__(path, meta)
        self.df = df

    @property
    def table(self):
        """The table (``df``)."""
        return self.df


class DirArtifact(Artifact):
    """An opened folder artifact (checkpoint, report, deploy bundle): ``art.files`` and ``art.file(name)``."""

    @property
    def files(self) -> list[str]:
        """The names of the folder's entries, sorted."""
        return sorted(p.name for p in self.path.iterdir())

    def file(self, name: str) -> Path:
        """Return the path of the folder's file ``name``.

        Parameters
        ----------
        name : str
            A file name in the folder.

        Returns
        -------
        Path
            Its path.

        Raises
        ------
        ArtifactError
            There is no such file.
        """
        p = self.path / name
        if not p.exists():
            raise ArtifactError(f"{self.path}: no file {name!r}")
        return p

    def table(self, name: str = TRAINING_LOG_FILE):
        """Open a table artifact inside the folder.

        Parameters
        ----------
        name : str, optional
            Its file name (default the training log).

        Returns
        -------
        pandas.DataFrame
            The table.
        """
        return open_artifact(self.path / name).df


def _check_chunk_files(path: Path, group) -> None:
    """Every chunk file recorded at write time must exist (a deleted shard would read back as zeros)."""
    expected = group.attrs.get(CHUNKS_KEY)
    if not isinstance(expected, dict):
        raise ArtifactError(f"{path}: no chunk record (written by an older version); rerun the producing stage")
    for name, n in expected.items():
        cdir = path / name / "c"
        found = sum(1 for p in cdir.rglob("*") if p.is_file()) if cdir.is_dir() else 0
        if found != n:
            raise ArtifactError(f"{path}: array {name!r} has {found} of its {n} chunk files; "
                                "the artifact is incomplete or damaged, rerun the producing stage")


def _validate(path: Path, meta_dict: Any, expect: str | None) -> Meta:
    if not isinstance(meta_dict, dict) or "schema" not in meta_dict:
        raise ArtifactError(f"{path}: not a geodistill artifact (no metadata); incomplete or foreign")
    meta = Meta.from_dict(meta_dict)
    schema = get_schema(meta.schema)
    if expect is not None and meta.schema != expect:
        raise ArtifactError(f"{path}: expected a {expect!r} artifact, found {meta.schema!r}")
    if meta.schema_version != schema.version:
        raise ArtifactError(f"{path}: schema {meta.schema!r} version {meta.schema_version}, "
                            f"this code reads version {schema.version}; rerun the producing stage")
    return meta


def _open_parquet(path: Path, expect: str | None) -> TableArtifact:
    import pyarrow.parquet as pq

    tbl = pq.read_table(path, page_checksum_verification=True)
    raw = (tbl.schema.metadata or {}).get(META_KEY.encode())
    meta = _validate(path, json.loads(raw) if raw else None, expect)
    missing = [c for c in get_schema(meta.schema).columns if c not in tbl.column_names]
    if missing:
        raise ArtifactError(f"{path}: missing columns {missing}")
    return TableArtifact(path, meta, tbl.to_pandas())


def _open_zarr(path: Path, expect: str | None) -> ZarrArtifact:
    import zarr

    group = zarr.open_group(store=str(path), mode="r")
    meta = _validate(path, group.attrs.get(META_KEY), expect)
    _check_chunk_files(path, group)
    spec = get_schema(meta.schema)
    present = dict(group.arrays())
    for name, (kind, ndim) in {**spec.arrays, **{k: v for k, v in spec.optional.items() if k in present}}.items():
        if name not in present:
            raise ArtifactError(f"{path}: missing array {name!r}")
        arr = present[name]
        if np.dtype(arr.dtype).kind != kind or arr.ndim != ndim:
            raise ArtifactError(f"{path}: array {name!r} is {arr.dtype}[{arr.ndim}d], "
                                f"schema wants kind {kind!r} with {ndim} dims")
    return ZarrArtifact(path, meta, group)


def _open_dir(path: Path, expect: str | None) -> DirArtifact:
    mp = path / META_FILE
    meta = _validate(path, json.loads(mp.read_text()) if mp.exists() else None, expect)
    missing = missing_files(path, get_schema(meta.schema).files)
    if missing:
        raise ArtifactError(f"{path}: missing files {missing}")
    return DirArtifact(path, meta)


def open_artifact(path: str | Path, schema: str | None = None) -> Artifact:
    """Open and validate an artifact: a ``.zarr`` group, a ``.parquet`` table or a folder.

    Validation: the metadata is present, the schema (and ``schema`` when given) and its version match, required
    arrays, columns and files exist with the right kinds, and every chunk file recorded at write time is there.

    Parameters
    ----------
    path : str or Path
        The artifact.
    schema : str, optional
        The schema it must have.

    Returns
    -------
    Artifact
        A :class:`ZarrArtifact`, :class:`TableArtifact` or :class:`DirArtifact`.

    Raises
    ------
    ArtifactError
        One line naming the path: not found, unknown type, not a geodistill artifact, another schema or
        version, missing parts, or unreadable or corrupt.
    """
    path = Path(path)
    if not path.exists():
        raise ArtifactError(f"{path}: artifact not found (run the stage that produces it)")
    opener = {".parquet": _open_parquet, ".zarr": _open_zarr}.get(path.suffix, _open_dir if path.is_dir() else None)
    if opener is None:
        raise ArtifactError(f"{path}: unknown artifact type (expected .zarr, .parquet or a directory)")
    try:
        return opener(path, schema)
    except ArtifactError:
        raise
    except Exception as e:  # corrupt file, unreadable JSON, broken zarr metadata ...
        detail = str(e).splitlines()[0][:200] if str(e) else ""
        raise ArtifactError(f"{path}: unreadable or corrupt artifact ({type(e).__name__}: {detail})") from None


def row_runs(sorted_rows: np.ndarray) -> list[tuple[int, int, int]]:
    """Split sorted, unique rows into contiguous runs.

    Parameters
    ----------
    sorted_rows : array_like
        Sorted, unique row indices.

    Returns
    -------
    list of tuple of int
        (first row, stop row, position of the first in the list) per run, e.g. [2, 3, 4, 9] ->
        [(2, 5, 0), (9, 10, 3)]; empty for no rows.
    """
    rows = np.asarray(sorted_rows, dtype=np.int64)
    if rows.size == 0:
        return []
    breaks = np.flatnonzero(np.diff(rows) != 1) + 1
    starts = np.concatenate([[0], breaks])
    ends = np.concatenate([breaks, [rows.size]])
    return [(int(rows[a]), int(rows[b - 1]) + 1, int(a)) for a, b in zip(starts, ends)]


def read_chunk_rows(arr, indices: np.ndarray) -> np.ndarray:
    """Read rows of a zarr array in the given order, one slice per contiguous run.

    Parameters
    ----------
    arr : zarr.Array or VerifiedArray
        The array.
    indices : array_like
        Unique row indices, any order.

    Returns
    -------
    numpy.ndarray
        [len(indices), ...] in the order of ``indices``.

    Raises
    ------
    IndexError
        A row repeats or lies outside the array.
    """
    indices = np.asarray(indices, dtype=np.int64).reshape(-1)
    order = np.argsort(indices, kind="stable")
    rows = indices[order]
    if rows.size and (rows[0] < 0 or rows[-1] >= arr.shape[0] or np.any(np.diff(rows) == 0)):
        raise IndexError(f"read_chunk_rows: rows must be unique and within 0..{arr.shape[0] - 1}")
    out = np.empty((rows.size,) + tuple(arr.shape[1:]), dtype=arr.dtype)
    for a, b, pos in row_runs(rows):
        out[order[pos:pos + b - a]] = arr[a:b]
    return out
