"""The one engine registry (pipeline.deploy.engines): segment and the benchmark name their engines from it,
and an engine gives the same logits whichever of them loads it."""

from __future__ import annotations

import numpy as np
import torch

from pipeline.deploy import benchmark as bench
from pipeline.deploy.engines import ENGINES, MODEL_ENGINES, SEGMENT_ENGINES, Source, unavailable
from pipeline.engine_table import ENGINE_CHOICES as SEGMENT_CHOICES
from pipeline.deploy.segmenter import load_segmenter
from pipeline.inference import images_to_tensor
from pipeline.params import BENCHMARK_VARIANTS
from tests._tiny_deploy import RES, make_checkpoint, tiny_model


def test_every_engine_name_is_one_registry_entry():
    assert set(SEGMENT_ENGINES) | set(BENCHMARK_VARIANTS) == set(ENGINES)
    assert SEGMENT_CHOICES == ("auto", *SEGMENT_ENGINES)
    assert MODEL_ENGINES == ("torch", "cuda")                      # what a checkpoint directory supports
    src = Source(tiny_model(), torch.device("cpu"), RES)
    assert unavailable("cuda_graph_bf16", src).startswith("needs a CUDA device")
    assert unavailable("onnx", src) is not None                     # no model.onnx given
    assert unavailable("fp32_eager_nchw", src) is None


def test_segmenter_and_benchmark_run_the_same_engine_alike(tmp_path):
    """segment's ``torch`` engine on a CPU is the benchmark's ``fp32_channels_last``: identical logits."""
    ckpt = make_checkpoint(tmp_path / "ck")
    seg = load_segmenter(ckpt, "torch", "cpu")
    images = (np.random.default_rng(0).random((3, RES, RES, 3)) * 255).astype(np.uint8)
    x = images_to_tensor(images)
    (variant,), skipped = bench.build_variants(seg_model(ckpt), "cpu", RES, ["fp32_channels_last"])
    assert not skipped and variant.device == "cpu"
    np.testing.assert_array_equal(seg.predict_logits(x), variant.run(x).numpy())


def seg_model(ckpt):
    from pipeline.inference import load_student

    return load_student(ckpt)[0]
