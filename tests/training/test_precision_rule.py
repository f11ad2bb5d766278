"""``train.precision: auto`` on a CPU follows the teacher's rule (pipeline.runtime.device.cpu_bf16_pays_off): bf16
autocast where oneDNN runs bf16 on AMX, or on avx512_bf16 from a vendor measured to gain from it, and
``ONEDNN_MAX_CPU_ISA`` does not cap oneDNN below them, fp32 elsewhere; pinned precisions ignore the host."""

from __future__ import annotations

import pytest
import torch

from pipeline.runtime import device

CPU = torch.device("cpu")


AMD, INTEL = "AuthenticAMD", "GenuineIntel"
AVX512_BF16 = {"avx2", "avx512f", "avx512_bf16"}
AMX = AVX512_BF16 | {"amx_tile", "amx_bf16"}


@pytest.mark.parametrize("flags, vendor, isa, bf16", [
    ({"avx2", "fma"}, INTEL, None, False),                   # AVX2 only: bf16 would be emulated
    (AVX512_BF16, AMD, None, True),                          # avx512_bf16 on the EPYC: bf16 matmuls 4x fp32's
    (AVX512_BF16, INTEL, None, False),                       # Intel without AMX: its bf16 matmuls half fp32's
    (AMX, INTEL, None, True),                                # AMX
    (AMX, INTEL, "AVX512_CORE_BF16", False),                 # AMX capped away: Intel's avx512_bf16 path
    (AVX512_BF16, AMD, "AVX2", False),                       # capped below bf16 (the AVX2 proxy)
    (AMX, INTEL, "avx512_core_vnni", False),                 # capped below bf16
    (AVX512_BF16, AMD, "avx512_core_amx", True),             # a cap that keeps bf16 native
    (AMX, INTEL, "avx512_core_amx", True),                   # a cap that keeps AMX
    ({"avx2", "fma"}, AMD, "ALL", False),                    # no cap gives units the CPU lacks
])
def test_auto_training_precision_follows_the_teacher_s_rule(cpu_host, flags, vendor, isa, bf16):
    cpu_host(flags, vendor, isa)
    assert device.autocast_dtype(CPU, "auto") == (torch.bfloat16 if bf16 else None)
    assert device.teacher_cpu_dtype() == ("bf16" if bf16 else "fp32")   # one rule for both
    assert device.autocast_dtype(CPU, "fp32") is None                    # pinned: whatever the host
    assert device.autocast_dtype(CPU, "bf16") == torch.bfloat16


def test_cpu_vendor_reads_the_first_vendor_id(monkeypatch, tmp_path):
    """The vendor comes from /proc/cpuinfo's first ``vendor_id``; empty without one."""
    import builtins

    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nvendor_id\t: AuthenticAMD\nflags\t\t: avx2\nvendor_id\t: GenuineIntel\n")
    real_open = builtins.open
    monkeypatch.setattr(builtins, "open", lambda path, *a, **k: real_open(
        info if path == "/proc/cpuinfo" else path, *a, **k))
    assert device.cpu_vendor() == "AuthenticAMD"
    info.write_text("processor\t: 0\nflags\t\t: avx2\n")
    assert device.cpu_vendor() == ""


@pytest.mark.parametrize("flags, vendor, isa, native", [
    (AVX512_BF16, INTEL, None, True),          # native, yet not worth it without AMX (the rule above: fp32)
    (AMX, INTEL, "AVX512_CORE_BF16", True),    # capped to the avx512_bf16 path: still native
    (AMX, INTEL, "AVX2", False),               # capped below bf16: emulated
    ({"avx2", "fma"}, AMD, None, False),
])
def test_native_bf16_is_the_flags_and_the_cap_whatever_the_vendor(cpu_host, flags, vendor, isa, native):
    """``cpu_bf16_native`` (what the benchmarks' bf16 peak needs) is the flags and the cap alone; the vendor only
    enters whether bf16 pays off."""
    cpu_host(flags, vendor, isa)
    assert device.cpu_bf16_native() == native
    assert not device.cpu_bf16_pays_off() or native
