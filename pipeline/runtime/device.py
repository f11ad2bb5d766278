"""Device, precision and allocator settings shared by training, teacher inference and deployment."""

from __future__ import annotations

import contextlib
import ctypes
import os

from pipeline.runtime.errors import InputError

__all__ = ["STAGE_CPUS_ENV", "BF16_FLAGS", "ONEDNN_BF16_ISAS", "resolve_device", "stage_cores", "cpu_flags",
           "cpu_vendor", "BF16_WITHOUT_AMX_VENDORS",
           "cpu_supports_bf16", "cpu_bf16_native", "cpu_bf16_pays_off", "teacher_cpu_dtype", "OPENVINO_ATTENTION_FLAGS",
           "OPENVINO_ATTENTION_VENDORS",
           "teacher_cpu_engine", "onednn_isa_cap", "cpu_amx_native", "autocast", "autocast_dtype", "GLIBC_MALLOC_ENV",
           "HEAP_RETAINED", "reuse_freed_memory"]


def resolve_device(name: str = "auto"):
    """Return the torch device a ``--device`` value names.

    Parameters
    ----------
    name : str
        ``auto`` (cuda when available, else cpu), ``cpu``, ``cuda`` or ``cuda:N``.

    Returns
    -------
    torch.device
        The device.

    Raises
    ------
    InputError
        ``name`` is none of these, or it names CUDA on a machine without it.
    """
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
    """Return the cores this stage may use.

    Returns
    -------
    int
        :data:`STAGE_CPUS_ENV` where a scheduler set it to a positive number, else ``os.cpu_count()``; at least 1.
    """
    try:
        given = int(float(os.environ.get(STAGE_CPUS_ENV) or 0))
    except ValueError:
        given = 0
    return max(1, given or os.cpu_count() or 1)


#: the CPU flags of native bf16 arithmetic; without one, bf16 is emulated and far slower
BF16_FLAGS = ("avx512_bf16", "amx_bf16")


def cpu_flags() -> frozenset[str]:
    """Return the CPU's feature flags from /proc/cpuinfo.

    Returns
    -------
    frozenset of str
        The flags; empty where there is no /proc/cpuinfo (not Linux).
    """
    try:
        with open("/proc/cpuinfo") as f:
            return frozenset(w for line in f if line.startswith("flags") for w in line.split(":", 1)[1].split())
    except OSError:
        return frozenset()


def cpu_vendor() -> str:
    """Return the CPU's vendor string from /proc/cpuinfo (``GenuineIntel``, ``AuthenticAMD``, ...).

    Returns
    -------
    str
        The first ``vendor_id``; empty where there is none (not Linux, or not x86).
    """
    try:
        with open("/proc/cpuinfo") as f:
            return next((line.split(":", 1)[1].strip() for line in f if line.startswith("vendor_id")), "")
    except OSError:
        return ""


def cpu_supports_bf16() -> bool:
    """Tell whether the CPU has native bf16 matrix units (:data:`BF16_FLAGS`), so bf16 is not emulated.

    Whether it is also faster than fp32 there is :func:`cpu_bf16_pays_off`'s question.

    Returns
    -------
    bool
        True where one of :data:`BF16_FLAGS` is among :func:`cpu_flags`.
    """
    return not cpu_flags().isdisjoint(BF16_FLAGS)


#: ``ONEDNN_MAX_CPU_ISA`` values (oneDNN's names) under which oneDNN still runs bf16 natively (avx512_bf16, AMX)
ONEDNN_BF16_ISAS = ("AVX512_CORE_BF16", "AVX512_CORE_FP16", "AVX512_CORE_AMX", "AVX512_CORE_AMX_FP16",
                    "AVX10_1_512", "AVX10_1_512_AMX", "AVX10_1_512_AMX_FP16", "AVX10_2_512", "AVX10_2_512_AMX_2",
                    "ALL", "DEFAULT")


def onednn_isa_cap() -> str:
    """Read oneDNN's ISA cap, ``ONEDNN_MAX_CPU_ISA``.

    Returns
    -------
    str
        Its value in upper case, stripped; empty where it is not set.
    """
    return os.environ.get("ONEDNN_MAX_CPU_ISA", "").strip().upper()


#: the CPU vendors whose avx512_bf16 units, without AMX, run bf16 matrix products faster than fp32 ones: measured on
#: a 2-core AMD EPYC (oneDNN's bf16 matmul 1,034 GFLOP/s against MKL's fp32 239; SAM 3 in bf16 0.32-0.47 of fp32's
#: time).  An Intel core's avx512_bf16 path (an AMX host with oneDNN capped at AVX512_CORE_BF16, as where AMX is not
#: granted) ran bf16 matmuls at half the fp32 rate (206 against 412 GFLOP/s) and SAM 3's default at 1.33x fp32's
#: time, so Intel bf16 needs AMX (docs/performance.md, "bf16 without AMX on an Intel core")
BF16_WITHOUT_AMX_VENDORS = ("AuthenticAMD",)


def cpu_bf16_native() -> bool:
    """Tell whether bf16 runs natively here.

    The CPU has bf16 units (:func:`cpu_supports_bf16`, read from its flags, never a timing probe) and
    ``ONEDNN_MAX_CPU_ISA``, where set, does not cap oneDNN below them (:data:`ONEDNN_BF16_ISAS`).  Native is not
    the same as faster than fp32: :func:`cpu_bf16_pays_off`.

    Returns
    -------
    bool
        False where bf16 would be emulated.
    """
    isa = onednn_isa_cap()
    if isa and isa not in ONEDNN_BF16_ISAS:
        return False
    return cpu_supports_bf16()


def cpu_bf16_pays_off() -> bool:
    """Apply the rule for bf16 on this CPU (the teacher's ``dtype: auto`` and training's ``precision: auto``).

    True where oneDNN runs bf16 on AMX tiles (:func:`cpu_amx_native`), or where bf16 is native
    (:func:`cpu_bf16_native`) on a CPU of one of :data:`BF16_WITHOUT_AMX_VENDORS`; else False: bf16 would be
    emulated, or, on an Intel core without AMX, its matrix products are slower than fp32's.  Read from the flags,
    the vendor and the ``ONEDNN_MAX_CPU_ISA`` cap, never a timing probe.

    Returns
    -------
    bool
        Whether ``auto`` means bf16 here.
    """
    return cpu_bf16_native() and (cpu_amx_native() or cpu_vendor() in BF16_WITHOUT_AMX_VENDORS)


def teacher_cpu_dtype() -> str:
    """Resolve ``teacher.dtype: auto`` on a CPU.

    Measured (docs/performance.md): on a 2-core avx512_bf16 host the real-size SAM 3 in bf16 takes a fraction
    of fp32's time per image with the same masks (the fidelity gate of benchmarks/bench_teacher.py).

    Returns
    -------
    str
        ``bf16`` where :func:`cpu_bf16_pays_off`, else ``fp32``.
    """
    return "bf16" if cpu_bf16_pays_off() else "fp32"


#: the CPU flags under which ``teacher.engine: auto`` runs SAM 3's bf16 attention in OpenVINO: measured on
#: avx512_bf16 without AMX (docs/performance.md); with AMX in use torch's attention was the faster
OPENVINO_ATTENTION_FLAGS = ("avx512_bf16",)
#: the CPU vendors on which that attention was measured faster: the AMD EPYC (its attention 2.2-3.1x torch's bf16 flash
#: kernel); on an Intel core it lost with AMX (1.05-1.3x torch's time) and without (the AMX host with oneDNN capped
#: at AVX512_CORE_BF16: a bf16 call 43.5 s against 36.0 s in torch; docs/performance.md)
OPENVINO_ATTENTION_VENDORS = ("AuthenticAMD",)
#: the ``ONEDNN_MAX_CPU_ISA`` values of :data:`ONEDNN_BF16_ISAS` that leave oneDNN its AMX kernels
ONEDNN_AMX_ISAS = tuple(isa for isa in ONEDNN_BF16_ISAS if "AMX" in isa or isa in ("ALL", "DEFAULT"))


def cpu_amx_native() -> bool:
    """Tell whether oneDNN runs bf16 on AMX tiles here: ``amx_bf16``, and no ``ONEDNN_MAX_CPU_ISA`` cap below it.

    Returns
    -------
    bool
        True where ``amx_bf16`` is among :func:`cpu_flags` and ``ONEDNN_MAX_CPU_ISA``, where set, is one of
        :data:`ONEDNN_AMX_ISAS`.
    """
    isa = onednn_isa_cap()
    return "amx_bf16" in cpu_flags() and (not isa or isa in ONEDNN_AMX_ISAS)


def teacher_cpu_engine(dtype_name: str) -> str:
    """Resolve ``teacher.engine: auto`` on a CPU, from its flags and vendor (never a timing probe).

    Measured (docs/performance.md, "The teacher's attention in OpenVINO" and "The teacher on AMX"): on a 2-core
    avx512_bf16 AMD EPYC, OpenVINO's fused attention ran SAM 3's attention shapes 2.2-3.1x faster than torch's
    bf16 flash kernel; on a 2-core Intel AMX host torch's kernel was the faster (OpenVINO's took 1.05-1.3x its
    time), also with oneDNN capped below AMX (a bf16 call 43.5 against 36.0 s), and fusing each MLP's activation
    into its first linear layer (oneDNN) took the teacher from 10.65 to 9.66 s per image at real size (the torch
    engine against onednn, one round-robin run). fp32 CPUs and pinned fp32: torch.

    Parameters
    ----------
    dtype_name : str
        The teacher's resolved dtype, ``fp32`` or ``bf16``.

    Returns
    -------
    str
        For bf16: ``onednn`` where oneDNN runs on AMX (:func:`cpu_amx_native`), else ``openvino`` on a CPU with one
        of :data:`OPENVINO_ATTENTION_FLAGS` from one of :data:`OPENVINO_ATTENTION_VENDORS`; else ``torch`` (an
        AMX CPU capped below AMX by ``ONEDNN_MAX_CPU_ISA`` runs as an Intel avx512_bf16 one: torch).
    """
    if dtype_name != "bf16":
        return "torch"
    if cpu_amx_native():
        return "onednn"
    if not cpu_flags().isdisjoint(OPENVINO_ATTENTION_FLAGS) and cpu_vendor() in OPENVINO_ATTENTION_VENDORS:
        return "openvino"
    return "torch"


def autocast(device, dtype, cache_enabled: bool = True):
    """Return the autocast context of ``dtype`` on ``device``.

    Parameters
    ----------
    device : torch.device or str
        The device that runs under the context.
    dtype : torch.dtype or None
        The autocast dtype (:func:`autocast_dtype`); None: fp32, no autocast.
    cache_enabled : bool
        False where the weight-cast cache must not outlive a CUDA-graph capture.

    Returns
    -------
    contextlib.AbstractContextManager
        ``torch.autocast``, or a null context for fp32.
    """
    import torch

    if dtype is None:
        return contextlib.nullcontext()
    return torch.autocast(device_type=torch.device(device).type, dtype=dtype, cache_enabled=cache_enabled)


def autocast_dtype(device, precision: str):
    """Return the autocast dtype of a ``precision`` param (fp32 | bf16 | auto), None meaning fp32.

    ``auto``: bf16 on a CUDA device that supports it; on a CPU, bf16 where :func:`cpu_bf16_pays_off` (the
    teacher's rule: the flags, the vendor and the ``ONEDNN_MAX_CPU_ISA`` cap), else fp32.

    Parameters
    ----------
    device : torch.device
        The device that trains or predicts.
    precision : str
        ``fp32`` | ``bf16`` | ``auto``.

    Returns
    -------
    torch.dtype or None
        ``torch.bfloat16`` or None (fp32: no autocast).

    Raises
    ------
    InputError
        ``precision`` is none of the three.
    """
    import torch

    if precision not in ("fp32", "bf16", "auto"):
        raise InputError(f"precision {precision!r}: expected fp32, bf16 or auto")
    if precision == "fp32":
        return None
    if precision == "bf16":
        return torch.bfloat16
    if device.type == "cuda":
        return torch.bfloat16 if torch.cuda.is_bf16_supported() else None
    return torch.bfloat16 if cpu_bf16_pays_off() else None


#: glibc's malloc settings a user may have chosen (environment); where one is set, :func:`reuse_freed_memory`
#: leaves malloc as the user chose it
GLIBC_MALLOC_ENV = ("GLIBC_TUNABLES", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_",
                    "MALLOC_MMAP_MAX_")
#: freed memory at the heap's top kept before glibc returns it to the system (M_TRIM_THRESHOLD)
HEAP_RETAINED = 2**30
_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4  # glibc's malloc.h
_FREED_MEMORY_REUSED = False


def reuse_freed_memory(device="cpu", libc=None) -> bool:
    """Let glibc's malloc keep the memory a training step or a teacher call frees for the next (process-wide).

    Only where ``device`` is a CPU: a GPU's tensors are not malloc's.

    With glibc's defaults, a block above its mmap threshold (128 KiB, adapting up to 32 MiB) is mapped from the
    system when allocated and returned when freed, so every step faults in and zero-fills fresh pages: about 10,000
    page faults and 28 ms of kernel time per step of ``distill``'s bf16 settings at 128², batch 8, and about 2
    million faults and 3 s of kernel time per SAM 3 call on a 256² image (2 cores). ``mallopt(M_MMAP_MAX, 0)``
    serves every block from the heap and ``mallopt(M_TRIM_THRESHOLD,`` :data:`HEAP_RETAINED` ``)`` keeps up to
    1 GiB of freed memory at its top, so a step or call reuses what the last one freed: training epochs about 10 %
    shorter in bf16 and fp32, SAM 3 calls about 20 % (docs/performance.md). Where tensors live changes, not what
    is computed: the trained weights and the teacher's answers are the same bits. The process keeps the memory it
    freed below the heap's top instead of returning it. Applied once; a glibc setting in the environment
    (:data:`GLIBC_MALLOC_ENV`) leaves malloc as chosen: ``GLIBC_TUNABLES=glibc.malloc.tcache_count=7`` (a default
    value) keeps glibc's adaptive defaults, a ``MALLOC_*_`` threshold fixes glibc's thresholds; a C library without
    ``mallopt`` (not glibc) is left alone.

    Parameters
    ----------
    device : torch.device or str
        The device that trains or predicts; anything but a CPU leaves malloc alone.
    libc : object, optional
        The C library (its ``mallopt``); default: this process's, through ``ctypes``.

    Returns
    -------
    bool
        True where the settings are in place (now or by an earlier call), False where they were left.
    """
    global _FREED_MEMORY_REUSED
    if str(device).split(":")[0] != "cpu":
        return False
    if _FREED_MEMORY_REUSED:
        return True
    if any(os.environ.get(name) for name in GLIBC_MALLOC_ENV):
        return False
    if libc is None:
        libc = ctypes.CDLL(None)
    mallopt = getattr(libc, "mallopt", None)
    if mallopt is None or not hasattr(libc, "gnu_get_libc_version"):
        return False
    _FREED_MEMORY_REUSED = bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, HEAP_RETAINED))
    return _FREED_MEMORY_REUSED
