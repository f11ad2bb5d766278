"""reports/gpu/teacher_gpu.py (issue 58 item 4: the real-size SAM 3's peak memory and compiled time on a GPU), its
logic on the CPU with the tiny random SAM 3: every batch and path timed the asked number of rounds, the JSON
rewritten per batch, the deadline and a missing API each stop it with a clear account.  On a CPU there is no
compile and no peak memory, and the JSON says so."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def teacher_gpu():
    spec = importlib.util.spec_from_file_location("teacher_gpu", REPO / "reports" / "gpu" / "teacher_gpu.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_each_batch_and_path_is_timed_and_written(teacher_gpu, tiny_sam3, tmp_path):
    out = tmp_path / "t.json"
    teacher_gpu.main(["--device", "cpu", "--checkpoint", str(tiny_sam3), "--batches", "1", "2", "--repeats", "2",
                      "--resolution", "28", "--out", str(out)])
    doc = json.loads(out.read_text())
    assert doc["finished"] and doc["stopped"] is None and sorted(doc["batches"]) == ["1", "2"]
    assert doc["compile_active"] == {"compiled": False, "eager": False}  # no compile off CUDA, and it says so
    for row in doc["batches"].values():
        for p in row["paths"].values():
            assert len(p["seconds"]) == 2 and 0 < p["ms_per_image_min"] <= p["ms_per_image_median"]
            assert p["peak_allocated_bytes"] is None  # no CUDA memory to read on a CPU
        assert row["eager_over_compiled_median"] > 0
    assert doc["parameters"] > 0 and doc["weights_bytes"] == 2 * doc["parameters"]  # bf16


def test_the_deadline_stops_before_the_next_batch(teacher_gpu, tiny_sam3, tmp_path):
    out = tmp_path / "t.json"
    teacher_gpu.main(["--device", "cpu", "--checkpoint", str(tiny_sam3), "--batches", "1", "--paths", "eager",
                      "--repeats", "1", "--resolution", "28", "--deadline", "0", "--out", str(out)])
    doc = json.loads(out.read_text())
    assert not doc["finished"] and doc["batches"] == {} and doc["stopped"].startswith("deadline")


def test_a_missing_api_is_one_clear_line(teacher_gpu, monkeypatch):
    monkeypatch.setitem(teacher_gpu.NEEDS, ("pipeline.teachers.sam3", "Sam3Teacher"), ("predict", "no_such_method"))
    with pytest.raises(SystemExit, match="Sam3Teacher lacks no_such_method"):
        teacher_gpu.require_api()
