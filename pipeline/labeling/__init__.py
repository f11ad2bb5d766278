"""Pseudo-labels of a folder of images in standard formats (``geodistill label``, ``pipeline.label``)."""

from pipeline.labeling.run import LABEL_FORMATS, LabelResult, label_folder

__all__ = ["LABEL_FORMATS", "LabelResult", "label_folder"]
