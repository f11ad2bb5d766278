"""The human loop: rank the images a person should check, export them to Label Studio / CVAT, and read the
corrected masks back (``geodistill review export|import``).

Imports nothing: :mod:`pipeline.labeling.run` imports the disagreement module and the export imports the
labelling outputs, so the package must not pull its modules in together.
"""
