"""Datasets: the embedded synthetic spacecraft benchmark, real-dataset adapters, one loader.

* ``pipeline.datasets.synthetic`` -- procedural spacecraft and rendered views with exact GT masks/parts;
* ``pipeline.datasets.adapters``  -- SpaceSense-Bench, SPARK 2024, SPEED+, TANGO, any folder -> rows;
* ``pipeline.datasets.loading``   -- ``read_rgb`` / ``read_mask`` and cached ``load_rgb`` / ``load_mask``;
* ``pipeline.datasets.manifest``  -- manifest checks (duplicate ids, eq:spacecraft-disjoint), bad-input policy;
* ``pipeline.datasets.build``     -- what the ``prepare`` stage calls.
"""

from pipeline.datasets.loading import BadFileError, read_mask, read_rgb

__all__ = ["BadFileError", "read_mask", "read_rgb"]
