"""The one engine registry (pipeline.deploy.engines): segment and the benchmark name their engines from it,
one row per engine, old names accepted everywhere, and an engine gives the same logits whichever of them loads it."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import yaml
from click.testing import CliRunner

from pipeline.catalog import META_FILE
from pipeline.deploy import benchmark as bench
from pipeline.deploy.bundle import DEPLOY_JSON
from pipeline.deploy.engines import ENGINES, Source, unavailable
from pipeline.engine_table import ENGINE_ALIASES, ENGINE_TABLE, MODEL_ENGINES, SEGMENT_ENGINES, engine_name
from pipeline.engine_table import ENGINE_CHOICES as SEGMENT_CHOICES
from pipeline.deploy.segmenter import load_segmenter, resolve_engine
from pipeline.runtime.errors import InputError
from pipeline.evaluation.inference import images_to_tensor
from pipeline.params import BENCHMARK_VARIANTS, load_params
from tests.builders.deploy import HAS_ONNX, PARAMS, RES, make_checkpoint, tiny_model


def test_every_engine_name_is_one_registry_entry():
    assert set(SEGMENT_ENGINES) | set(BENCHMARK_VARIANTS) == set(ENGINES)
    assert SEGMENT_CHOICES == ("auto", *SEGMENT_ENGINES)
    assert MODEL_ENGINES == ("torch", "cuda")                      # what a checkpoint directory supports
    src = Source(tiny_model(), torch.device("cpu"), RES)
    assert unavailable("cuda_graph_bf16", src).startswith("needs a CUDA device")
    assert unavailable("onnxruntime_fp32", src) is not None         # no model.onnx given
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
    from pipeline.evaluation.inference import load_student

    return load_student(ckpt)[0]


def test_one_row_per_engine_and_every_old_name_points_at_one():
    rows = [(e.loader, tuple(sorted(e.options.items())), e.reads) for e in ENGINE_TABLE.values()]
    assert len(set(rows)) == len(rows)                              # no two rows run the same thing
    for old, new in ENGINE_ALIASES.items():
        assert new in ENGINE_TABLE and old not in ENGINE_TABLE and old not in SEGMENT_CHOICES, old
        assert engine_name(old) == new
    assert [engine_name(n) for n in ENGINE_TABLE] == list(ENGINE_TABLE)


def test_an_old_engine_name_is_accepted_in_python_params_and_the_benchmark(tmp_path):
    ckpt = make_checkpoint(tmp_path / "ck")
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    (bundle / DEPLOY_JSON).write_text("{}")
    (bundle / META_FILE).write_text('{"schema": "deploy"}')  # what makes a folder a bundle (is_deploy_bundle)
    assert resolve_engine(bundle, "onnx") == "onnxruntime_fp32" and resolve_engine(bundle, "int8") == "onnxruntime_int8"
    with pytest.raises(InputError, match="onnxruntime_int8: needs a deploy bundle"):
        load_segmenter(ckpt, "int8")
    # params: an old name in a user's params.yaml is read as the engine's name
    text = open(PARAMS).read().replace("onnxruntime_fp32, onnxruntime_int8", "onnx, int8")
    assert "onnx, int8" in text
    (tmp_path / "params.yaml").write_text(text)
    variants = load_params(tmp_path / "params.yaml")["deploy"]["benchmark_variants"]
    assert variants == BENCHMARK_VARIANTS == yaml.safe_load(open(PARAMS))["deploy"]["benchmark_variants"]
    got = load_params(PARAMS, ["deploy.benchmark_variants=[int8,onnxruntime_int8,onnx]"])["deploy"]
    assert got["benchmark_variants"] == ["onnxruntime_int8", "onnxruntime_fp32"]
    # the benchmark: the same engine under either name
    model = tiny_model()
    onnx = None
    if HAS_ONNX:
        from pipeline.deploy.mask_path import export_onnx

        onnx = export_onnx(model, tmp_path / "m.onnx", RES, 17)
    old, skipped_old = bench.build_variants(model, "cpu", RES, ["onnx"], onnx)
    new, skipped_new = bench.build_variants(model, "cpu", RES, ["onnxruntime_fp32"], onnx)
    assert [v.name for v in old] == [v.name for v in new] and skipped_old == skipped_new
    assert set(skipped_old) | {v.name for v in old} == {"onnxruntime_fp32"}
    if old:
        x = images_to_tensor((np.random.default_rng(1).random((2, RES, RES, 3)) * 255).astype(np.uint8))
        np.testing.assert_array_equal(old[0].run(x).numpy(), new[0].run(x).numpy())


def test_segment_help_lists_the_engine_names_and_the_old_ones():
    from pipeline.cli.segment import main

    out = " ".join(CliRunner().invoke(main, ["--help"], terminal_width=200).output.split())
    assert " | ".join(SEGMENT_CHOICES) in out
    assert "also accepted: " + ", ".join(f"{o} = {n}" for o, n in ENGINE_ALIASES.items()) in out
