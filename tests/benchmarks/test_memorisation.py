"""Smoke test of the memorisation diagnosis (benchmarks/memorisation.py) on tiny SIMULATOR artifacts (32 px)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from benchmarks import memorisation as memo
from pipeline.runtime.errors import InputError
from stages.consensus import main as consensus_main
from tests.builders.teacher import PARAMS, build_artifacts, run_stage


def test_regions_partition_and_copy_rates():
    gt = np.zeros((1, 16, 16), bool)
    gt[0, 4:12, 4:12] = True
    gt[0, 8, 12:15] = True  # a one-pixel-wide arm: thin
    vote = gt.copy()
    vote[0, 8, 12:15] = False  # the vote drops the arm
    vote[0, 0:2, 0:2] = True  # and adds a blob far from the object
    lab = memo.region_labels(gt, vote, band=1, radius=1)
    names = np.array(memo.REGIONS)[lab[0]]
    # the arm's pixel next to the square survives the opening (the disk fits there): it is boundary, not thin
    assert (names[8, 13:15] == "thin").all() and names[8, 12] == "boundary"
    assert (names[0:2, 0:2] == "fp_blob").all() and names[4, 4] == "thin"  # a square corner is opened away too
    assert names[7, 7] == "interior" and names[4, 8] == "boundary" and names[3, 8] == "boundary"
    assert names[15, 15] == "background"
    pred = gt.copy()  # corrects the arm, copies the blob, adds one own error on the background
    pred[0, 0:2, 0:2] = True
    pred[0, 15, 15] = True
    rates = memo.copy_rates(memo.error_counts(pred, gt, vote, lab))
    assert rates["thin"]["copied"] == 0.0 and rates["thin"]["vote_wrong_px"] == 2
    assert rates["fp_blob"]["copied"] == 1.0 and rates["fp_blob"]["vote_wrong_px"] == 4
    assert rates["background"]["own"] == pytest.approx(1 / rates["background"]["vote_right_px"])
    assert np.isnan(rates["interior"]["copied"])  # the vote is right on every interior pixel
    assert memo.scored_epochs(list(range(1, 11)), 4, 6) == [4, 6, 8, 10]
    value, lo, hi = memo.bootstrap_ratio(np.array([1, 3]), np.array([2, 4]), np.random.default_rng(0), 200)
    assert value == pytest.approx(4 / 6) and 0.5 <= lo <= value <= hi <= 0.75


def test_memorisation_runs_and_resumes_on_tiny_simulator_artifacts(tmp_path, monkeypatch):
    paths = build_artifacts(tmp_path / "art", n=12, splits=["train"] * 6 + ["val"] * 4 + ["test"] * 2)
    assert run_stage(paths, tmp_path / "cache").exit_code == 0
    res = CliRunner().invoke(consensus_main, ["--params", PARAMS, "--device", "cpu", "--teacher", paths["out"],
                                              "--out", str(tmp_path / "art" / "consensus.zarr")])
    assert res.exit_code == 0, res.output
    argv = ["--artifacts", str(tmp_path / "art"), "--workdir", str(tmp_path / "work"), "--profile", "demo",
            "--resolution", "32", "--set", "train.recipe=progressive", "--set", "train.epochs_stage1=3",
            "--set", "train.channels=[4,8,8]", "--score-stride", "1", "--out", str(tmp_path / "m.json")]
    doc = memo.main(argv)
    assert doc["info"]["replay_matches_teacher_zarr"] and len(doc["draws"]["per_image"]) == 6
    assert set(doc["runs"]) == {"plain", "supervised_ceiling"}
    plain = doc["runs"]["plain"]
    assert plain["annotation_free"] and not doc["runs"]["supervised_ceiling"]["annotation_free"]
    c = plain["curves"]
    assert c["epochs"] == [1, 2, 3] and len(c["cal"]["iou_ref"]) == 4  # every epoch and the final model
    assert all(0 <= x <= 1 for x in c["05"]["iou_ref"])
    for g, rates in c["cal"]["copied"].items():
        assert all(r is None or 0 <= r <= 1 for r in rates), g
    assert json.loads((tmp_path / "m.json").read_text())["runs"]["plain"]["curves"] == c
    from pipeline.training import loop as training

    def boom(*args, **kwargs):
        raise AssertionError("trained or scored again")

    monkeypatch.setattr(training, "train", boom)
    monkeypatch.setattr(memo, "score_epoch", boom)
    again = memo.main([*argv, "--figure", str(tmp_path / "m.png")])  # the runs and their scores are kept
    assert again["runs"] == doc["runs"]
    assert (tmp_path / "m.png").read_bytes()[:4] == b"\x89PNG"


def test_a_teacher_that_is_not_the_simulator_is_refused(tiny):
    from pipeline import catalog
    from pipeline.artifacts.store import open_artifact

    rows = memo.training_rows(open_artifact(catalog.path("manifest", tiny), "manifest"))
    with pytest.raises(InputError, match="SIMULATOR"):
        memo.replay_draws(tiny, rows)
