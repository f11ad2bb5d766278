"""``teacher.engine``: SAM 3's bf16 attention in OpenVINO's fused CPU kernel (pipeline/teachers/attention.py).

The rule of ``auto`` reads CPU flags; the OpenVINO function gives torch's attention within bf16 rounding in
every memory layout and with either kind of mask SAM 3 passes, hands every call it does not take to transformers'
own SDPA, and leaves transformers'
interface as it found it; the torch engine's fingerprint is the one from before the setting. The fidelity gate
on the fitted tiny SAM 3 runs with both engines in test_teacher_cpu_dtype.py."""

from __future__ import annotations

import logging

import pytest

from pipeline.runtime import device
from pipeline.runtime.errors import InputError
from pipeline.teachers import attention
from pipeline.teachers.attention import OpenVINOAttention, attention_engine, resolve_teacher_engine

torch = pytest.importorskip("torch")
F = torch.nn.functional
AVX512_BF16 = frozenset({"avx2", "avx512f", "avx512_bf16"})


@pytest.mark.parametrize("flags, vendor, dtype, expect", [
    (AVX512_BF16, "AuthenticAMD", "bf16", "openvino"),                   # measured: OpenVINO's attention is faster
    (AVX512_BF16, "GenuineIntel", "bf16", "torch"),                      # measured (AMX capped away): it is slower
    (AVX512_BF16 | {"amx_tile", "amx_bf16"}, "GenuineIntel", "bf16", "onednn"),  # AMX: torch's attention, fused MLPs
    (AVX512_BF16 | {"amx_tile", "amx_bf16"}, "GenuineIntel", "fp32", "torch"),   # AMX, pinned fp32: torch
    ({"avx2", "fma"}, "GenuineIntel", "fp32", "torch"),                  # AVX2: fp32 teacher, torch
    (AVX512_BF16, "AuthenticAMD", "fp32", "torch"),                      # a pinned fp32 stays in torch
])
def test_auto_follows_the_cpu_flags(monkeypatch, flags, vendor, dtype, expect):
    monkeypatch.delenv("ONEDNN_MAX_CPU_ISA", raising=False)
    monkeypatch.setattr(device, "cpu_flags", lambda: frozenset(flags))
    monkeypatch.setattr(device, "cpu_vendor", lambda: vendor)
    monkeypatch.setattr(attention, "openvino_version", lambda: "2026.4.1")
    assert device.teacher_cpu_engine(dtype) == expect
    assert resolve_teacher_engine("auto", "cpu", dtype) == (expect, None)
    assert resolve_teacher_engine("torch", "cpu", dtype) == ("torch", None)


def test_what_cannot_run_in_openvino_runs_in_torch_and_says_so_in_one_line(monkeypatch):
    monkeypatch.setattr(device, "cpu_flags", lambda: AVX512_BF16)
    monkeypatch.setattr(attention, "openvino_version", lambda: None)
    engine, note = resolve_teacher_engine("openvino", "cpu", "bf16")
    assert engine == "torch" and "openvino is not installed" in note and "\n" not in note
    assert resolve_teacher_engine("auto", "cpu", "bf16")[0] == "torch"
    monkeypatch.setattr(attention, "openvino_version", lambda: "2026.4.1")
    engine, note = resolve_teacher_engine("openvino", "cpu", "fp32")
    assert engine == "torch" and "bf16 attention only" in note
    with pytest.raises(InputError, match="teacher.engine='onnx'"):
        resolve_teacher_engine("onnx", "cpu", "bf16")


def test_an_amx_cpu_capped_below_amx_runs_as_an_intel_avx512_bf16_one(monkeypatch):
    """Capped below AMX, an Intel AMX CPU is an Intel avx512_bf16 one: a pinned bf16 runs torch's attention there
    (OpenVINO's was slower on it: docs/performance.md), and ``auto`` gives fp32 anyway."""
    monkeypatch.setattr(device, "cpu_flags", lambda: AVX512_BF16 | {"amx_tile", "amx_bf16"})
    monkeypatch.setattr(device, "cpu_vendor", lambda: "GenuineIntel")
    monkeypatch.setattr(attention, "openvino_version", lambda: "2026.4.1")
    for isa, expect in (("AVX512_CORE_AMX", "onednn"), ("", "onednn"), ("AVX512_CORE_BF16", "torch")):
        monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", isa)
        assert device.teacher_cpu_engine("bf16") == expect, isa


def test_what_cannot_run_fused_by_onednn_runs_in_torch_and_says_so_in_one_line(monkeypatch):
    assert resolve_teacher_engine("onednn", "cpu", "bf16") == ("onednn", None)  # this torch has the fused layer
    for dtype_name, device_name, why in (("fp32", "cpu", "bf16 MLPs only"), ("bf16", "cuda", "CPU only")):
        engine, note = resolve_teacher_engine("onednn", device_name, dtype_name)
        assert engine == "torch" and why in note and "\n" not in note
    monkeypatch.setattr(attention, "onednn_fusion_available", lambda: False)
    engine, note = resolve_teacher_engine("onednn", "cpu", "bf16")
    assert engine == "torch" and "fused activation" in note and "\n" not in note
    monkeypatch.setattr(device, "cpu_flags", lambda: AVX512_BF16 | {"amx_tile", "amx_bf16"})
    assert resolve_teacher_engine("auto", "cpu", "bf16")[0] == "torch"  # auto on AMX without the op: torch


def test_the_fingerprint_and_path_name_the_engine_and_the_torch_engine_keeps_its_fingerprint(tiny_sam3, monkeypatch,
                                                                                          caplog):
    from pipeline.teachers.sam3 import Sam3Teacher

    monkeypatch.setattr(device, "cpu_flags", lambda: AVX512_BF16)
    monkeypatch.setattr(device, "cpu_vendor", lambda: "AuthenticAMD")
    monkeypatch.setattr(attention, "openvino_version", lambda: "2026.4.1")
    kw = dict(device="cpu", dtype="bf16", resolution=(40, 40))
    ov, pinned = Sam3Teacher(tiny_sam3, engine="auto", **kw), Sam3Teacher(tiny_sam3, engine="torch", **kw)
    fp = pinned.fingerprint()
    assert set(fp) == {"backend", "checkpoint", "dtype", "resolution", "score_threshold", "mask_threshold",
                       "text_max_length"}   # the keys from before teacher.engine: no cached answer is lost
    assert ov.fingerprint() == {**fp, "engine": "openvino attention", "openvino": "2026.4.1"}
    assert ov.path() == "sam3 torch eager bf16 + openvino attention on cpu"
    assert pinned.path() == "sam3 torch eager bf16 on cpu"
    monkeypatch.setattr(attention, "openvino_version", lambda: None)
    fallen = Sam3Teacher(tiny_sam3, engine="openvino", **kw)
    assert fallen.engine == "torch" and fallen.fingerprint() == fp
    with caplog.at_level(logging.WARNING):
        fallen.load()
    assert [r.getMessage() for r in caplog.records if "openvino" in r.getMessage()] == [f"sam3: {fallen.engine_note}"]
    monkeypatch.setattr(device, "cpu_flags", lambda: AVX512_BF16 | {"amx_tile", "amx_bf16"})
    fused = Sam3Teacher(tiny_sam3, engine="auto", **kw)
    assert fused.fingerprint() == {**fp, "engine": "onednn fused MLP activations"}
    assert fused.path() == "sam3 torch eager bf16 + onednn fused MLP activations on cpu"
    assert "set teacher.engine: torch to keep them" in fused.cache_note()


def _reference(q, k, v, scale):
    return F.scaled_dot_product_attention(q.float(), k.float(), v.float(), scale=scale).transpose(1, 2)


@pytest.mark.parametrize("layout", ["bnhd", "bhnd", "strided"])
def test_openvino_attention_matches_torch_in_every_layout(layout):
    pytest.importorskip("openvino")
    g = torch.Generator().manual_seed(0)
    b, h, n, m, d = 2, 4, 37, 53, 16   # query and key lengths differ (cross-attention)

    def make(length):
        if layout == "bnhd":   # a [B, N, H, D] projection viewed as heads: no copy
            return torch.randn(b, length, h, d, generator=g).bfloat16().transpose(1, 2)
        t = torch.randn(b, h, length, d, generator=g).bfloat16()
        return t if layout == "bhnd" else t[..., ::1, :].transpose(2, 3).contiguous().transpose(2, 3)
    q, k, v = make(n), make(m), make(m)
    calls = []
    fn = OpenVINOAttention(lambda *a, **kw: calls.append(a), threads=1)
    out, weights = fn(torch.nn.Identity(), q, k, v, scaling=0.3)
    assert weights is None and not calls and out.dtype == torch.bfloat16 and out.shape == (b, n, h, d)
    ref = _reference(q, k, v, 0.3)
    torch_bf16 = F.scaled_dot_product_attention(q, k, v, scale=0.3).transpose(1, 2).float()
    # within bf16 rounding of the output: a few units of its last place, like torch's own bf16 kernel
    assert (out.float() - ref).abs().max() <= 4 * (torch_bf16 - ref).abs().max() + 2 ** -8
    default_scale, _ = fn(torch.nn.Identity(), q, k, v)
    assert torch.allclose(default_scale.float(), _reference(q, k, v, d ** -0.5), atol=2e-2)


@pytest.mark.parametrize("kind", ["bool", "bias"])
def test_openvino_attention_applies_sam3s_masks_as_torch_does(kind):
    """The DETR encoder's text padding (boolean, True = attend, broadcast over heads) and the DETR decoder's box
    bias (additive bf16 per head): the same attention as torch's within bf16 rounding."""
    pytest.importorskip("openvino")
    g = torch.Generator().manual_seed(1)
    b, h, n, m, d = 2, 4, 21, 33, 16
    q, k, v = (torch.randn(b, h, length, d, generator=g).bfloat16() for length in (n, m, m))
    if kind == "bool":
        mask = torch.rand(b, 1, n, m, generator=g) > 0.4
        mask[..., 0] = True                        # every query attends to something, as with text padding
    else:
        mask = (torch.randn(b, h, n, m, generator=g) * 3).bfloat16()
    calls = []
    fn = OpenVINOAttention(lambda *a, **kw: calls.append(a), threads=1)
    out, _ = fn(torch.nn.Identity(), q, k, v, attention_mask=mask, scaling=0.25)
    ref = F.scaled_dot_product_attention(q.float(), k.float(), v.float(), attn_mask=mask if kind == "bool"
                                         else mask.float(), scale=0.25).transpose(1, 2)
    torch_bf16 = F.scaled_dot_product_attention(q, k, v, attn_mask=mask, scale=0.25).transpose(1, 2).float()
    assert not calls and out.shape == (b, n, h, d)
    assert (out.float() - ref).abs().max() <= 4 * (torch_bf16 - ref).abs().max() + 2 ** -8


def test_calls_it_does_not_take_go_to_transformers_sdpa_and_the_interface_is_restored():
    from transformers.modeling_utils import ALL_ATTENTION_FUNCTIONS

    calls = []
    fn = OpenVINOAttention(lambda module, q, k, v, mask, **kw: calls.append((q.dtype, mask is not None, kw)) or
                           ("fallback", None), threads=1)
    q = torch.randn(1, 2, 5, 8).bfloat16()
    module = torch.nn.Identity()
    assert fn(module, q, q, q, attention_mask=torch.zeros(1, 1, 5, 5))[0] == "fallback"   # an fp32 bias
    assert fn(module, q.float(), q.float(), q.float())[0] == "fallback"                  # fp32: bit for bit torch
    assert fn(module, q, q, q, dropout=0.1)[0] == "fallback"
    assert fn(module, q, q, q, is_causal=True)[0] == "fallback"
    assert fn(module, q, q[:, :1], q[:, :1])[0] == "fallback"                            # grouped heads
    assert [c[:2] for c in calls] == [(torch.bfloat16, True), (torch.float32, False)] + [(torch.bfloat16, False)] * 3
    before = ALL_ATTENTION_FUNCTIONS["sdpa"]
    with attention_engine(fn):
        assert ALL_ATTENTION_FUNCTIONS["sdpa"] is fn
    assert ALL_ATTENTION_FUNCTIONS["sdpa"] is before
    with attention_engine(None):
        assert ALL_ATTENTION_FUNCTIONS["sdpa"] is before
