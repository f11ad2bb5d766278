"""The tests' shared fixtures: tiny artifacts, a one-epoch Stage-I state, the tiny random SAM 3 and tiny
student checkpoints, each built once per module (or once per session) for every module that asks.

The rule of this folder: **no test module imports another test module** (``test_*.py``; a test module
imported by another would be collected twice and share its fixtures by import, which pyflakes reports as
redefinitions).  What several modules share lives here (fixtures) or in a helper module ``tests/_*.py``
(plain functions and constants), imported as ``tests._name``:

- ``tests/_tiny_train.py``  -- the training tests' tiny artifacts and helpers (``build_tiny_artifacts``,
  ``tiny_cfg``, ``load_arrays``, the train-stage subprocess);
- ``tests/_tiny_eval.py``   -- the result stages' tiny artifacts with random checkpoints, their params
  and command runner;
- ``tests/_tiny_deploy.py`` -- a tiny random student, its checkpoint, thresholds, artifacts, export;
- ``tests/_tiny_teacher.py`` -- the teacher stage's tiny artifacts and runner, a folder of images and the
  ``geodistill`` command runner.

Helper modules import no test module either; tests/test_test_layout.py checks both.  The fixtures
import their helpers when first used, so that a run of a light test module does not load them.
"""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    """The training tests' tiny artifacts (tests/_tiny_train.py), built once per module."""
    from tests._tiny_train import build_tiny_artifacts

    return build_tiny_artifacts(tmp_path_factory.mktemp("tiny") / "artifacts")


@pytest.fixture(scope="module")
def stage1_state(tiny) -> dict:
    """The mask-path state of a one-epoch Stage-I ``plain`` run on ``tiny`` (seed 42): the warm start
    of the Stage-II methods."""
    from pipeline import training
    from pipeline.methods import get_method
    from tests._tiny_train import load_arrays, tiny_cfg

    cfg = tiny_cfg(epochs_stage1=1)
    data, val = load_arrays(tiny, "plain", cfg)
    return training.train(get_method("plain"), cfg, data, val, 42, checkpointer=training.NoCheckpointer(),
                          show_progress=False).model.mask_path_state_dict()


@pytest.fixture(scope="session")
def tiny_sam3(tmp_path_factory) -> Path:
    """The tiny random SAM 3 (pipeline/teachers/tiny_sam3.py) whose vocabulary holds the words of the
    paper's prompts, saved once per session (skipped without transformers)."""
    pytest.importorskip("transformers")
    from pipeline.params import PAPER_PROMPTS
    from pipeline.teachers.tiny_sam3 import build_tiny_sam3

    words = tuple(dict.fromkeys(w for p in PAPER_PROMPTS for w in p.split()))
    return build_tiny_sam3(tmp_path_factory.mktemp("sam3") / "tiny-sam3", words=words)


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory) -> dict[str, Path]:
    """A tiny checkpoint recording its training resolution (as the train stage writes it) and the same
    weights without it (an older checkpoint)."""
    import pandas as pd

    from pipeline.artifacts import make_meta
    from pipeline.inference import save_checkpoint
    from tests._tiny_deploy import RES, tiny_model

    root = tmp_path_factory.mktemp("ckpts")
    log = pd.DataFrame({"epoch": [1], "stage": [1], "loss": [0.1], "val_iou": [0.5], "val_bf1": [0.5],
                        "lr": [1e-4]})
    meta = make_meta("checkpoint", "train", "test", {"seed": 42, "method": "geodistill"})
    common = dict(method="geodistill", seed=42, stage=1, selected_epoch=1, tau=0.5)
    return {"with": save_checkpoint(root / "with", tiny_model(3), meta, log, resolution=RES, **common),
            "without": save_checkpoint(root / "without", tiny_model(3), meta, log, **common)}
