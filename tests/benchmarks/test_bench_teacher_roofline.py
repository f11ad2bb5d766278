"""Smoke test of ``benchmarks.bench_teacher --roofline`` on the tiny random SAM 3: every row of the table
printed and written as JSON (FLOPs by module, per-module times, host limits, round-robin medians, ratio, gate)."""

from __future__ import annotations

import json
import re

import pytest

pytest.importorskip("transformers")


def test_roofline_prints_and_writes_its_table(tmp_path, capsys, tiny_sam3):
    from benchmarks.bench_teacher import main

    out = tmp_path / "roofline.json"
    main(["--roofline", "--checkpoint", str(tiny_sam3), "--images", "1", "--repeats", "2", "--resolution", "32",
          "--no-warmup", "--json", str(out)])
    text = capsys.readouterr().out
    for pattern in (r"limits \(measured 2048\^3 matmul, best / median\): fp32 \d+ / \d+ GFLOP/s",
                    r"FLOPs per image, 6 prompts: .*backbone [\d.]+ G.*; text once per run [\d.e+-]+ G",
                    r"per-module wall time of the default path", r"fp32 eager \(fp32\): median +[\d.]+ s/image",
                    r"default / fp32 eager \(medians\): \d\.\d{3}", r"fidelity vs fp32 eager: mean mask IoU"):
        assert re.search(pattern, text), (pattern, text)
    doc = json.loads(out.read_text())
    assert set(doc["seconds"]) == {"fp32 eager", "default"} and all(len(v) == 2 for v in doc["seconds"].values())
    assert doc["default_over_fp32"] == pytest.approx(doc["median_s_per_image"]["default"]
                                                     / doc["median_s_per_image"]["fp32 eager"])
    flops = doc["flops_per_image"]
    assert {"backbone", "detr_encoder", "detr_decoder", "mask_decoder"} <= set(flops) and min(flops.values()) >= 0
    assert flops["backbone"] > 0 and flops["detr_encoder"] > 0 and doc["text_flops_per_run"] > 0
    assert doc["limits"]["fp32_gflops"] > 0 and doc["host"]["load_average_before"]
    assert doc["fidelity"]["pairs"] == 6 and "passes" in doc["fidelity"]


def test_batch_sweep_logic_on_a_cpu(tmp_path, capsys, tiny_sam3):
    """The GPU script's rows (reports/gpu/teacher.sh) computed on a CPU: one row per batch size, the first call
    and the steady time; peak memory is CUDA's only (n/a here) and compile is forced off on a CPU."""
    from benchmarks.bench_teacher import main

    out = tmp_path / "sweep.json"
    main(["--batch-sweep", "1,2", "--checkpoint", str(tiny_sam3), "--images", "2", "--repeats", "1",
          "--resolution", "32", "--dtype", "bf16", "--compile", "--json", str(out)])
    text = capsys.readouterr().out
    assert re.search(r"batch   1: first call +[\d.]+ s, median +[\d.]+ ms/image, .* peak n/a \(not CUDA\)", text), text
    assert re.search(r"batch 2 / batch 1 time per image: \d+\.\d\d x", text), text
    rows = json.loads(out.read_text())["rows"]
    assert [r["batch_size"] for r in rows] == [1, 2] and all(r["s_per_image_median"] > 0 for r in rows)
    assert all(r["dtype"] == "bf16" and r["compile"] is False and r["peak_gib_above_model"] is None for r in rows)
