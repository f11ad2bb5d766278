"""The prepare stage's work called directly (pipeline.datasets.prepare), and the stage as wiring."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from click.testing import CliRunner

from pipeline import catalog
from pipeline.artifacts.lineage import make_meta
from pipeline.artifacts.store import open_artifact
from pipeline.datasets.params import check_data_params
from pipeline.params import load_params, section
from pipeline.datasets.prepare import REFERENCE_NOTE, prepare
from stages.prepare import main as prepare_main

PARAMS = str(Path(__file__).resolve().parents[2] / "params.yaml")
SETS = ["data.resolution=32", "data.synthetic.train_views=1", "data.synthetic.val_views=1",
        "data.synthetic.test_views=1", "data.contact_sheet_images=2"]


def test_prepare_writes_the_catalogued_artifacts_as_the_stage_does(tmp_path):
    params = load_params(PARAMS, SETS + [f"data.cache_dir={tmp_path / 'cache'}"])
    seen = []

    def meta(schema, params, **extra):
        seen.append(schema)
        return make_meta(schema, "prepare", "test", params, **extra)

    done = prepare(check_data_params(section(params, "data")), tmp_path / "a", meta)
    assert seen == ["images", "reference", "skipped_files", "manifest"]
    man = open_artifact(catalog.path("manifest", tmp_path / "a"), "manifest")
    images = open_artifact(catalog.path("images", tmp_path / "a"), "images")
    reference = open_artifact(catalog.path("reference", tmp_path / "a"), "reference")
    n = len(done.rows)
    assert n == len(man.df) > 0 and images["image"].shape == (n, 32, 32, 3)
    assert reference.attrs["note"] == REFERENCE_NOTE and list(images.attrs["image_ids"]) == man.df["image_id"].tolist()
    assert man.meta.params["content_sha256"] and catalog.path("contact_sheet", tmp_path / "a").stat().st_size > 0
    assert done.policy.skipped == []

    args = ["--params", PARAMS, "--out-dir", str(tmp_path / "b"), "--set", f"data.cache_dir={tmp_path / 'cache'}"]
    for s in SETS:
        args += ["--set", s]
    assert CliRunner().invoke(prepare_main, args, catch_exceptions=False).exit_code == 0
    staged = open_artifact(catalog.path("images", tmp_path / "b"), "images")
    np.testing.assert_array_equal(staged.numpy("image"), images.numpy("image"))
    assert staged.meta.params == images.meta.params  # the content fingerprint, whoever calls
