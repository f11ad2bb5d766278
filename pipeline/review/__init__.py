"""The human loop: rank the images a person should check, export them to Label Studio / CVAT, and read
the corrected masks back (``geodistill review export|import``).

:func:`pipeline.consensus.agreement_entropy` -- the per-image prompt-disagreement statistic ``label`` records;
:mod:`pipeline.review.ranking` -- the rankings (which images most need a person);
:mod:`pipeline.review.formats` -- Label Studio brush RLE / polygons and COCO RLE (pure);
:mod:`pipeline.review.export` -- ``review export`` on a ``label`` output folder;
:mod:`pipeline.review.corrections` -- ``review import``: the ``corrections`` artifact.

This file imports nothing: :mod:`pipeline.labeling.run` imports the disagreement module, and the export
imports the labelling outputs, so the package must not pull its modules in together.
"""
