"""An artifact's metadata record (``Meta``): schema, stage, params, lineage, fingerprint and run id.

Under ``SOURCE_DATE_EPOCH`` the creation time and run id are pinned, so that a rerun writes byte-identical
artifacts.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import hashlib
import importlib.metadata
import json
import os
import sys
import uuid
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from pipeline.artifacts.schemas import get_schema
from pipeline.runtime.errors import ArtifactError, InputError

__all__ = ["PROGRAM", "canonical_json", "fingerprint", "library_versions", "run_as", "require_same_run", "Meta",
           "make_meta"]

#: the program's name (the console script), also the namespace of the artifacts' metadata.  It equals the
#: proposed method's name by coincidence: tests/core/test_method_table.py exempts exactly this assignment.
PROGRAM = "geodistill"
_LIBS = ("numpy", "scipy", "torch", "zarr", "pyarrow", "scikit-image", "opencv-python-headless")


def canonical_json(obj: Any) -> str:
    """Serialise ``obj`` as deterministic JSON: sorted keys, no whitespace; numpy scalars, sets, paths normalised.

    Parameters
    ----------
    obj : Any
        A JSON-able value; numpy scalars become Python numbers, sets sorted lists and paths strings, at any depth.

    Returns
    -------
    str
        The JSON text, the same for equal values whatever their key order.

    Raises
    ------
    TypeError
        ``obj`` holds a value of another type (from :func:`json.dumps`).
    """

    def default(o):
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, (set, frozenset)):
            return sorted(o)
        if isinstance(o, Path):
            return str(o)
        raise TypeError(f"not JSON serialisable: {type(o).__name__}")

    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=default)


def fingerprint(stage: str, code_version: str, params: Mapping[str, Any], input_fingerprints: Iterable[str]) -> str:
    """Hash what decides an artifact: sha256 over (stage, code version, canonical params, sorted input fingerprints).

    Parameters
    ----------
    stage : str
        The stage's name.
    code_version : str
        The stage's code version (:mod:`pipeline.runtime.codeversion`).
    params : Mapping[str, Any]
        The params the stage read, serialised by :func:`canonical_json`.
    input_fingerprints : Iterable[str]
        The fingerprints of the artifacts it read; their order does not count.

    Returns
    -------
    str
        The sha256 as 64 hex digits.
    """
    payload = canonical_json({"stage": stage, "code_version": code_version, "params": params,
                              "inputs": sorted(input_fingerprints)})
    return hashlib.sha256(payload.encode()).hexdigest()


def library_versions() -> dict[str, str]:
    """Return the versions of Python and of the installed libraries whose behaviour an artifact depends on.

    Returns
    -------
    dict[str, str]
        ``"python"`` and each installed distribution of the module's list (numpy, torch, zarr, ...) -> its
        version; one not installed is left out.
    """
    out = {"python": sys.version.split()[0]}
    for lib in _LIBS:
        with contextlib.suppress(importlib.metadata.PackageNotFoundError):
            out[lib] = importlib.metadata.version(lib)
    return out


def creation_time() -> str:
    """UTC ISO time for ``Meta.created_at``: ``SOURCE_DATE_EPOCH`` when set, else now."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    if not epoch:
        return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    try:
        return _dt.datetime.fromtimestamp(int(epoch), _dt.timezone.utc).isoformat(timespec="seconds")
    except (ValueError, OverflowError, OSError):
        raise InputError(f"SOURCE_DATE_EPOCH={epoch!r}: expected whole seconds since 1970") from None


_RUN_ID: str | None = None


def _new_run_id(argv: list[str]) -> str:
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    return hashlib.sha256("\0".join([epoch, *argv]).encode()).hexdigest()[:16] if epoch else uuid.uuid4().hex[:16]


def run_id() -> str:
    """Return this process's run id, recorded in every artifact it writes (:func:`require_same_run`)."""
    global _RUN_ID
    if _RUN_ID is None:
        _RUN_ID = _new_run_id(sys.argv[1:])
    return _RUN_ID


@contextlib.contextmanager
def run_as(argv: list[str]):
    """Make :func:`run_id` that of a process run with command line ``argv`` inside the block.

    For one run of several in a process (the CLI calling stages in turn); the previous run id is back on exit.

    Parameters
    ----------
    argv : list[str]
        The command line, program name aside, of the run this block stands for.

    Yields
    ------
    str
        The run id in force inside the block: a hash of ``SOURCE_DATE_EPOCH`` and ``argv`` when that is set,
        else a random one.
    """
    global _RUN_ID
    saved, _RUN_ID = _RUN_ID, _new_run_id(list(argv))
    try:
        yield _RUN_ID
    finally:
        _RUN_ID = saved


def require_same_run(*artifacts) -> None:
    """Refuse artifacts of one stage that different runs of it wrote (an interrupted run).

    Train's are exempt: each (method, seed) checkpoint is its own run.

    Parameters
    ----------
    *artifacts : opened artifacts or None
        Each with ``.path`` and ``.meta`` (a :class:`Meta`); None is skipped.

    Raises
    ------
    pipeline.runtime.errors.ArtifactError
        Two artifacts of one stage carry different run ids; the message names both paths and the stage to rerun.
    """
    first = {}  # stage -> its first artifact
    for a in artifacts:
        if a is None or a.meta.stage == "train":  # each (method, seed) checkpoint is its own run
            continue
        ref = first.setdefault(a.meta.stage, a)
        if a.meta.run_id != ref.meta.run_id:
            raise ArtifactError(f"{a.path}: written by another run of stage {a.meta.stage!r} than {ref.path} "
                                f"(an interrupted run?); rerun stage {a.meta.stage!r}")


@dataclasses.dataclass
class Meta:
    """The metadata record every artifact carries; the fields left empty are filled in on construction.

    Attributes
    ----------
    schema : str
        The artifact's schema name (a :data:`pipeline.catalog.ARTIFACTS` key).
    stage : str
        The stage that wrote it.
    code_version : str
        That stage's code version.
    params : dict
        The params the stage read.
    inputs : list[dict]
        Its lineage: one ``{"path", "schema", "fingerprint"}`` per artifact read.
    fingerprint : str
        :func:`fingerprint` of the above; "" -> computed.
    schema_version : int or None
        The schema's version; None -> the catalogue's current one.
    library_versions : dict
        :func:`library_versions` at write time; empty -> read now.
    created_at : str
        UTC ISO creation time; "" -> now, or ``SOURCE_DATE_EPOCH`` when set.
    run_id : str
        The writing process's run id (:func:`require_same_run`); "" -> this process's.
    extra : dict
        Stage-specific fields.

    Raises
    ------
    pipeline.runtime.errors.ArtifactError
        ``schema`` is no known artifact schema (when ``schema_version`` is None).
    pipeline.runtime.errors.InputError
        ``SOURCE_DATE_EPOCH`` is not whole seconds (when ``created_at`` is empty).
    """

    schema: str
    stage: str
    code_version: str
    params: dict
    inputs: list[dict]
    fingerprint: str = ""
    schema_version: int | None = None
    library_versions: dict = dataclasses.field(default_factory=dict)
    created_at: str = ""
    run_id: str = ""
    extra: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        """Fill in the fields left empty: schema version, fingerprint, library versions, time and run id."""
        if self.schema_version is None:
            self.schema_version = get_schema(self.schema).version
        if not self.fingerprint:
            self.fingerprint = fingerprint(self.stage, self.code_version, self.params,
                                           [i["fingerprint"] for i in self.inputs])
        self.library_versions = self.library_versions or library_versions()
        self.created_at = self.created_at or creation_time()
        self.run_id = self.run_id or run_id()

    def to_dict(self) -> dict:
        """Return the record as plain JSON types.

        Returns
        -------
        dict
            Every field, as :func:`canonical_json` serialises it.
        """
        return json.loads(canonical_json(dataclasses.asdict(self)))

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Meta:
        """Read a record written by :meth:`to_dict`; keys that are no field (a newer writer's) are ignored.

        Parameters
        ----------
        d : Mapping[str, Any]
            The stored record.

        Returns
        -------
        Meta
            The record; fields missing from ``d`` are filled in as on construction.
        """
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})


def make_meta(schema: str, stage: str, code_version: str, params: Mapping[str, Any],
              inputs: Iterable = (), **extra) -> Meta:
    """Build the metadata record of a new artifact.

    Parameters
    ----------
    schema : str
        The artifact's schema name.
    stage : str
        The stage writing it.
    code_version : str
        That stage's code version.
    params : Mapping[str, Any]
        The params the stage read; stored as :func:`canonical_json` normalises them.
    inputs : Iterable, optional
        The artifacts read: opened artifacts (with ``.path`` and ``.meta``) or (path, :class:`Meta`) pairs.
    **extra
        Stage-specific fields, stored under :attr:`Meta.extra`.

    Returns
    -------
    Meta
        The record, with its fingerprint, library versions, creation time and run id filled in.
    """
    lineage = []
    for inp in inputs:
        path, m = (inp.path, inp.meta) if hasattr(inp, "meta") else inp
        lineage.append({"path": str(path), "schema": m.schema, "fingerprint": m.fingerprint})
    return Meta(schema=schema, stage=stage, code_version=code_version,
                params=json.loads(canonical_json(dict(params))), inputs=lineage, extra=extra)
