"""Pseudo-labels of a folder of images in standard formats (``geodistill label``, ``pipeline.label``).

:mod:`pipeline.labeling.formats` -- COCO RLE / instance records and YOLO segmentation lines (pure);
:mod:`pipeline.labeling.run` -- the folder run: teacher (cached), vote, gate, export.
"""

from pipeline.labeling.run import FORMATS, LabelResult, label_folder

__all__ = ["FORMATS", "LabelResult", "label_folder"]
