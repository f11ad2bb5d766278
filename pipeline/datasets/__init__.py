"""Datasets: the embedded synthetic spacecraft benchmark, real-dataset readers, one loader."""

from pipeline.datasets.loading import BadFileError, read_mask, read_rgb

__all__ = ["BadFileError", "read_mask", "read_rgb"]
