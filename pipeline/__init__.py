"""GeoDistill-Refine: annotation-free spacecraft segmentation (library: numeric core + artifact IO).

Notebook entry points: ``pipeline.open_artifact(path)``; ``pipeline.label(...)``, ``pipeline.distill(...)``
and ``pipeline.Segmenter.from_bundle(path).predict(image)`` (:mod:`pipeline.api`).
"""

import importlib
import os
import sys


def quiet_opencv() -> None:
    """Silence OpenCV's own log (``[ WARN:0@0.05] global grfmt_png.cpp ...`` before our one-line
    message about a corrupt image): ``OPENCV_LOG_LEVEL`` before cv2 is first imported, and the level
    of an already imported cv2.  Called here, so every cv2 user of the project (they all import
    ``pipeline``) goes through it; a user's own OPENCV_LOG_LEVEL is kept."""
    os.environ.setdefault("OPENCV_LOG_LEVEL", "SILENT")
    cv2 = sys.modules.get("cv2")
    if cv2 is not None and os.environ["OPENCV_LOG_LEVEL"].upper() in ("SILENT", "OFF", "0", "DISABLED"):
        try:
            cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
        except AttributeError:  # a cv2 build without the logging module
            pass


quiet_opencv()

from pipeline.artifacts import open_artifact  # noqa: E402  (after quiet_opencv: it may import cv2)

__all__ = ["open_artifact", "label", "distill", "Segmenter"]
__version__ = "0.1.0"

# Loaded on first use: importing ``pipeline`` stays light (no torch), and -- because these are plain
# strings, not import statements -- pipeline.orchestration.dag's import scan does not make the API's modules a code
# dependency of every DVC stage (each stage imports this package).
_LAZY = {"label": ("pipeline.api", "label"), "distill": ("pipeline.api", "distill"),
         "Segmenter": ("pipeline.deploy.segmenter", "Segmenter")}


def __getattr__(name):
    if name in _LAZY:
        module, attr = _LAZY[name]
        return getattr(importlib.import_module(module), attr)
    raise AttributeError(f"module 'pipeline' has no attribute {name!r}")
