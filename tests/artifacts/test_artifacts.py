"""Artifact layer: round trips, fingerprints, atomic writes, corruption errors."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import pipeline.artifacts.lineage
from pipeline.artifacts.lineage import fingerprint, make_meta
from pipeline.artifacts.store import ZarrWriter, artifact_dir, open_artifact, write_parquet, write_zarr
from pipeline.runtime.errors import ArtifactError, InputError


def _meta(schema="consensus", params=None, inputs=()):
    return make_meta(schema, "test_stage", "code-v1", params or {"vote_threshold": 0.5}, inputs)


def _consensus_arrays(n=5, h=6, w=7, seed=0):
    rng = np.random.default_rng(seed)
    return {
        "agreement": rng.random((n, h, w), dtype=np.float32),
        "voted": rng.random((n, h, w)) > 0.5,
        "n_valid": rng.integers(0, 7, n).astype(np.int16),
    }


def test_zarr_round_trip_and_meta(tmp_path):
    arrays = _consensus_arrays()
    write_zarr(tmp_path / "c.zarr", arrays, _meta(), attrs={"image_ids": list("abcde")})
    art = pipeline.open_artifact(tmp_path / "c.zarr")
    for k, v in arrays.items():
        np.testing.assert_array_equal(art.numpy(k), v)
        assert art[k].dtype == v.dtype
    assert art.attrs["image_ids"] == list("abcde")
    m = art.meta
    assert m.schema == "consensus" and m.schema_version == 1 and m.stage == "test_stage"
    assert m.params == {"vote_threshold": 0.5}
    assert "numpy" in m.library_versions and m.created_at
    assert len(m.fingerprint) == 64


def test_source_date_epoch_makes_reruns_byte_identical(tmp_path, monkeypatch):
    import hashlib

    def digest(path):
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    df = pd.DataFrame({"method": ["plain"], "seed": [42], "tau": [0.5], "val_iou": [0.7]})
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    assert pipeline.artifacts.lineage.creation_time() == "2023-11-14T22:13:20+00:00"
    write_parquet(tmp_path / "a.parquet", df, make_meta("thresholds", "calibrate", "v1", {}))
    write_parquet(tmp_path / "b.parquet", df, make_meta("thresholds", "calibrate", "v1", {}))
    assert digest(tmp_path / "a.parquet") == digest(tmp_path / "b.parquet")
    assert pipeline.open_artifact(tmp_path / "a.parquet").meta.created_at == "2023-11-14T22:13:20+00:00"
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "yesterday")
    with pytest.raises(InputError, match="SOURCE_DATE_EPOCH"):
        make_meta("thresholds", "calibrate", "v1", {})


def test_streamed_writer_shards_into_few_files(tmp_path):
    n, h, w = 40, 8, 8
    with ZarrWriter(tmp_path / "c.zarr", _meta(), shard_images=16) as wr:
        wr.create("agreement", (n, h, w), np.float32)
        wr.create("voted", (n, h, w), bool)
        wr.create("n_valid", (n,), np.int16)
        for i in reversed(range(n)):  # out of order on purpose
            wr.write("agreement", i, np.full((h, w), i, np.float32))
            wr.write("voted", i, np.full((h, w), i % 2 == 0))
            wr.write("n_valid", i, i % 7)
    art = open_artifact(tmp_path / "c.zarr", "consensus")
    np.testing.assert_array_equal(art.numpy("agreement")[:, 0, 0], np.arange(n))
    np.testing.assert_array_equal(art.numpy("n_valid"), np.arange(n) % 7)
    shard_files = [p for p in (tmp_path / "c.zarr" / "agreement").rglob("*") if p.is_file() and p.name != "zarr.json"]
    assert len(shard_files) == 3  # 40 images, 16 per shard: 3 files, not 40


def test_parquet_round_trip_with_lineage(tmp_path):
    write_zarr(tmp_path / "c.zarr", _consensus_arrays(), _meta())
    parent = open_artifact(tmp_path / "c.zarr")
    df = pd.DataFrame({"path": ["a.png", "b.png"], "reason": ["corrupt", "zero-byte"]})
    write_parquet(tmp_path / "s.parquet", df, _meta("skipped_files", inputs=[parent]))
    art = open_artifact(tmp_path / "s.parquet", "skipped_files")
    pd.testing.assert_frame_equal(art.df, df)
    assert art.meta.inputs == [{"path": str(tmp_path / "c.zarr"), "schema": "consensus",
                                "fingerprint": parent.fingerprint}]


def test_fingerprint_stable_and_sensitive():
    base = fingerprint("s", "v1", {"a": 1, "b": [1, 2]}, ["x", "y"])
    assert base == fingerprint("s", "v1", {"b": [1, 2], "a": 1}, ["y", "x"])  # canonical order
    assert base != fingerprint("s", "v1", {"a": 2, "b": [1, 2]}, ["x", "y"])  # param change
    assert base != fingerprint("s", "v1", {"a": 1, "b": [1, 2]}, ["x", "z"])  # input change
    assert base != fingerprint("s", "v2", {"a": 1, "b": [1, 2]}, ["x", "y"])  # code change
    assert base != fingerprint("t", "v1", {"a": 1, "b": [1, 2]}, ["x", "y"])  # stage change
    # creation time and library versions are provenance, not identity
    assert _meta().fingerprint == _meta().fingerprint


def test_failure_mid_write_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError):
        with ZarrWriter(tmp_path / "c.zarr", _meta()) as wr:
            wr.create("agreement", (3, 4, 4), np.float32)
            wr.write("agreement", 0, np.zeros((4, 4)))
            raise RuntimeError("killed")
    assert list(tmp_path.iterdir()) == []


def test_kill_mid_write_leaves_no_complete_artifact(tmp_path):
    """A real SIGKILL mid-write: only a hidden temp dir may remain, and the final path is absent."""
    script = textwrap.dedent(f"""
        import os, signal, numpy as np
        from pipeline.artifacts.lineage import make_meta
        from pipeline.artifacts.store import ZarrWriter
        m = make_meta("consensus", "s", "c", {{}}, [])
        with ZarrWriter({str(tmp_path / 'c.zarr')!r}, m, shard_images=2) as w:
            w.create("agreement", (6, 4, 4), np.float32)
            for i in range(3):
                w.write("agreement", i, np.zeros((4, 4)))
            os.kill(os.getpid(), signal.SIGKILL)
    """)
    proc = subprocess.run([sys.executable, "-c", script], cwd=Path(__file__).parents[2])
    assert proc.returncode != 0
    assert not (tmp_path / "c.zarr").exists()
    with pytest.raises(ArtifactError, match="not found"):
        open_artifact(tmp_path / "c.zarr")


def test_overwrite_is_atomic_replacement(tmp_path):
    write_zarr(tmp_path / "c.zarr", _consensus_arrays(seed=1), _meta())
    new = _consensus_arrays(seed=2)
    write_zarr(tmp_path / "c.zarr", new, _meta(params={"vote_threshold": 0.6}))
    art = open_artifact(tmp_path / "c.zarr")
    np.testing.assert_array_equal(art.numpy("voted"), new["voted"])
    assert art.meta.params == {"vote_threshold": 0.6}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.zarr"]


def test_corrupt_artifacts_give_one_line_error_naming_path(tmp_path):
    write_zarr(tmp_path / "c.zarr", _consensus_arrays(), _meta())
    (tmp_path / "c.zarr" / "zarr.json").write_text("{not json")
    with pytest.raises(ArtifactError) as e:
        open_artifact(tmp_path / "c.zarr")
    assert str(tmp_path / "c.zarr") in str(e.value) and "\n" not in str(e.value)

    write_parquet(tmp_path / "s.parquet", pd.DataFrame({"path": ["a"], "reason": ["b"]}), _meta("skipped_files"))
    (tmp_path / "s.parquet").write_bytes(b"garbage" * 10)
    with pytest.raises(ArtifactError, match="corrupt"):
        open_artifact(tmp_path / "s.parquet")


def test_schema_mismatch_and_foreign_files(tmp_path):
    write_zarr(tmp_path / "c.zarr", _consensus_arrays(), _meta())
    with pytest.raises(ArtifactError, match="expected a 'teacher' artifact"):
        open_artifact(tmp_path / "c.zarr", "teacher")
    # wrong dtype for a schema array
    bad = _consensus_arrays()
    bad["voted"] = bad["voted"].astype(np.float32)
    write_zarr(tmp_path / "bad.zarr", bad, _meta())
    with pytest.raises(ArtifactError, match="voted"):
        open_artifact(tmp_path / "bad.zarr")
    # missing required array at write time
    with pytest.raises(ArtifactError, match="needs arrays"):
        write_zarr(tmp_path / "m.zarr", {"agreement": np.zeros((1, 2, 2), np.float32)}, _meta())
    assert not (tmp_path / "m.zarr").exists()
    # a parquet file with no geodistill metadata
    pd.DataFrame({"x": [1]}).to_parquet(tmp_path / "foreign.parquet")
    with pytest.raises(ArtifactError, match="not a geodistill artifact"):
        open_artifact(tmp_path / "foreign.parquet")
    # older schema version
    write_zarr(tmp_path / "old.zarr", _consensus_arrays(), _meta())
    zj = tmp_path / "old.zarr" / "zarr.json"
    doc = json.loads(zj.read_text())
    doc["attributes"]["geodistill"]["schema_version"] = 0
    zj.write_text(json.dumps(doc))
    with pytest.raises(ArtifactError, match="version 0"):
        open_artifact(tmp_path / "old.zarr")


def test_dir_artifact(tmp_path):
    meta = _meta("report")
    with artifact_dir(tmp_path / "r", meta) as d:
        (d / "report.md").write_text("# r")
        (d / "report.html").write_text("<html></html>")
    art = open_artifact(tmp_path / "r", "report")
    assert art.files == ["meta.json", "report.html", "report.md"]
    with pytest.raises(ArtifactError, match="needs files"):
        with artifact_dir(tmp_path / "r2", meta) as d:
            (d / "report.md").write_text("x")
    assert not (tmp_path / "r2").exists()
    assert not any(p.name.startswith(".r2") for p in tmp_path.iterdir())
    os.remove(tmp_path / "r" / "report.html")
    with pytest.raises(ArtifactError, match="missing files"):
        open_artifact(tmp_path / "r")


def test_read_chunk_rows_slices_equal_zarrs_orthogonal_selection(tmp_path):
    """Plain slices per contiguous run (the fix of issue 25) give exactly what zarr's orthogonal selection
    gives, for sorted, unsorted and gapped rows of a sharded one-row-per-chunk array."""
    import zarr

    from pipeline.artifacts.store import read_chunk_rows, row_runs

    rng = np.random.default_rng(0)
    data = rng.integers(0, 255, size=(23, 5, 4), dtype=np.uint8)
    arr = zarr.create_array(str(tmp_path / "a.zarr"), shape=data.shape, dtype=data.dtype, chunks=(1, 5, 4),
                            shards=(8, 5, 4))
    arr[:] = data
    for rows in ([0, 1, 2, 3], [22, 3, 4, 5, 17, 0], list(rng.permutation(23)[:11]), [7], []):
        rows = np.asarray(rows, dtype=np.int64)
        got = read_chunk_rows(arr, rows)
        expect = arr.get_orthogonal_selection((np.sort(rows),))[np.argsort(np.argsort(rows))] if rows.size \
            else data[:0]
        assert got.dtype == data.dtype and np.array_equal(got, expect) and np.array_equal(got, data[rows])
    assert row_runs(np.array([2, 3, 4, 9])) == [(2, 5, 0), (9, 10, 3)]
    with pytest.raises(IndexError):
        read_chunk_rows(arr, np.array([1, 1]))


#: a command that reads an array with one corrupt chunk beside a read that is still pending (slowed here), then
#: says how many tasks zarr's loop holds when the process exits (before zarr's own exit hook closes it)
PENDING_READ_SCRIPT = """
import asyncio, atexit, sys
from zarr.core import sync
from zarr.storage import LocalStore
from pipeline.artifacts.store import open_artifact
from pipeline.cli.conventions import one_line_errors

def pending():
    async def count():
        return len(asyncio.all_tasks() - {asyncio.current_task()})
    print("pending", asyncio.run_coroutine_threadsafe(count(), sync.loop[0]).result(5))

atexit.register(pending)  # after zarr's hook: runs before it
read = LocalStore.get

async def slow(self, key, *args, **kwargs):
    if key.startswith("agreement/c/1/"):
        await asyncio.sleep(60)
    return await read(self, key, *args, **kwargs)

LocalStore.get = slow
with one_line_errors("consensus"):
    open_artifact(sys.argv[1])["agreement"][...]
"""


def test_a_corrupt_chunk_read_leaves_one_line_and_no_pending_read(tmp_path):
    """Issue 64: the stage's one line, nothing after it -- the sibling reads zarr left pending are cancelled
    and awaited before the exit, so asyncio prints no "Task was destroyed but it is pending!"."""
    path = tmp_path / "c.zarr"
    with ZarrWriter(path, _meta(), shard_images=1) as w:  # one file per image: one read per row
        for name, value in _consensus_arrays(n=3).items():
            w.write_all(name, value)
    first = path / "agreement" / "c" / "0" / "0" / "0"
    data = bytearray(first.read_bytes())
    data[5] ^= 0xFF
    first.write_bytes(bytes(data))
    res = subprocess.run([sys.executable, "-c", PENDING_READ_SCRIPT, str(path)], capture_output=True, text=True,
                         timeout=120, env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])})
    assert res.returncode == 2, res.stderr
    assert res.stderr.splitlines() == [f"geodistill consensus: error: {path}: array 'agreement': corrupt chunk "
                                       "(ValueError); rerun the producing stage"]
    assert res.stdout.splitlines() == ["pending 0"]
