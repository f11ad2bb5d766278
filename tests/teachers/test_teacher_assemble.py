"""The teacher stage's work called directly (pipeline.teachers.assemble), the teacher registry, and the
stage as wiring: the CLI writes what the library writes."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.artifacts.lineage import make_meta
from pipeline.artifacts.store import open_artifact
from pipeline.runtime.errors import InputError
from pipeline.params import PAPER, load_params, section
from pipeline.teacher_table import BACKENDS, TEACHER_TABLE, TeacherSpec, register_teacher, teacher_class, unregister_teacher
from pipeline.teachers import check_teacher_params, make_teacher
from pipeline.teachers.base import RegisteredTeacher
from pipeline.teachers.assemble import (SCORE_COLUMNS, check_alignment, fingerprint_params, open_teacher_run,
                                        score_rows, score_table)
from tests.builders.teacher import PARAMS, build_artifacts, run_stage


def _cfg(cache, **over) -> dict:
    return check_teacher_params({**section(load_params(PARAMS), "teacher"), "cache_dir": str(cache), **over})


def _meta(schema):
    return make_meta(schema, "teacher", "test", {})


def _open(paths):
    return open_artifact(paths["manifest"], "manifest"), open_artifact(paths["images"], "images")


def test_a_run_writes_every_row_and_leaves_other_splits_empty(tmp_path):
    paths = build_artifacts(tmp_path, n=6)
    run = open_teacher_run(_cfg(tmp_path / "cache", splits=["train", "val"]), *_open(paths), paths["reference"], "cpu")
    assert run.rows == [0, 1, 2, 4, 5]  # build_artifacts' splits: train train val test train train
    run.fill(run.rows)
    table = run.write(tmp_path / "t.zarr", tmp_path / "s.parquet", _meta)
    t = open_artifact(tmp_path / "t.zarr", "teacher")
    k = len(PAPER.teacher.prompts)
    assert t["masks"].shape == (6, k, 32, 32) and t["vflip_masks"].shape == (6, 32, 32)
    assert not t.numpy("masks")[3].any() and not t.numpy("scores")[3].any()  # the test row did not run
    assert t.numpy("scores")[[0, 1, 2, 4, 5]].max() > 0
    assert t.attrs["backend"] == "simulated" and t.attrs["simulator"] is True
    assert list(table.columns) == list(SCORE_COLUMNS) and len(table) == 6 * k
    assert table["ran"].tolist() == [r != 3 for r in range(6) for _ in range(k)]
    np.testing.assert_array_equal(table["score"].to_numpy().reshape(6, k), t.numpy("scores"))
    np.testing.assert_allclose(table["mask_area"].to_numpy().reshape(6, k), t.numpy("masks").mean(axis=(2, 3)))
    assert open_artifact(tmp_path / "s.parquet", "teacher_scores").df.equals(table)


def test_the_stage_writes_what_the_library_writes(tmp_path):
    """stages/teacher.py is wiring: its artifacts hold the same arrays and table as a direct call."""
    paths = build_artifacts(tmp_path, n=4)
    assert run_stage(paths, tmp_path / "cache").exit_code == 0
    run = open_teacher_run(_cfg(tmp_path / "cache"), *_open(paths), paths["reference"], "cpu")
    table = run.write(tmp_path / "t.zarr", tmp_path / "s.parquet", _meta)
    staged, direct = open_artifact(paths["out"], "teacher"), open_artifact(tmp_path / "t.zarr", "teacher")
    for name in ("masks", "scores", "vflip_masks", "vflip_scores"):
        np.testing.assert_array_equal(staged.numpy(name), direct.numpy(name))
    assert open_artifact(paths["scores"], "teacher_scores").df.equals(table)
    assert staged.meta.params == {"teacher": fingerprint_params(run.cfg)}  # the cache's place is not fingerprinted
    assert "cache_dir" not in staged.meta.params["teacher"]


def test_score_rows_validity_and_area():
    masks = np.zeros((2, 4, 4), bool)
    masks[0, :2] = True
    rows = score_rows("a", ["p", "q"], masks, np.array([0.5, 0.0], np.float32), "train", True)
    assert rows == [("a", 0, "p", 0.5, True, 0.5, "train", True), ("a", 1, "q", 0.0, False, 0.0, "train", True)]
    table = score_table(rows)
    assert table["score"].dtype == np.float32 and table["prompt_index"].dtype == np.int16


def test_alignment_refuses_another_row_order(tmp_path):
    paths = build_artifacts(tmp_path, n=4)
    man, img = _open(paths)
    check_alignment(man.df, img, None)
    with pytest.raises(InputError, match="image_id order"):
        check_alignment(man.df.iloc[::-1].reset_index(drop=True), img, None)
    with pytest.raises(InputError, match="rows but the manifest has 3"):
        check_alignment(man.df.iloc[:3], img, None)


def test_the_registry_holds_every_backend_name_once():
    assert tuple(TEACHER_TABLE) == BACKENDS
    for name in BACKENDS:
        cls = teacher_class(name)
        assert cls.backend == name and all(callable(getattr(cls, m)) for m in ("from_params", "fingerprint", "predict"))
    assert [n for n in BACKENDS if TEACHER_TABLE[n].simulator] == ["simulated"]
    shared = {n: type("T", (RegisteredTeacher,), {"backend": n})() for n in BACKENDS}  # their capabilities' source
    assert [n for n, t in shared.items() if not t.use_cache] == ["imported"]
    with pytest.raises(ValueError, match="registered already"):
        register_teacher("sam3", TEACHER_TABLE["sam3"])
    unregister_teacher("sam3")  # a built-in backend stays
    assert "sam3" in TEACHER_TABLE


def test_make_teacher_builds_from_the_registry(tmp_path, monkeypatch):
    teacher = make_teacher(_cfg(tmp_path, seed=7), (32, 32))
    assert type(teacher) is teacher_class("simulated") and teacher.seed == 7 and teacher.resolution == (32, 32)

    class Fake:
        @classmethod
        def from_params(cls, cfg, resolution, device):
            return ("fake", cfg["backend"], resolution, device)

    monkeypatch.setitem(TEACHER_TABLE, "simulated", TeacherSpec(Fake, "a fake", simulator=True))
    assert make_teacher(_cfg(tmp_path), (8, 8), "cpu") == ("fake", "simulated", (8, 8), "cpu")
