"""The teacher stage end to end on the tiny artifacts of tests/builders/teacher.py (simulated and imported
backends, cache hits / misses / resume / shards / corrupt entries, excluded splits, bad input -> exit 2)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.artifacts.store import open_artifact
from tests.builders.teacher import PARAMS, H, W, build_artifacts, cache_files, run_stage


@pytest.fixture()
def art(tmp_path, monkeypatch):
    monkeypatch.setenv("GEODISTILL_QUIET", "1")
    return build_artifacts(tmp_path / "a"), tmp_path / "cache"


def test_stage_writes_artifacts_and_reuses_cache(art):
    paths, cache = art
    r = run_stage(paths, cache)
    assert r.exit_code == 0, r.output
    t = open_artifact(paths["out"], "teacher")
    masks, scores = t.numpy("masks"), t.numpy("scores")
    assert masks.shape == (6, 6, H, W) and masks.dtype == bool
    assert scores.shape == (6, 6) and scores.dtype == np.float32
    assert t.numpy("vflip_masks").shape == (6, H, W) and t.numpy("vflip_scores").shape == (6,)
    assert t.attrs["backend"] == "simulated" and t.attrs["simulator"] is True
    assert len(t.attrs["prompts"]) == 6 and t.attrs["image_ids"][0] == "img000"
    # invalid prompts: score 0 and an empty mask
    assert not masks[scores == 0].any()
    tbl = open_artifact(paths["scores"], "teacher_scores").df
    assert len(tbl) == 36
    np.testing.assert_allclose(tbl["score"].to_numpy().reshape(6, 6), scores)
    np.testing.assert_allclose(tbl["mask_area"].to_numpy().reshape(6, 6), masks.mean(axis=(2, 3)))
    assert (tbl["valid"].to_numpy() == (tbl["score"].to_numpy() > 0)).all()
    assert len(cache_files(cache)) == 6 * 7  # 6 images x (6 prompts + 1 flipped base prompt)

    # a rerun computes nothing (entries untouched) and reproduces the artifact exactly
    mtimes = {p: p.stat().st_mtime_ns for p in cache_files(cache)}
    fp = t.fingerprint
    r = run_stage(paths, cache)
    assert r.exit_code == 0
    assert {p: p.stat().st_mtime_ns for p in cache_files(cache)} == mtimes
    t2 = open_artifact(paths["out"], "teacher")
    assert t2.fingerprint == fp
    np.testing.assert_array_equal(t2.numpy("masks"), masks)

    # a param the teacher does not read (batch size) recomputes nothing
    r = run_stage(paths, cache, sets=["teacher.batch_size=3", "teacher.dtype=bf16"])
    assert r.exit_code == 0
    assert {p: p.stat().st_mtime_ns for p in cache_files(cache)} == mtimes
    # a param it does read (the simulator seed) gives new entries
    r = run_stage(paths, cache, sets=["teacher.seed=1"])
    assert r.exit_code == 0
    assert len(cache_files(cache)) == 2 * 6 * 7


def test_adding_a_prompt_computes_only_that_prompt(art):
    paths, cache = art
    assert run_stage(paths, cache).exit_code == 0
    before = {p: p.stat().st_mtime_ns for p in cache_files(cache)}
    base = open_artifact(paths["out"]).numpy("masks")
    import yaml

    prompts = yaml.safe_load(Path(PARAMS).read_text())["teacher"]["prompts"] + ["orbital platform"]
    r = run_stage(paths, cache, sets=[f"teacher.prompts={prompts!r}".replace("'", '"'), "geometry.n_prompts=7"])
    assert r.exit_code == 0, r.output
    after = {p: p.stat().st_mtime_ns for p in cache_files(cache)}
    assert len(after) == len(before) + 6
    assert all(after[p] == m for p, m in before.items())
    masks = open_artifact(paths["out"]).numpy("masks")
    assert masks.shape[1] == 7
    np.testing.assert_array_equal(masks[:, :6], base)  # the six old answers are unchanged


def test_shards_fill_the_cache_then_assemble_computes_nothing(art):
    paths, cache = art
    for i in range(3):
        r = run_stage(paths, cache, "--shard", f"{i}/3")
        assert r.exit_code == 0, r.output
        assert not Path(paths["out"]).exists()  # a shard writes no artifact
    files = cache_files(cache)
    assert len(files) == 6 * 7
    mtimes = {p: p.stat().st_mtime_ns for p in files}
    assert run_stage(paths, cache).exit_code == 0
    assert {p: p.stat().st_mtime_ns for p in cache_files(cache)} == mtimes
    # the same answers as a run without shards into a fresh cache
    sharded = open_artifact(paths["out"]).numpy("masks")
    assert run_stage(paths, cache.parent / "fresh").exit_code == 0
    np.testing.assert_array_equal(open_artifact(paths["out"]).numpy("masks"), sharded)


def test_one_shard_covers_only_its_images(art):
    paths, cache = art
    assert run_stage(paths, cache, "--shard", "1/2").exit_code == 0
    assert len(cache_files(cache)) == 3 * 7  # rows 1, 3, 5


def test_resume_after_interrupted_run_and_corrupt_entry(art):
    paths, cache = art
    assert run_stage(paths, cache).exit_code == 0
    full = open_artifact(paths["out"]).numpy("masks")
    files = cache_files(cache)
    # an interrupted run: half the entries never got written
    for p in files[::2]:
        p.unlink()
    # a corrupt entry: one flipped byte in the packed mask, one truncated file
    survivors = cache_files(cache)
    data = bytearray(survivors[0].read_bytes())
    data[-1] ^= 0xFF
    survivors[0].write_bytes(bytes(data))
    survivors[1].write_bytes(survivors[1].read_bytes()[:20])
    untouched = {p: p.stat().st_mtime_ns for p in survivors[2:]}
    r = run_stage(paths, cache)
    assert r.exit_code == 0
    assert len(cache_files(cache)) == len(files)
    assert all(p.stat().st_mtime_ns == m for p, m in untouched.items())
    np.testing.assert_array_equal(open_artifact(paths["out"]).numpy("masks"), full)


def test_excluded_split_gets_empty_invalid_answers(art):
    paths, cache = art
    r = run_stage(paths, cache, sets=["teacher.splits=[train]"])
    assert r.exit_code == 0, r.output
    t = open_artifact(paths["out"])
    split = open_artifact(paths["manifest"]).df["split"].to_numpy()
    assert t.numpy("scores")[split != "train"].max() == 0
    assert not t.numpy("masks")[split != "train"].any()
    tbl = open_artifact(paths["scores"]).df
    assert set(tbl.loc[~tbl["ran"], "split"]) == {"val", "test"}
    assert len(cache_files(cache)) == int((split == "train").sum()) * 7


@pytest.mark.parametrize("sets, needle", [
    (["teacher.backend=sam3", "teacher.checkpoint=/nonexistent/sam3"], "/nonexistent/sam3"),
    (["teacher.backend=sam3", "teacher.checkpoint=null"], "teacher.checkpoint"),
    (["teacher.backend=magic"], "teacher.backend"),
    (["teacher.prompts=[spacecraft, '']"], "teacher.prompts[1]"),
    (["teacher.prompts=[spacecraft, Spacecraft]"], "duplicates"),
    (["teacher.prompts=[]"], "teacher.prompts"),
    (["teacher.base_prompt_index=6"], "teacher.base_prompt_index"),
    (["teacher.splits=[training]"], "teacher.splits"),
    (["teacher.backend=imported", "teacher.imported_dir=/nonexistent/masks"], "/nonexistent/masks"),
])
def test_bad_input_exits_2_with_one_line(art, sets, needle):
    paths, cache = art
    r = run_stage(paths, cache, sets=sets)
    assert r.exit_code == 2
    assert needle in r.output and "Traceback" not in r.output
    assert len(r.output.strip().splitlines()) == 1


def test_bad_shard_and_missing_artifact_exit_2(art, tmp_path):
    paths, cache = art
    r = run_stage(paths, cache, "--shard", "3/3")
    assert r.exit_code == 2 and "--shard" in r.output
    bad = dict(paths, images=str(tmp_path / "nope.zarr"))
    r = run_stage(bad, cache)
    assert r.exit_code == 2 and "nope.zarr" in r.output
