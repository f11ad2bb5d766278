"""The int8 bundle gives the same masks on every x86 CPU: its weights cannot saturate the int16 pair sums
of CPUs without VNNI, and OpenVINO restricted to AVX2 (``ONEDNN_MAX_CPU_ISA=AVX2``) computes the host's
logits exactly and the golden pair's masks."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from pipeline.deploy.bundle import INT8_FILE

from pipeline.deploy.mask_path import ONNX_INPUT, export_onnx, ort_session

from pipeline.deploy.quantize import quantize_onnx_int8
from pipeline.deploy import quantize
from pipeline.deploy.bundle import golden_frame
from pipeline.deploy.openvino_engine import OpenVinoRunner, openvino_unavailable_reason
from pipeline.runtime.errors import InputError
from pipeline.model import TinyUNet
from tests.builders.deploy import HAS_ONNX, int8_settings, make_artifacts, make_checkpoint, run_export

pytestmark = pytest.mark.skipif(not HAS_ONNX, reason="needs onnx + onnxruntime (the onnx extra)")
HAS_OPENVINO = openvino_unavailable_reason() is None
RES = 64


def conv_weights(path) -> list[np.ndarray]:
    """The integer weights of every quantised convolution of an int8 QDQ model."""
    import onnx
    from onnx import numpy_helper

    graph = onnx.load(str(path)).graph
    init = {t.name: numpy_helper.to_array(t) for t in graph.initializer}
    producer = {o: n for n in graph.node for o in n.output}
    out = []
    for node in graph.node:
        if node.op_type == "Conv" and not set(node.output) & {o.name for o in graph.output}:
            dq = producer.get(node.input[1])
            assert dq is not None and dq.op_type == "DequantizeLinear", "every convolution's weight is quantised"
            out.append(init[dq.input[0]])
    return out


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """A full-width random TinyUNet's fp32 ONNX file and its int8 files with 7- and 8-bit weights."""
    root = tmp_path_factory.mktemp("isa")
    torch.manual_seed(0)
    model = TinyUNet().eval()
    for mod in model.modules():
        if isinstance(mod, torch.nn.BatchNorm2d):
            mod.running_mean.uniform_(-0.2, 0.2)
            mod.running_var.uniform_(0.5, 1.5)
    fp32 = export_onnx(model, root / "m.onnx", RES, 17)
    rng = np.random.default_rng(1)
    calib = np.stack([golden_frame(RES)] + [np.clip(rng.normal(120, 80, (RES, RES, 3)), 0, 255).astype(np.uint8)
                                            for _ in range(5)])
    q7 = quantize_onnx_int8(fp32, root / "q7.onnx", calib, int8_settings())
    q8 = quantize_onnx_int8(fp32, root / "q8.onnx", calib, int8_settings(int8_weight_bits=8))
    x = calib.transpose(0, 3, 1, 2).astype(np.float32) / np.float32(255)
    return {"q7": q7, "q8": q8, "x": x}


def test_default_weights_cannot_saturate_an_int16_pair_sum(models):
    """u8 x s8 kernels without VNNI add two products into int16: 2 * 255 * |w| <= 32767 needs |w| <= 64.
    The mask head (the convolution that writes the logits) stays fp32."""
    import onnx

    graph = onnx.load(str(models["q7"])).graph
    head = [n for n in graph.node if n.op_type == "Conv" and n.output[0] == graph.output[0].name]
    assert len(head) == 1 and quantize.output_convolutions(models["q7"]) == [head[0].name]
    assert head[0].input[1] in {t.name for t in graph.initializer}  # a float weight, no DequantizeLinear
    w7 = conv_weights(models["q7"])
    assert w7 and all(w.dtype == np.int8 for w in w7)
    assert max(int(np.abs(w.astype(int)).max()) for w in w7) <= 64
    assert all(2 * 255 * int(np.abs(w.astype(int)).max()) <= np.iinfo(np.int16).max for w in w7)
    # the 8-bit setting uses the full range, which the check above would catch
    assert max(int(np.abs(w.astype(int)).max()) for w in conv_weights(models["q8"])) > 64
    with pytest.raises(InputError, match="deploy.int8_weight_bits=6"):  # the schema's rule, before any file
        int8_settings(int8_weight_bits=6)


def test_host_isa_reads_the_widest_dot_product_set():
    assert quantize.host_isa({"avx2", "avx512f", "avx512_vnni", "amx_int8"}) == "amx_int8"
    assert quantize.host_isa({"avx2", "avx512f", "avx512_vnni"}) == "avx512_vnni"
    assert quantize.host_isa({"avx2", "avx512f", "avx512bw"}) == "avx2"
    assert quantize.host_isa({"sse4_2"}) == "baseline"


@pytest.mark.skipif(not HAS_OPENVINO, reason="needs openvino (the openvino extra)")
def test_avx2_gives_the_host_logits_with_7_bit_weights(models):
    native = OpenVinoRunner(models["q7"], threads=1)(models["x"])
    avx2 = quantize.openvino_logits(models["q7"], models["x"], "AVX2")
    np.testing.assert_array_equal(avx2, native)
    if quantize.host_isa() != "avx2":  # on a VNNI host the full 8-bit range saturates under AVX2
        assert not np.array_equal(quantize.openvino_logits(models["q8"], models["x"], "AVX2"),
                                  OpenVinoRunner(models["q8"], threads=1)(models["x"]))


@pytest.mark.skipif(not HAS_OPENVINO, reason="needs openvino (the openvino extra)")
def test_the_bundle_states_and_meets_its_instruction_sets(tmp_path):
    """Export checks the int8 masks on the host and under AVX2, records both in contract.json, and the
    bundle's int8 model under AVX2 reproduces its golden mask within the int8 gate."""
    ckpt = make_checkpoint(tmp_path / "ckpt", seed=3)
    art = make_artifacts(tmp_path / "art")
    r = run_export(ckpt, tmp_path / "deploy", "--tau", "0.5", "--artifacts", str(art),
                   "--set", "deploy.int8_min_mask_iou=0.5")
    assert r.exit_code == 0, r.output
    bundle = tmp_path / "deploy"
    contract = json.loads((bundle / "contract.json").read_text())
    isas = [c["isa"] for c in contract["int8"]["verified_on"]]
    assert isas == [quantize.host_isa(), "avx2"] and contract["int8"]["model"] == INT8_FILE
    assert "7-bit" in contract["int8"]["quantization"]
    golden = np.load(bundle / "golden_input.npy")[None].transpose(0, 3, 1, 2).astype(np.float32) / np.float32(255)
    z = quantize.openvino_logits(bundle / INT8_FILE, golden, "AVX2")
    ort = ort_session(bundle / INT8_FILE).run(None, {ONNX_INPUT: golden})[0]
    mask = np.load(bundle / "golden_mask.npy")
    rep = quantize.int8_agreement(mask[None, None].astype(np.float64) * 2 - 1, z, 0.5, 0.5)
    assert rep["passed"], rep
    # ONNX Runtime on this host and OpenVINO under AVX2 draw the same mask (they requantise differently)
    assert quantize.int8_agreement(ort, z, 0.5, 0.99)["passed"]
