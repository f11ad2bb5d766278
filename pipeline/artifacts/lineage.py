"""An artifact's metadata record (``Meta``): schema, stage, params, lineage, fingerprint and run id; under
``SOURCE_DATE_EPOCH`` the creation time and run id are pinned, so that a rerun writes byte-identical artifacts."""

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
    """Deterministic JSON: sorted keys, no whitespace, numpy scalars, sets and paths normalised."""

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
    """sha256 over (stage name, stage code version, canonical params, sorted input fingerprints)."""
    payload = canonical_json({"stage": stage, "code_version": code_version, "params": params,
                              "inputs": sorted(input_fingerprints)})
    return hashlib.sha256(payload.encode()).hexdigest()


def library_versions() -> dict[str, str]:
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
    """This process's run id, recorded in every artifact it writes (:func:`require_same_run`)."""
    global _RUN_ID
    if _RUN_ID is None:
        _RUN_ID = _new_run_id(sys.argv[1:])
    return _RUN_ID


@contextlib.contextmanager
def run_as(argv: list[str]):
    """Inside, :func:`run_id` is that of a process run with command line ``argv`` (one run of several in a process)."""
    global _RUN_ID
    saved, _RUN_ID = _RUN_ID, _new_run_id(list(argv))
    try:
        yield _RUN_ID
    finally:
        _RUN_ID = saved


def require_same_run(*artifacts) -> None:
    """ArtifactError unless the outputs of each stage among ``artifacts`` carry one run id (train's excepted)."""
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
        if self.schema_version is None:
            self.schema_version = get_schema(self.schema).version
        if not self.fingerprint:
            self.fingerprint = fingerprint(self.stage, self.code_version, self.params,
                                           [i["fingerprint"] for i in self.inputs])
        self.library_versions = self.library_versions or library_versions()
        self.created_at = self.created_at or creation_time()
        self.run_id = self.run_id or run_id()

    def to_dict(self) -> dict:
        return json.loads(canonical_json(dataclasses.asdict(self)))

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Meta:
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})


def make_meta(schema: str, stage: str, code_version: str, params: Mapping[str, Any],
              inputs: Iterable = (), **extra) -> Meta:
    """The metadata record of a new artifact; ``inputs`` are opened artifacts or (path, Meta) pairs."""
    lineage = []
    for inp in inputs:
        path, m = (inp.path, inp.meta) if hasattr(inp, "meta") else inp
        lineage.append({"path": str(path), "schema": m.schema, "fingerprint": m.fingerprint})
    return Meta(schema=schema, stage=stage, code_version=code_version,
                params=json.loads(canonical_json(dict(params))), inputs=lineage, extra=extra)
