"""Device and precision selection shared by training, teacher inference and deployment."""

from __future__ import annotations

from pipeline.errors import InputError


def resolve_device(name: str = "auto"):
    """``auto`` -> cuda when available, else cpu.  ``cuda`` without a GPU is a user error."""
    import torch

    if name not in ("auto", "cpu", "cuda") and not str(name).startswith("cuda:"):
        raise InputError(f"--device {name!r}: expected auto, cpu or cuda")
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if str(name).startswith("cuda") and not torch.cuda.is_available():
        raise InputError(f"--device {name}: CUDA is not available on this machine")
    return torch.device(name)


def cpu_supports_bf16() -> bool:
    """True where the CPU has native bf16 matrix units (AVX-512-BF16 / AMX), so bf16 autocast pays off."""
    try:
        with open("/proc/cpuinfo") as f:
            flags = f.read()
    except OSError:
        return False
    return "avx512_bf16" in flags or "amx_bf16" in flags


def autocast_dtype(device, precision: str):
    """Map a ``precision`` param (fp32 | bf16 | auto) to an autocast dtype or None (= fp32)."""
    import torch

    if precision not in ("fp32", "bf16", "auto"):
        raise InputError(f"precision {precision!r}: expected fp32, bf16 or auto")
    if precision == "fp32":
        return None
    if precision == "bf16":
        return torch.bfloat16
    if device.type == "cuda":
        return torch.bfloat16 if torch.cuda.is_bf16_supported() else None
    return torch.bfloat16 if cpu_supports_bf16() else None
