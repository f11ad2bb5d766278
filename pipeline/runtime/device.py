"""Device and precision selection shared by training, teacher inference and deployment."""

from __future__ import annotations

import contextlib
import os

from pipeline.runtime.errors import InputError


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


#: the cores a scheduler gave this process (``geodistill run`` sets it for each stage's process): what a stage
#: may fill with processes of its own; unset, the machine's cores
STAGE_CPUS_ENV = "GEODISTILL_STAGE_CPUS"


def stage_cores() -> int:
    """The cores this stage may use: :data:`STAGE_CPUS_ENV` where a scheduler set it, else ``os.cpu_count()``."""
    try:
        given = int(float(os.environ.get(STAGE_CPUS_ENV) or 0))
    except ValueError:
        given = 0
    return max(1, given or os.cpu_count() or 1)


#: the CPU flags of native bf16 arithmetic; without one, bf16 is emulated and far slower
BF16_FLAGS = ("avx512_bf16", "amx_bf16")


def cpu_flags() -> frozenset[str]:
    """The CPU's feature flags from /proc/cpuinfo (empty where there is none: not Linux)."""
    try:
        with open("/proc/cpuinfo") as f:
            return frozenset(w for line in f if line.startswith("flags") for w in line.split(":", 1)[1].split())
    except OSError:
        return frozenset()


def cpu_supports_bf16() -> bool:
    """True where the CPU has native bf16 matrix units (:data:`BF16_FLAGS`), so bf16 autocast pays off."""
    return not cpu_flags().isdisjoint(BF16_FLAGS)


def autocast(device, dtype, cache_enabled: bool = True):
    """The autocast context of ``dtype`` on ``device`` (None: fp32).  ``cache_enabled=False`` where the
    weight-cast cache must not outlive a CUDA-graph capture."""
    import torch

    if dtype is None:
        return contextlib.nullcontext()
    return torch.autocast(device_type=torch.device(device).type, dtype=dtype, cache_enabled=cache_enabled)


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
