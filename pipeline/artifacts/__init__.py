"""Versioned, fingerprinted, atomically written artifacts: Zarr v3 groups, Parquet tables, folders."""

from pipeline.artifacts.store import open_artifact

__all__ = ["open_artifact"]
