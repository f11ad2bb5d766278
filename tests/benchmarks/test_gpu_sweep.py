"""The CUDA batch sweep of the efficiency benchmark (pipeline.deploy.benchmark), its logic on the CPU:
which batches are tried, the stop at the first out-of-memory batch (a fake engine raises
torch.cuda.OutOfMemoryError), the best batch, and what the run records and prints."""

from __future__ import annotations

import pytest
import torch

from pipeline.deploy import benchmark as B
from tests.builders.deploy import tiny_model


def test_cuda_sweeps_powers_of_two_to_256_and_a_cpu_keeps_the_configured_batches():
    assert B.throughput_batches([1, 4, 16], "cpu") == [1, 4, 16]
    assert B.throughput_batches([16, 4, 1], "cuda") == [1, 2, 4, 8, 16, 32, 64, 128, 256]
    assert B.throughput_batches([3, 512], "cuda:0") == [1, 2, 3, 4, 8, 16, 32, 64, 128, 256, 512]
    assert B.CUDA_MAX_BATCH == 256


def fake_variant(oom_from: int | None, tried: list[int]) -> B.Variant:
    def run(x):
        tried.append(len(x))
        if oom_from is not None and len(x) >= oom_from:
            raise torch.cuda.OutOfMemoryError("CUDA out of memory. Tried to allocate 9.00 GiB")
        return x[:, :1]
    return B.Variant("fake", "a fake GPU engine", run, "cuda")


@pytest.fixture
def clock(monkeypatch):
    """time_calls with a fixed cost per call: 1 ms + 0.1 ms per image (images/s grows with the batch)."""
    def time_calls(fn, x, warmup, iters, sync):
        fn(x)
        return [1e-3 + 1e-4 * len(x)] * iters
    monkeypatch.setattr(B, "time_calls", time_calls)


def test_the_sweep_stops_at_the_first_out_of_memory_batch_and_reports_the_best(clock):
    tried: list[int] = []
    g = torch.Generator().manual_seed(0)
    sweep = B.throughput_sweep(fake_variant(64, tried), 3, 4, B.throughput_batches([1, 4, 16], "cuda"), 4, g)
    assert sorted(set(tried)) == [1, 2, 4, 8, 16, 32, 64]  # 128 and 256 are never tried
    assert sweep.oom_batch == 64 and list(sweep.images_per_s) == [1, 2, 4, 8, 16, 32]
    assert sweep.batch == 32 and sweep.best == pytest.approx(32 / (1e-3 + 32e-4))
    assert sweep.record()["oom_batch"] == 64 and sweep.record()["images_per_s"]["32"] == sweep.best
    full = B.throughput_sweep(fake_variant(None, []), 3, 4, B.throughput_batches([1], "cuda"), 4, g)
    assert full.oom_batch is None and full.batch == 256 and len(full.images_per_s) == 9
    with pytest.raises(torch.cuda.OutOfMemoryError):  # not even batch 1 fits: nothing to report
        B.throughput_sweep(fake_variant(1, []), 3, 4, [1, 2], 4, g)
    info = {"batches": [1, 4, 16], "throughput_sweep": {"fake": sweep.record(), "cpu_only": {
        "images_per_s": {"1": 10.0, "4": 30.0}, "best_batch": 4, "oom_batch": None}}}
    line = B.format_sweep(info)
    assert line.startswith("throughput sweep fake (batch: images/s): 1: 909") and "best at batch 32" in line
    assert "batch 64 ran out of memory" in line and "cpu_only" not in line


def test_measure_variants_records_the_sweep_on_the_cpu():
    rows, info = B.measure_variants(tiny_model(), resolution=16, device="cpu", variants=["fp32_eager_nchw"],
                                    warmup=1, iters=2, batches=[1, 2])
    sweep = info["throughput_sweep"]["fp32_eager_nchw"]
    assert list(sweep["images_per_s"]) == ["1", "2"] and sweep["oom_batch"] is None
    assert rows[0]["batch"] == sweep["best_batch"] and rows[0]["throughput"] == sweep["images_per_s"][str(rows[0]["batch"])]
    assert B.format_sweep(info) == ""  # nothing beyond the configured batches: the table says it all
