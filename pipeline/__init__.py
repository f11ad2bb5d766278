"""GeoDistill-Refine: annotation-free spacecraft segmentation (library: numeric core + artifact IO).

Notebook entry points: ``pipeline.open_artifact(path)``; ``pipeline.label(...)``, ``pipeline.distill(...)``
and ``pipeline.Segmenter.from_bundle(path).predict(image)`` (:mod:`pipeline.api`).
"""

import importlib

from pipeline.artifacts import open_artifact

__all__ = ["open_artifact", "label", "distill", "Segmenter"]
__version__ = "0.1.0"

# Loaded on first use: importing ``pipeline`` stays light (no torch), and -- because these are plain
# strings, not import statements -- pipeline.dag's import scan does not make the API's modules a code
# dependency of every DVC stage (each stage imports this package).
_LAZY = {"label": ("pipeline.api", "label"), "distill": ("pipeline.api", "distill"),
         "Segmenter": ("pipeline.deploy.segmenter", "Segmenter")}


def __getattr__(name):
    if name in _LAZY:
        module, attr = _LAZY[name]
        return getattr(importlib.import_module(module), attr)
    raise AttributeError(f"module 'pipeline' has no attribute {name!r}")
