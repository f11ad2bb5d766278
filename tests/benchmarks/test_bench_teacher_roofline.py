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
