"""Smoke test of ``benchmarks.bench_teacher --roofline`` on the tiny random SAM 3: every row of the table
printed and written as JSON (FLOPs by module, per-module times and op-kind shares of the two defaults, host
limits, round-robin medians of the four paths, the ratios, the gate of both engines, and whether the torch
engine gave the answers of 3056231's default)."""

from __future__ import annotations

import json
import re

import pytest

pytest.importorskip("transformers")


def test_roofline_prints_and_writes_its_table(tmp_path, capsys, tiny_sam3):
    from benchmarks.bench_teacher import DEFAULT, FP32, OLD_DEFAULT, OTHER_ENGINES, TORCH_ENGINE, engine_path, main

    out = tmp_path / "roofline.json"
    main(["--roofline", "--checkpoint", str(tiny_sam3), "--images", "1", "--repeats", "2", "--resolution", "32",
          "--no-warmup", "--dtype", "bf16", "--json", str(out)])
    text = capsys.readouterr().out
    for pattern in (r"limits \(measured 2048\^3 matmul, best / median\): fp32 \d+ / \d+ GFLOP/s",
                    r"FLOPs per image, 6 prompts: .*backbone [\d.]+ G.*; text once per run [\d.e+-]+ G",
                    r"per-module wall time, default at 3056231 ", r"per-module wall time, default ",
                    r"per-module wall time, torch attention ",
                    r"shares of self CPU time: attention \d+% \([\d.]+ s\), matmul .*copies .*elementwise",
                    r"fp32 eager +\(fp32\): median +[\d.]+ s/image",
                    r"default \(sam3 torch eager \w+.*on cpu\) / fp32 eager \(medians\): [\d.]+  \(targets <= 0.35 "
                    r"on avx512_bf16", r"torch attention / fp32 eager: [\d.]+",
                    r"fidelity of default vs fp32 eager: mean mask IoU", r"fidelity of torch attention vs fp32 eager",
                    r"torch attention against default at 3056231: answers identical"):
        assert re.search(pattern, text), (pattern, text)
    doc = json.loads(out.read_text())
    base = {FP32, OLD_DEFAULT, TORCH_ENGINE, DEFAULT}
    engines = set(doc["seconds"]) - base  # each other engine that runs here, beside the default's
    assert base <= set(doc["seconds"]) and all(len(v) == 2 for v in doc["seconds"].values())
    assert engines <= {engine_path(e) for e in OTHER_ENGINES}
    assert ("onednn" in doc["paths"][DEFAULT]) != (engine_path("onednn") in engines)  # tried once, default or not
    for k in engines:
        assert k.split()[-1] in doc["paths"][k] and "passes" in doc["fidelity_by_path"][k]
        assert re.search(rf"{k} / fp32 eager \(medians\): [\d.]+; / default: [\d.]+", text), text
    med = doc["median_s_per_image"]
    assert doc["default_over_fp32"] == pytest.approx(med[DEFAULT] / med[FP32])
    assert doc["old_default_over_fp32"] == pytest.approx(med[OLD_DEFAULT] / med[FP32])
    assert doc["torch_attention_identical_to_3056231"] is True  # the savings are exact
    assert doc["default_path"].startswith("sam3 torch eager") and set(doc["op_shares"]) == {OLD_DEFAULT, TORCH_ENGINE,
                                                                                          DEFAULT}
    for shares in doc["op_shares"].values():
        assert set(shares) == {"attention", "matmul", "copies", "elementwise", "other"}
        assert sum(v["share"] for v in shares.values()) == pytest.approx(1.0) and shares["matmul"]["seconds"] > 0
    flops = doc["flops_per_image"]
    assert {"backbone", "detr_encoder", "detr_decoder", "mask_decoder"} <= set(flops) and min(flops.values()) >= 0
    assert flops["backbone"] > 0 and flops["detr_encoder"] > 0 and doc["text_flops_per_run"] > 0
    assert doc["limits"]["fp32_gflops"] > 0 and doc["host"]["load_average_before"]
    assert doc["fidelity"]["pairs"] == 6 and "passes" in doc["fidelity"] and "passes" in doc["fidelity_torch_attention"]


def test_batch_sweep_times_each_batch_and_path_and_writes_it(tmp_path, capsys, tiny_sam3):
    """The GPU script's rows (reports/gpu/run.sh, section teacher) computed on a CPU: per batch size each path's
    first call and its round-robin times, the JSON rewritten per batch; compile is forced off on a CPU and the
    JSON says so; peak memory is CUDA's only (None here)."""
    from benchmarks.bench_teacher import main

    out = tmp_path / "sweep.json"
    main(["--batch-sweep", "1,2", "--checkpoint", str(tiny_sam3), "--paths", "compiled,eager", "--repeats", "2",
          "--resolution", "28", "--dtype", "bf16", "--json", str(out)])
    text = capsys.readouterr().out
    assert re.search(r"batch   1: compiled median +[\d.]+ ms/image, min +[\d.]+, first call +[\d.]+ s, peak n/a "
                     r"\(not CUDA\); eager median", text), text
    assert re.search(r"eager: batch 2 / batch 1 time per image: \d+\.\d\d x", text), text
    doc = json.loads(out.read_text())
    assert doc["finished"] and doc["stopped"] is None and sorted(doc["batches"]) == ["1", "2"]
    assert doc["compile_active"] == {"compiled": False, "eager": False}  # no compile off CUDA, and it says so
    assert doc["dtype_used"] == {"compiled": "bf16", "eager": "bf16"}
    for row in doc["batches"].values():
        for p in row["paths"].values():
            assert len(p["seconds"]) == 2 and 0 < p["ms_per_image_min"] <= p["ms_per_image_median"]
            assert p["first_call_s"] > 0 and p["peak_allocated_bytes"] is None  # no CUDA memory to read on a CPU
        assert row["eager_over_compiled_median"] > 0
    assert doc["parameters"] > 0 and doc["weights_bytes"] == 2 * doc["parameters"]  # bf16


def test_batch_sweep_deadline_stops_before_the_next_batch(tmp_path, capsys, tiny_sam3):
    """run.sh's guard hands the sweep its budget as --deadline: past it no batch starts, and the JSON (read by
    reports/gpu/collect.py) says the sweep stopped at its deadline."""
    from benchmarks.bench_teacher import main

    out = tmp_path / "sweep.json"
    main(["--batch-sweep", "1", "--checkpoint", str(tiny_sam3), "--repeats", "1", "--resolution", "28",
          "--deadline", "0", "--json", str(out)])
    doc = json.loads(out.read_text())
    assert not doc["finished"] and doc["batches"] == {} and doc["stopped"].startswith("deadline")
    assert "stopped: deadline" in capsys.readouterr().out


def test_batch_sweep_refuses_an_unknown_path(tiny_sam3):
    from benchmarks.bench_teacher import main

    with pytest.raises(SystemExit, match="--paths 'fast'"):
        main(["--batch-sweep", "1", "--checkpoint", str(tiny_sam3), "--paths", "fast"])


def test_attention_kernels_times_both_engines_on_tiny_shapes(tmp_path, capsys):
    """``--attention-kernels --shapes tiny``: torch's bf16 attention and OpenVINO's, round-robin, each with its
    GFLOP/s and its error against fp32 (both within bf16 rounding), and their ratio, printed and written."""
    pytest.importorskip("openvino")
    from benchmarks.bench_teacher import main

    out = tmp_path / "kernels.json"
    main(["--attention-kernels", "--shapes", "tiny", "--repeats", "2", "--json", str(out)])
    text = capsys.readouterr().out
    assert re.search(r"tiny 2x2x49x16: torch bf16 median [\d.]+ ms .*openvino bf16 median .*torch / openvino "
                     r"[\d.]+x", text), text
    row = json.loads(out.read_text())["shapes"]["tiny"]
    assert row["shape"] == [2, 2, 49, 16] and row["torch_over_openvino"] > 0
    for engine in ("torch bf16", "openvino bf16"):
        assert 0 < row[engine]["min_s"] <= row[engine]["median_s"] and row[engine]["max_abs_error_vs_fp32"] < 0.02
