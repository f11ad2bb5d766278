"""bench_train at a tiny size, each variant in a process of its own (and, ``--in-process``, all in this one): it times
fp32 eager NCHW against ``distill``'s resolved settings, and its one-step profile adds up and counts the FLOPs of a
training step (no timing is asserted)."""

from __future__ import annotations

import math

import pytest
import torch


def test_bench_train_times_distill_s_settings_and_profiles_one_step():
    from torch.utils.flop_counter import FlopCounterMode

    from benchmarks import bench_train
    from pipeline.profiles import load_profile
    from pipeline.runtime.device import autocast_dtype, reuse_freed_memory

    threads = torch.get_num_threads()
    try:
        out = bench_train.main(["--images", "4", "--sizes", "32", "--reps", "1", "--profile-size", "32",
                                "--profile-steps", "2", "--threads", "1", "--set", "train.channels=[4,8,16]"])
    finally:
        torch.set_num_threads(threads)
    distill = load_profile("distill")["train"]
    assert out["timed_in"] == "a process per variant" and out["heap_reuse"] == reuse_freed_memory()
    assert out["batch_size"] == distill["batch_size"]
    assert out["settings"] == {"fp32 eager NCHW": {"precision": "fp32", "channels_last": False},
                               "distill": {"precision": distill["precision"],
                                           "channels_last": distill["channels_last"]}}
    rows = out["sizes"]["32"]["variants"]
    amp = autocast_dtype(torch.device("cpu"), distill["precision"])
    assert rows["distill"]["autocast"] == (str(amp).replace("torch.", "") if amp is not None else "fp32")
    assert rows["fp32 eager NCHW"]["autocast"] == "fp32"
    for r in rows.values():
        assert len(r["epoch_seconds"]) == 1 and r["min_seconds"] <= r["median_seconds"]
        assert r["images_per_second"] == pytest.approx(4 / r["median_seconds"]) and math.isfinite(r["loss_after"])
    profile = out["profile"]["variants"]
    model = bench_train.open_run(bench_train.variants(["train.channels=[4,8,16]"])["fp32 eager NCHW"],
                                 bench_train.train_data(*bench_train.synthetic_set(8, 32, 0)), "cpu", 0).model
    with FlopCounterMode(display=False) as forward:
        model.forward_train(torch.rand(distill["batch_size"], 3, 32, 32))
    for v in profile.values():
        phases = v["phases"]
        assert set(phases) == {*bench_train.PHASES, "step"} and all(t >= 0 for t in phases.values())
        # a training step's forward + backward: about three forwards (the backward computes two products a layer)
        assert 2.5 <= v["gflop_per_step"] * 1e9 / forward.get_total_flops() <= 3.5
        assert v["limit_seconds"] == pytest.approx(v["gflop_per_step"] / v["peak_gflops"])


def test_bench_train_times_distill_s_settings_at_other_batch_sizes():
    from benchmarks import bench_train
    from pipeline.profiles import load_profile

    own = load_profile("distill")["train"]["batch_size"]
    threads = torch.get_num_threads()
    try:
        out = bench_train.main(["--images", "4", "--sizes", "32", "--reps", "1", "--profile-size", "0",
                                "--threads", "1", "--set", "train.channels=[4,8,16]", "--batches", "2", str(own),
                                "--in-process"])
    finally:
        torch.set_num_threads(threads)
    rows, size = out["sizes"]["32"]["variants"], out["sizes"]["32"]
    # the profile's own batch is not timed twice; batch 2 is distill's settings at that batch
    assert set(rows) == {"fp32 eager NCHW", "distill", bench_train.batch_variant(2)}
    assert out["settings"][bench_train.batch_variant(2)] == out["settings"]["distill"]
    other = rows[bench_train.batch_variant(2)]
    assert other["batch_size"] == 2 and rows["distill"]["batch_size"] == own
    assert other["seconds_per_step"] == pytest.approx(other["median_seconds"] / 2)  # 4 images, 2 a step
    assert size["batch_speedup_median"][bench_train.batch_variant(2)] == pytest.approx(
        rows["fp32 eager NCHW"]["median_seconds"] / other["median_seconds"])


def test_a_variant_process_that_fails_raises_here_with_its_error():
    from benchmarks import bench_train

    one = bench_train.process_timer({"precision": "fp32"}, 16, 2, 0, "cpu", 1)  # no other train key: it fails
    with pytest.raises(RuntimeError, match="bench_train worker .*KeyError"):
        one(0)
    one.close()
