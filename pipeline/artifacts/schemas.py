"""An artifact's schema: the one its catalogue entry holds (:data:`pipeline.catalog.ARTIFACTS`)."""

from __future__ import annotations

from pathlib import Path

from pipeline.catalog import ARTIFACTS, Schema
from pipeline.runtime.errors import ArtifactError

__all__ = ["get_schema", "check_kind", "missing_files"]


def get_schema(name: str) -> Schema:
    """Look up the schema of artifact ``name`` in the catalogue.

    Parameters
    ----------
    name : str
        A :data:`pipeline.catalog.ARTIFACTS` key.

    Returns
    -------
    pipeline.catalog.Schema
        Its schema.

    Raises
    ------
    pipeline.runtime.errors.ArtifactError
        ``name`` is not in the catalogue, or its entry has no schema.
    """
    spec = ARTIFACTS.get(name)
    if spec is None or spec.schema is None:
        raise ArtifactError(f"unknown artifact schema {name!r}")
    return spec.schema


def check_kind(name: str, kind: str) -> Schema:
    """Look up the schema ``name`` and check that its artifact is of ``kind``.

    Parameters
    ----------
    name : str
        A :data:`pipeline.catalog.ARTIFACTS` key.
    kind : str
        The storage kind expected: ``"zarr"``, ``"parquet"`` or ``"dir"``.

    Returns
    -------
    pipeline.catalog.Schema
        Its schema.

    Raises
    ------
    pipeline.runtime.errors.ArtifactError
        ``name`` has no schema (:func:`get_schema`), or its kind is not ``kind``.
    """
    schema = get_schema(name)
    if schema.kind != kind:
        raise ArtifactError(f"schema {name!r} is a {schema.kind} artifact, not {kind}")
    return schema


def missing_files(directory: Path, files) -> list[str]:
    """List the entries of a schema's ``files`` absent from ``directory``.

    Parameters
    ----------
    directory : Path
        The artifact's folder.
    files : Iterable[str]
        A schema's file entries (:attr:`pipeline.catalog.Schema.files`); ``"a|b"`` is present when either is.

    Returns
    -------
    list[str]
        The entries none of whose alternatives exists, in ``files``' order.
    """
    return [f for f in files if not any((Path(directory) / alt).exists() for alt in f.split("|"))]
