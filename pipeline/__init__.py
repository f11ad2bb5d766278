"""GeoDistill-Refine: annotation-free spacecraft segmentation.

Notebook entry points: ``open_artifact``, ``label``, ``distill`` and ``Segmenter`` (:mod:`pipeline.api`),
loaded on first use.
"""

import importlib
import os
import sys


def quiet_opencv() -> None:
    """Silence OpenCV's own log, which would precede our one-line message about a corrupt image.

    A user's own ``OPENCV_LOG_LEVEL`` is kept.  Every cv2 user of the project imports ``pipeline`` first.
    """
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

# Loaded on first use: importing ``pipeline`` starts no torch, and strings, not imports, keep the API's modules
# out of every stage's code deps (each stage imports this package).
_LAZY = {"label": ("pipeline.api", "label"), "distill": ("pipeline.api", "distill"),
         "Segmenter": ("pipeline.deploy.segmenter", "Segmenter")}


def __getattr__(name):
    """Load ``label``, ``distill`` and ``Segmenter`` on first use (importing ``pipeline`` starts no torch).

    Parameters
    ----------
    name : str
        The attribute asked for.

    Returns
    -------
    object
        The API function or class.

    Raises
    ------
    AttributeError
        ``name`` is not an attribute of ``pipeline``.
    """
    if name in _LAZY:
        module, attr = _LAZY[name]
        return getattr(importlib.import_module(module), attr)
    raise AttributeError(f"module 'pipeline' has no attribute {name!r}")
