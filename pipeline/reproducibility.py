"""What "the same published number" means: the reproducibility tolerance, written once.

A rerun of a published protocol -- another machine of the same kind, another thread count, fp32 instead
of bf16 -- reproduces a student metric when every test group's mean metric is within these absolute
tolerances of the published one.  The stability benchmark judges a training recipe against them, and CI
judges a fresh demo run against the committed metrics with them.

Keys are the metric names of the DVC metrics files (``reports/metrics/students/<group>/<method>.json``):
``iou`` = mean test Image IoU, ``bf1`` = mean test Boundary F1 (pipeline.metrics).
"""

from __future__ import annotations

#: Absolute tolerance per published student metric (mean over a test group's images).
TOLERANCE: dict[str, float] = {"iou": 0.01, "bf1": 0.02}
