"""What a training run reads, opened from an artifacts directory: the train stage's inputs, callable
without the CLI (the train stage and the recipe study both call :func:`load_inputs`).

This module stays torch-free: :mod:`pipeline.training` (torch) is imported when a run loads its arrays.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from pipeline import catalog
from pipeline.artifacts import open_artifact, require_same_run


def load_inputs(artifacts: str | Path, spec, cfg: Mapping[str, Any]) -> tuple[Any, Any, list]:
    """Open what the method's training reads and the validation reference; build the arrays.

    Returns (TrainData, ValData or None, the artifacts opened -- the checkpoint's lineage).
    reference.zarr is opened only when the manifest has validation rows, and goes only to
    :func:`pipeline.training.validation_data` -- except for the supervised ceiling (NOT
    annotation-free), whose targets :func:`pipeline.supervised.ceiling_training_data` builds from it.
    """
    from pipeline import training  # torch: imported when a run trains, not with the stage module

    def opened_artifact(name: str):
        return open_artifact(catalog.path(name, artifacts), catalog.ARTIFACTS[name].schema)

    inputs = {name: opened_artifact(name) for name in training.training_inputs(spec, cfg)}
    # outputs of one stage must come from one run (a kill between geometry.zarr and gates.parquet)
    require_same_run(*inputs.values())
    opened = list(inputs.values())
    reference = None
    if spec.annotation_free:
        data = training.training_data(spec, cfg, inputs)
    else:  # the supervised ceiling: the one method whose loss sees reference masks (NOT annotation-free)
        from pipeline.supervised import ceiling_training_data  # imports pipeline.training (torch)

        reference = opened_artifact("reference")
        opened.append(reference)
        require_same_run(*opened)
        data = ceiling_training_data(spec, inputs, reference)
    val = None
    if len(training.validation_rows(inputs["manifest"])):
        if reference is None:
            reference = opened_artifact("reference")
            opened.append(reference)
            require_same_run(*opened)
        val = training.validation_data(inputs["manifest"], inputs["images"], reference)
    return data, val, opened
