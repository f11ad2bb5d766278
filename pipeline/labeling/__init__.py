"""Pseudo-labels of a folder of images in standard formats (``geodistill label``, ``pipeline.label``).

:mod:`pipeline.labeling.formats` -- COCO RLE / instance records and YOLO segmentation lines (pure);
:mod:`pipeline.labeling.run` -- the folder run: teacher (cached), vote, gate, export;
:mod:`pipeline.labeling.reading` -- the input folder and the teacher's answers on it;
:mod:`pipeline.labeling.writing` -- the files written under ``out``.
"""

from pipeline.labeling.run import FORMATS, LabelResult, label_folder

__all__ = ["FORMATS", "LabelResult", "label_folder"]
