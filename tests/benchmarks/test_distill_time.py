"""Smoke test of the same-wall-time distill benchmark (benchmarks/distill_time.py).

A whole run is two ``--time`` probes and two ``geodistill distill`` projects (about 70 s each at 32 px, too long for
CI), so its parts are tested here on what CI already has: the export on the tiny artifacts, read back by the
imported teacher; the runs' params; one run's record read from the lane's finished distill project; the pairing.
"""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks import distill_time


def test_export_is_what_the_imported_teacher_reads(tiny, tmp_path):
    from pipeline import catalog
    from pipeline.artifacts.store import open_artifact
    from pipeline.profiles import load_profile
    from pipeline.teachers.base import TeacherInput
    from pipeline.teachers.imported import ImportedTeacher
    from pipeline.training.inputs import read_rows
    from tests.builders.training import PROMPTS

    folders = distill_time.export_inputs(tiny, tmp_path / "inputs", PROMPTS)
    manifest = open_artifact(catalog.path("manifest", tiny), "manifest").df
    ids = manifest["image_id"].tolist()
    assert sorted(p.stem for p in folders["images"].iterdir()) == sorted(ids)
    # the masks of the validation and test images only: distill never trains on an image with a mask
    assert sorted(p.stem for p in folders["masks"].iterdir()) == sorted(manifest.loc[manifest.split != "train",
                                                                                      "image_id"])
    teacher = open_artifact(catalog.path("teacher", tiny), "teacher")
    rows = np.arange(len(ids))
    want_masks, want_scores = read_rows(teacher, "masks", rows), read_rows(teacher, "scores", rows)
    size = want_masks.shape[-1]
    got_masks, got_scores = ImportedTeacher(folders["imported"], (size, size)).predict(
        [TeacherInput(i, "sha", np.zeros((size, size, 3), np.uint8)) for i in ids], PROMPTS)
    valid = want_scores > 0  # an answer with score 0 is no candidate: its mask is empty (finalize_answers)
    np.testing.assert_array_equal(got_masks[valid], want_masks[valid])
    np.testing.assert_allclose(got_scores, want_scores, rtol=1e-6)
    # Stage I's steps at the cap: the training images (those without a mask) at distill's batch, epochs_stage1 times
    n_train = int((manifest.split == "train").sum())
    train = load_profile("distill", ["data.resolution=32"])["train"]
    cap = distill_time.cap_steps(folders, "new", ["data.resolution=32"])
    assert cap == train["epochs_stage1"] * -(-n_train // train["batch_size"])
    assert distill_time.cap_steps(folders, "new", ["data.resolution=32"], 3 * train["epochs_stage1"]) == 3 * cap
    # two --time values whose budgets both reach the cap share one run; a binding budget has its own
    assert distill_time.project_name("new", cap + 5, cap, 1) == distill_time.project_name("new", cap * 3, cap, 1)
    assert distill_time.project_name("today", cap - 1, cap, 1) == f"today-{cap - 1}-s1"
    # complete: a second call writes nothing
    (folders["images"] / f"{ids[0]}.png").write_bytes(b"mine")
    distill_time.export_inputs(tiny, tmp_path / "inputs", PROMPTS)
    assert (folders["images"] / f"{ids[0]}.png").read_bytes() == b"mine"


def test_a_run_trains_the_seed_it_exports_at_the_fixed_budget():
    from pipeline.profiles import load_profile

    sets = distill_time.run_sets("today", 43, "10m", 1234, ["data.resolution=32"], threads=1)
    params = load_profile("distill", sets)  # validates: the exported run is a trained one
    assert params["train"]["step_budget"] == 1234 and params["train"]["until"] == "plateau"
    assert params["train"]["precision"] == "fp32" and params["train"]["channels_last"] is True
    assert params["protocol"]["runs"]["plain"] == [43] and params["deploy"]["export_seed"] == 43
    assert load_profile("distill", distill_time.run_sets("new", 43, "10m", 1, [], 1))["train"]["precision"] == "auto"
    # today's cap never moves (distill before issue 63); a cap --time raised travels with the run's budget
    assert params["train"]["time_cap_factor"] == 1 and params["train"]["epochs_stage1"] == 220
    raised = load_profile("distill", distill_time.run_sets("new", 43, "30m", 19_000, [], 1, epochs=570))["train"]
    assert (raised["epochs_stage1"], raised["step_budget"], raised["time_cap_factor"]) == (570, 19_000, 4)


def test_a_finished_project_is_read_and_paired(distill_with_masks):
    out, proc = distill_with_masks
    assert proc.returncode == 0, proc.stderr[-2000:]
    today = distill_time.run_record(out, "today", 42, steps=10, wall=1.0)
    assert today["steps_run"] > 0 and today["stage1_seconds"] >= 0 and today["stage2_seconds"] >= 0
    n = len(today["image_ids"])
    assert n > 0 and len(today["image_ious"]) == n == len(today["plain_image_ious"]) == len(today["vote_image_ious"])
    assert all(0 <= v <= 1 for v in today["vote_image_ious"])  # the vote scored on the same test images
    new = {**today, "setting": "new", "image_ious": [v + 0.01 for v in today["image_ious"]]}
    clusters = {i: f"sc{k % 2}" for k, i in enumerate(today["image_ids"])}
    groups = dict.fromkeys(today["image_ids"], "g")
    (g, pooled) = distill_time.comparison([today, new], clusters, groups)
    assert g["group"] == "g" and pooled["group"] == "all" and pooled["images"] == n
    assert pooled["gain"] == pytest.approx(0.01) and pooled["verdict"] == "one seed"
    # against the vote: the new runs' own vote scores are the control
    (_, vs_vote) = distill_time.comparison([today, new], clusters, groups, control=("new", "vote_image_ious"))
    assert vs_vote["gain"] == pytest.approx(np.mean(new["image_ious"]) - np.mean(today["vote_image_ious"]))
    assert vs_vote["ratio"] == pytest.approx(np.mean(new["image_ious"]) / np.mean(today["vote_image_ious"]))
    text = distill_time.table({"runs": [today, new], "gain": [g, pooled], "plain_gain": [pooled],
                               "vote_gain": [vs_vote], "plain_vote_gain": [vs_vote]})
    assert "| today | 42 | 10 |" in text and "+0.010" in text and "the teacher's vote" in text
    with pytest.raises(SystemExit, match="different test images"):
        distill_time.comparison([today, {**new, "image_ids": today["image_ids"][::-1]}], clusters, groups)
