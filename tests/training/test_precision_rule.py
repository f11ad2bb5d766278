"""``train.precision: auto`` on a CPU follows the teacher's rule (pipeline.runtime.device.cpu_bf16_native): bf16
autocast where the CPU's flags show native bf16 units and ``ONEDNN_MAX_CPU_ISA`` does not cap oneDNN below them,
fp32 elsewhere; pinned precisions ignore the host."""

from __future__ import annotations

import pytest
import torch

from pipeline.runtime import device

CPU = torch.device("cpu")


@pytest.mark.parametrize("flags, isa, bf16", [
    ({"avx2", "fma"}, None, False),                                    # AVX2 only: bf16 would be emulated
    ({"avx2", "avx512f", "avx512_bf16"}, None, True),                  # avx512_bf16
    ({"avx2", "avx512f", "avx512_bf16", "amx_tile", "amx_bf16"}, None, True),  # AMX
    ({"avx2", "avx512f", "avx512_bf16"}, "AVX2", False),               # capped below bf16 (the AVX2 proxy)
    ({"avx2", "avx512f", "avx512_bf16", "amx_bf16"}, "avx512_core_vnni", False),  # capped below bf16
    ({"avx2", "avx512f", "avx512_bf16"}, "avx512_core_amx", True),     # a cap that keeps bf16 native
    ({"avx2", "fma"}, "ALL", False),                                   # no cap gives units the CPU lacks
])
def test_auto_training_precision_follows_the_teacher_s_rule(monkeypatch, flags, isa, bf16):
    monkeypatch.setattr(device, "cpu_flags", lambda: frozenset(flags))
    if isa is None:
        monkeypatch.delenv("ONEDNN_MAX_CPU_ISA", raising=False)
    else:
        monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", isa)
    assert device.autocast_dtype(CPU, "auto") == (torch.bfloat16 if bf16 else None)
    assert device.teacher_cpu_dtype() == ("bf16" if bf16 else "fp32")   # one rule for both
    assert device.autocast_dtype(CPU, "fp32") is None                    # pinned: whatever the host
    assert device.autocast_dtype(CPU, "bf16") == torch.bfloat16
