"""Issue 19 fast paths on the CPU: the CUDA engine's fallback, device parity, OpenVINO int8, the
benchmark's new variants and remarks, and the SAM 3 teacher's dtype/batch-size rules.

The CUDA code itself (graphs, bf16, fused AdamW, auto batch from free memory) needs a GPU; here its
CPU fallbacks must give exactly the numbers of the paths they replace."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline.deploy import benchmark as bench
from pipeline.deploy.cuda_engine import FastStudent
from pipeline.metrics import mask_agreement
from pipeline.deploy.engines import ENGINES, Source
from pipeline.deploy.segmenter import load_segmenter, resolve_engine
from pipeline.runtime.errors import InputError
from pipeline.evaluation.inference import images_to_tensor
from tests.builders.deploy import HAS_ONNX, RES, int8_settings, make_checkpoint, tiny_model

HAS_OPENVINO = __import__("pipeline.deploy.openvino_engine", fromlist=["x"]).openvino_unavailable_reason() is None


def _images(n=3, size=RES, seed=0):
    return np.random.default_rng(seed).integers(0, 255, (n, size, size, 3), dtype=np.uint8)


# ---- CUDA engine: CPU fallback -----------------------------------------------------------------------
def test_fast_student_cpu_fallback_is_the_torch_engine_bit_for_bit():
    model = tiny_model()
    fast = FastStudent(model, "cpu")
    assert fast.precision == "fp32" and not fast.cuda_graphs        # auto on a CPU; graphs are CUDA-only
    images = _images()
    x = images_to_tensor(images)
    ref = ENGINES["torch"].load(Source(model, torch.device("cpu"))).run(x).numpy()  # eager, channels_last
    np.testing.assert_array_equal(fast.logits(x).numpy(), ref)
    with pytest.raises(InputError, match="precision"):
        FastStudent(model, "cpu", precision="fp8")


def test_auto_engine_is_cuda_on_a_gpu_and_the_cuda_engine_runs_on_a_cpu(tmp_path):
    ckpt = make_checkpoint(tmp_path / "ckpt")
    assert resolve_engine(ckpt, "auto") == "torch"
    assert resolve_engine(ckpt, "auto", "cuda") == "cuda"            # a string: no GPU needed to decide
    assert resolve_engine(ckpt, "cuda") == "cuda"
    with pytest.raises(InputError, match="openvino_int8"):
        resolve_engine(ckpt, "openvino_int8")                       # needs a bundle
    torch_seg = load_segmenter(ckpt, "torch", "cpu")
    cuda_seg = load_segmenter(ckpt, "cuda", "cpu")
    assert cuda_seg.engine == "cuda" and cuda_seg.info["precision"] == "fp32"
    images = _images()
    np.testing.assert_array_equal(cuda_seg.predict_probs(images), torch_seg.predict_probs(images))


def test_device_parity_runs_on_the_cpu_and_reports_identical_masks(tmp_path):
    from pipeline.deploy.mask_path import check_parity, device_parity, export_torchscript

    model = tiny_model()
    ts = export_torchscript(model, tmp_path / "m.ts", RES)
    par = device_parity(model, 0.5, RES, 1e-4, "cpu", ts)
    assert par["torchscript"]["passed"] and par["torchscript"]["mask_iou"] == 1.0
    assert par["fast_engine"]["passed"] and par["fast_engine"]["mask_iou"] == 1.0
    assert par["fast_engine"]["precision"] == "fp32"
    assert "device" not in check_parity(model, 0.5, RES, 1e-4, torchscript=ts, device="cpu")  # CUDA only


def test_mask_agreement_is_mean_per_image_iou():
    a = np.zeros((2, 1, 4, 4), np.float32)
    b = a.copy()
    a[0, 0, :2] = 1.0          # image 0: 8 px vs 4 px -> IoU 0.5
    b[0, 0, :1] = 1.0
    assert mask_agreement(a, b, 0.5) == pytest.approx((0.5 + 1.0) / 2)   # image 1: both empty -> 1


# ---- OpenVINO int8 ------------------------------------------------------------------------------------
@pytest.mark.skipif(not (HAS_OPENVINO and HAS_ONNX), reason="openvino / onnxruntime not installed")
def test_openvino_runs_the_onnx_files_like_onnxruntime(tmp_path):
    from pipeline.deploy import quantize as q8
    from pipeline.deploy.mask_path import export_onnx, ort_session
    from pipeline.deploy.openvino_engine import OpenVinoRunner

    model = tiny_model()
    fp32 = export_onnx(model, tmp_path / "m.onnx", RES, 17)
    x = images_to_tensor(_images(2)).numpy()
    ov = OpenVinoRunner(fp32)
    np.testing.assert_allclose(ov(x), ort_session(fp32).run(None, {"image": x})[0], atol=1e-4)
    assert ov(x[:1]).shape == (1, 1, RES, RES)                     # another shape: compiled again
    int8 = q8.quantize_onnx_int8(fp32, tmp_path / "m8.onnx", _images(8, seed=1), int8_settings())
    z_ort = ort_session(int8).run(None, {"image": x})[0]
    z_ov = OpenVinoRunner(int8)(x)
    assert mask_agreement(z_ov, z_ort, 0.0) > 0.95                 # same int8 model, other kernels
    variants, skipped = bench.build_variants(model, "cpu", RES, ["openvino_int8", "cuda_graph_bf16"],
                                             fp32, int8)
    assert [v.name for v in variants] == ["openvino_int8"] and "CUDA" in skipped["cuda_graph_bf16"]
    np.testing.assert_allclose(variants[0].run(torch.from_numpy(x)).numpy(), z_ov, atol=1e-6)


def test_openvino_engine_needs_its_file_or_its_extra(tmp_path, monkeypatch):
    from tests.builders.deploy import run_export

    ckpt = make_checkpoint(tmp_path / "ckpt")
    assert run_export(ckpt, tmp_path / "deploy", "--tau", "0.5", "--no-int8").exit_code == 0
    import pipeline.deploy.openvino_engine as ove

    monkeypatch.setattr(ove, "openvino_unavailable_reason", lambda: "openvino not importable (extra)")
    with pytest.raises(InputError, match="openvino not importable"):
        load_segmenter(tmp_path / "deploy", "openvino_int8", "cpu")
    monkeypatch.undo()
    if HAS_OPENVINO and HAS_ONNX:
        from pipeline.runtime.errors import ArtifactError

        with pytest.raises(ArtifactError, match="model.int8.onnx"):
            load_segmenter(tmp_path / "deploy", "openvino_int8", "cpu")


# ---- benchmark remarks ------------------------------------------------------------------------------
def test_variant_remark_marks_skipped_and_slow_variants():
    assert bench.variant_remark(bench.OK, 1.0, 1.0) == ""
    slow = bench.variant_remark("slow on this CPU (...)", 100.0, 4.0)
    assert slow.startswith("not timed: probe 100 ms = 25x") and "pathologically slow" in slow
    assert bench.variant_remark("skipped: needs a CUDA device", float("nan"), None) == "not run: needs a CUDA device"


def test_measured_rows_carry_timed_and_remark():
    rows, info = bench.measure_variants(tiny_model(), resolution=RES, variants=["fp32_eager_nchw", "cuda_graph_bf16"],
                                        warmup=0, iters=1, batches=[1])
    assert [r["variant"] for r in rows] == ["fp32_eager_nchw", "cuda_graph_bf16"] and "cuda_graph_bf16" in info["skipped"]
    assert rows[0]["timed"] is True and rows[0]["remark"] == ""
    # the variant the host cannot run is in the table as skipped, with the reason and no numbers
    skipped = rows[1]
    assert skipped["status"] == "skipped: " + info["skipped"]["cuda_graph_bf16"] and skipped["timed"] is False
    assert "CUDA" in skipped["remark"] and np.isnan(skipped["latency_ms"]) and "cuda_graph_bf16" not in info["slow"]
    assert "skipped: needs a CUDA device" in bench.format_table(rows)


def _counting_engines(monkeypatch, names):
    """Replace the loaders of engines ``names`` by ones that count their loads and calls (a fake runner)."""
    import dataclasses

    from pipeline.deploy import engines

    calls = {n: 0 for n in names}

    def loader(name):
        def load(src):
            calls[name] += 1

            def run(x):
                calls[name] += 1
                return torch.zeros(x.shape[0], 1, *x.shape[2:])
            return engines.Runner(run)
        return load
    for n in names:
        monkeypatch.setitem(engines.ENGINES, n, dataclasses.replace(engines.ENGINES[n], load=loader(n)))
    return calls


@pytest.mark.parametrize("flags, native", [({"avx2", "fma"}, False), ({"avx512f", "avx512_vnni"}, False),
                                           ({"avx2", "avx512_bf16"}, True), ({"amx_bf16", "amx_tile"}, True)])
def test_a_bf16_variant_on_a_cpu_without_native_bf16_is_never_called(monkeypatch, flags, native):
    """Issue 44: bf16 on a CPU whose flags lack avx512_bf16 and amx_bf16 is decided from the flags -- never
    loaded, never called -- and is in the table as skipped with the reason; with either flag it is timed."""
    import pipeline.runtime.device

    monkeypatch.setattr(pipeline.runtime.device, "cpu_flags", lambda: frozenset(flags))
    calls = _counting_engines(monkeypatch, ["bf16_autocast", "bf16_channels_last"])
    rows, info = bench.measure_variants(tiny_model(), resolution=RES, variants=list(bench.VARIANTS), warmup=1,
                                        iters=1, batches=[1], slow_factor=1e9)
    by = {r["variant"]: r for r in rows}
    assert set(by) == set(bench.VARIANTS)  # every variant has its row, run or not
    for name in calls:
        if native:
            assert calls[name] > 0 and by[name]["status"] == bench.OK
        else:
            assert calls[name] == 0, f"{name} was called on a CPU without native bf16"
            assert by[name]["status"].startswith("skipped: bf16 is emulated on this CPU")
            assert by[name]["remark"].startswith("not run: bf16 is emulated") and not by[name]["timed"]
    assert "needs a CUDA device" in by["cuda_graph_bf16"]["status"]  # and CUDA on a CPU host, likewise


# ---- SAM 3 teacher: dtype auto, batch size from memory -----------------------------------------------
def test_teacher_dtype_auto_and_batch_size_rules(monkeypatch):
    from pipeline.teachers.sam3 import MAX_AUTO_BATCH, auto_batch_size, resolve_teacher_dtype

    # a CPU without bf16 units (the rule on the flags: tests/teachers/test_teacher_cpu_dtype.py)
    monkeypatch.setattr("pipeline.teachers.sam3.teacher_cpu_dtype", lambda: "fp32")
    assert resolve_teacher_dtype("auto", "cpu") == ("fp32", False)
    assert resolve_teacher_dtype("fp32", "cuda") == ("fp32", False)   # as asked: no TF32
    assert resolve_teacher_dtype("bf16", "cpu") == ("bf16", False)
    with pytest.raises(InputError, match="teacher.dtype"):
        resolve_teacher_dtype("fp16", "cpu")
    gib = 2 ** 30
    assert auto_batch_size("cuda", used_bytes=2 * gib, free_bytes=30 * gib) == 10      # 0.7 * 30 / 2
    assert auto_batch_size("cuda", used_bytes=2 * gib, free_bytes=1 * gib) == 1
    assert auto_batch_size("cuda", used_bytes=1, free_bytes=80 * gib) == MAX_AUTO_BATCH
    assert auto_batch_size("cpu") == 2


def test_teacher_auto_defaults_answer_like_fp32_on_the_cpu(tmp_path, monkeypatch):
    """On a CPU without bf16 units, ``auto`` is fp32 eager: the same answers and cache entries."""
    pytest.importorskip("transformers")
    monkeypatch.setattr("pipeline.teachers.sam3.teacher_cpu_dtype", lambda: "fp32")
    from pipeline.teachers.base import TeacherInput
    from pipeline.teachers.sam3 import Sam3Teacher
    from pipeline.teachers.tiny_sam3 import build_tiny_sam3

    prompts = ["spacecraft", "satellite"]
    ckpt = build_tiny_sam3(tmp_path / "tiny", words=("spacecraft", "satellite"))
    items = [TeacherInput(f"i{k}", f"s{k}", im) for k, im in enumerate(_images(3, 40, seed=2))]
    auto = Sam3Teacher(ckpt, device="cpu", resolution=(40, 40), score_threshold=0.0, compile=True)
    fp32 = Sam3Teacher(ckpt, device="cpu", dtype="fp32", batch_size=2, resolution=(40, 40), score_threshold=0.0)
    assert auto.dtype_name == "fp32" and not auto.tf32 and auto.batch_size == 2 and not auto.compile
    assert auto.fingerprint() == fp32.fingerprint()                    # the same cache entries
    (m1, s1), (m2, s2) = auto.predict(items, prompts), fp32.predict(items, prompts)
    np.testing.assert_array_equal(m1, m2)
    np.testing.assert_array_equal(s1, s2)
