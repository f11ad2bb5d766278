"""An artifact's schema: the one its catalogue entry holds (:data:`pipeline.catalog.ARTIFACTS`)."""

from __future__ import annotations

from pathlib import Path

from pipeline.catalog import ARTIFACTS, Schema
from pipeline.runtime.errors import ArtifactError

__all__ = ["get_schema", "check_kind", "missing_files"]


def get_schema(name: str) -> Schema:
    spec = ARTIFACTS.get(name)
    if spec is None or spec.schema is None:
        raise ArtifactError(f"unknown artifact schema {name!r}")
    return spec.schema


def check_kind(name: str, kind: str) -> Schema:
    """The schema ``name``, which must be of ``kind`` ("zarr", "parquet" or "dir")."""
    schema = get_schema(name)
    if schema.kind != kind:
        raise ArtifactError(f"schema {name!r} is a {schema.kind} artifact, not {kind}")
    return schema


def missing_files(directory: Path, files) -> list[str]:
    """The entries of a schema's ``files`` absent from ``directory`` (``"a|b"``: neither exists)."""
    return [f for f in files if not any((Path(directory) / alt).exists() for alt in f.split("|"))]
