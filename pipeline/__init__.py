"""GeoDistill-Refine: annotation-free spacecraft segmentation (library: numeric core + artifact IO).

Notebook entry point: ``pipeline.open_artifact(path)``.
"""

from pipeline.artifacts import open_artifact

__all__ = ["open_artifact"]
__version__ = "0.1.0"
