"""Artifacts you can trust (issue: verified reads, atomic replaces, run ids, safe model loading), driven
through the stage commands: each case must end in exit 2 with one line naming the file, nothing lost."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.artifacts.atomic import FAULT_ENV
from pipeline.artifacts.lineage import make_meta, require_same_run
from pipeline.artifacts.store import ZarrWriter, open_artifact, write_parquet, write_zarr
from pipeline.runtime.errors import ArtifactError

ROOT = Path(__file__).resolve().parents[2]
PROMPTS = ["spacecraft", "satellite", "space probe", "space vehicle",
           "spacecraft with rigid body and appendages", "artificial object in space with panels and antennas"]


def _teacher(path: Path, n: int = 6, size: int = 32, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    masks = rng.random((n, 6, size, size)) < 0.3
    scores = rng.uniform(0.2, 0.9, (n, 6)).astype(np.float32)
    write_zarr(path, {"masks": masks, "scores": scores}, make_meta("teacher", "teacher", "test", {}),
               attrs={"prompts": PROMPTS, "image_ids": [f"i{i}" for i in range(n)]})
    return path


def _consensus(tmp: Path, teacher: Path, out: Path, *extra: str, env: dict | None = None):
    return subprocess.run([sys.executable, "-m", "stages.consensus", "--params", str(ROOT / "params.yaml"),
                           "--teacher", str(teacher), "--out", str(out), *extra],
                          capture_output=True, text=True, cwd=ROOT, env={**os.environ, **(env or {})})


def _one_error_line(r, *words):
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    lines = [ln for ln in r.stderr.strip().splitlines() if "error" in ln]
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    for w in words:
        assert w in lines[0], lines[0]


def _chunk_files(art: Path, name: str) -> list[Path]:
    return sorted(p for p in (art / name / "c").rglob("*") if p.is_file())


def test_flipped_byte_in_a_zarr_chunk_is_detected(tmp_path):
    teacher = _teacher(tmp_path / "teacher.zarr")
    f = _chunk_files(teacher, "masks")[0]
    data = bytearray(f.read_bytes())
    for i in (40, 41, 42, 43):   # inside the first chunk's compressed bytes
        data[i] ^= 0xFF
    f.write_bytes(bytes(data))
    r = _consensus(tmp_path, teacher, tmp_path / "consensus.zarr")
    _one_error_line(r, "teacher.zarr", "masks", "corrupt")
    assert not (tmp_path / "consensus.zarr").exists()


def test_flipped_float_byte_is_detected_not_silently_read(tmp_path):
    teacher = _teacher(tmp_path / "teacher.zarr")
    f = _chunk_files(teacher, "scores")[0]
    data = bytearray(f.read_bytes())
    data[len(data) // 3] ^= 0x01
    f.write_bytes(bytes(data))
    with pytest.raises(ArtifactError, match="scores.*corrupt"):
        open_artifact(teacher)["scores"][...]


def test_deleted_zarr_shard_is_detected_not_read_as_zeros(tmp_path):
    teacher = _teacher(tmp_path / "teacher.zarr")
    _chunk_files(teacher, "masks")[0].unlink()
    r = _consensus(tmp_path, teacher, tmp_path / "consensus.zarr")
    _one_error_line(r, "teacher.zarr", "masks", "chunk files")
    assert not (tmp_path / "consensus.zarr").exists()


def test_all_empty_rows_still_write_every_chunk(tmp_path):
    path = tmp_path / "e.zarr"
    write_zarr(path, {"masks": np.zeros((3, 6, 8, 8), bool), "scores": np.zeros((3, 6), np.float32)},
               make_meta("teacher", "teacher", "t", {}))
    art = open_artifact(path)  # would fail if zarr had skipped the all-fill-value chunks
    assert not art.numpy("masks").any()


def test_flipped_bytes_in_a_parquet_page_are_detected(tmp_path):
    path = tmp_path / "skipped.parquet"
    df = pd.DataFrame({"path": [f"file_{i}_" + "x" * 40 for i in range(200)], "reason": ["r"] * 200})
    write_parquet(path, df, make_meta("skipped_files", "prepare", "t", {}))
    import pyarrow.parquet as pq

    col = pq.ParquetFile(path).metadata.row_group(0).column(0)
    start = col.data_page_offset + col.total_compressed_size // 2   # inside the first column's page data
    data = bytearray(path.read_bytes())
    for i in (start, start + 1):
        data[i] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(ArtifactError, match="skipped.parquet"):
        open_artifact(path)


@pytest.mark.parametrize("point", ["before_replace", "after_exchange"])
def test_kill_during_replace_leaves_a_complete_artifact(tmp_path, point):
    teacher = _teacher(tmp_path / "teacher.zarr")
    out = tmp_path / "consensus.zarr"
    assert _consensus(tmp_path, teacher, out).returncode == 0
    old_fp = open_artifact(out).fingerprint
    r = _consensus(tmp_path, teacher, out, "--set", "consensus.vote_threshold=0.7", env={FAULT_ENV: point})
    assert r.returncode == -9  # SIGKILL
    art = open_artifact(out)  # complete: either the old or the new artifact
    assert art.meta.schema == "consensus" and art.numpy("voted").shape == (6, 32, 32)
    assert art.fingerprint != old_fp if point == "after_exchange" else art.fingerprint == old_fp
    # the next write removes the dead run's temporaries
    assert _consensus(tmp_path, teacher, out).returncode == 0
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".consensus.zarr.")] == []


def test_outputs_of_one_stage_from_different_runs_are_refused(tmp_path):
    meta_a = make_meta("geometry", "geometry", "c", {})
    write_zarr(tmp_path / "geometry.zarr", {"sdf": np.zeros((1, 4, 4), np.float32),
                                            "skeleton": np.zeros((1, 4, 4), bool)}, meta_a)
    gates_cols = ["image_id", "split", "c", "v", "a", "a0", "g_conf", "g_valid", "g_area", "g", "n_valid"]
    meta_b = make_meta("gates", "geometry", "c", {})
    meta_b.run_id = "another-run"
    write_parquet(tmp_path / "gates.parquet", pd.DataFrame({c: [0] for c in gates_cols}), meta_b)
    geo, gates = open_artifact(tmp_path / "geometry.zarr"), open_artifact(tmp_path / "gates.parquet")
    with pytest.raises(ArtifactError, match="another run of stage 'geometry'"):
        require_same_run(geo, gates)
    meta_b.run_id = meta_a.run_id
    write_parquet(tmp_path / "gates.parquet", pd.DataFrame({c: [0] for c in gates_cols}), meta_b)
    require_same_run(geo, open_artifact(tmp_path / "gates.parquet"))


def test_train_stage_refuses_gates_from_another_geometry_run(tmp_path):
    """Item 5 through the CLI: new gates.parquet beside an older geometry.zarr -> exit 2, one line."""
    from tests.builders.training import build_tiny_artifacts, train_cli, train_params_file

    art = build_tiny_artifacts(tmp_path / "artifacts")
    gates = open_artifact(art / "gates.parquet")
    meta = gates.meta
    meta.run_id = "a-later-run"
    write_parquet(art / "gates.parquet", gates.df, meta)
    r = train_cli("--params", str(train_params_file(tmp_path)), "--stage", "2", "--method", "sdf_scratch",
                  "--seed", "42", "--artifacts", str(art), "--out", str(tmp_path / "ck"), "--device", "cpu",
                  "--resume-dir", str(tmp_path / "cache"), cwd=tmp_path)
    _one_error_line(r, "gates.parquet", "another run of stage 'geometry'", "rerun stage 'geometry'")
    assert not (tmp_path / "ck").exists()


def test_zarr_writer_failure_keeps_the_old_artifact(tmp_path):
    teacher = _teacher(tmp_path / "teacher.zarr")
    fp = open_artifact(teacher).fingerprint
    with pytest.raises(RuntimeError):
        with ZarrWriter(teacher, make_meta("teacher", "teacher", "x", {"a": 1})) as w:
            w.create("masks", (1, 6, 4, 4), bool)
            raise RuntimeError("boom")
    assert open_artifact(teacher).fingerprint == fp
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_crafted_pickle_checkpoint_is_refused_before_it_runs(tmp_path):
    import torch

    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    ckpt = tmp_path / "ckpt"
    ckpt.mkdir()
    torch.save({"state_dict": {}, "config": {}, "x": Evil()}, ckpt / "model.pt")
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    import cv2

    cv2.imwrite(str(imgs / "a.png"), np.zeros((32, 32, 3), np.uint8))
    r = subprocess.run([sys.executable, "-m", "pipeline.cli.segment", "--checkpoint", str(ckpt), "--input", str(imgs),
                        "--output", str(tmp_path / "out"), "--params", str(ROOT / "params.yaml")],
                       capture_output=True, text=True, cwd=ROOT)
    _one_error_line(r, "model.pt")
    assert not marker.exists()
