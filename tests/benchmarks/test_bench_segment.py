"""Smoke test of ``python -m benchmarks.bench_segment`` at a tiny size: every CPU engine timed
(or skipped with its reason), model-only beside end to end, the ratios and the stated target."""

from __future__ import annotations

import cv2
import pytest

from benchmarks import bench_segment as B
from pipeline.runtime.errors import InputError


@pytest.fixture(autouse=True)
def quiet(monkeypatch):
    monkeypatch.setenv("GEODISTILL_QUIET", "1")


def test_bench_segment_prints_end_to_end_beside_model_only_for_every_engine(tmp_path, capsys):
    result = B.main(["--images", "5", "--size", "40x30", "--resolution", "32", "--channels", "4,8,16", "--batch", "2",
                     "--repeats", "1", "--json", str(tmp_path / "r.json")])
    out = capsys.readouterr().out
    engines = set(result["engines"]) | set(result["skipped"])
    assert engines == {"torch", "torchscript", "onnxruntime_fp32", "onnxruntime_int8", "openvino_int8", "cuda"}
    assert "torch" in result["engines"] and "needs a CUDA device" in result["skipped"]["cuda"]
    for name, row in result["engines"].items():
        assert row["model"]["median"] > 0 and row["overlapped"]["median"] > 0 and row["serial"]["best"] > 0
        assert row["overlapped_ratio"] == pytest.approx(row["overlapped"]["median"] / row["model"]["median"])
        assert row["serial_best_ratio"] == pytest.approx(row["serial"]["best"] / row["model"]["best"])
        assert len(result["seconds"][name]["overlapped"]) == 1
        line = next(ln for ln in out.splitlines() if ln.startswith(name + " "))
        assert line.rstrip().endswith(("met", "NOT met"))
    assert "Target: end to end >= 0.8 x model-only" in out and (tmp_path / "r.json").exists()
    with pytest.raises(InputError, match="unknown engine"):
        B.load_engines(tmp_path, ["tensorrt"])
    assert B.load_engines(tmp_path / "nowhere", ["int8"])[1].keys() == {"onnxruntime_int8"}  # an old name


def test_generated_images_are_photo_sized_and_not_flat(tmp_path):
    files = B.photo_like_images(tmp_path, 2, 64, 48, "png")
    img = cv2.imread(str(files[1]))
    assert [f.name for f in files] == ["img000.png", "img001.png"] and img.shape == (48, 64, 3)
    assert img.std() > 10
