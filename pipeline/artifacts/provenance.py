"""The environment a published number came from (docs/environment.md).

Python, libraries, the torch build, the CPU and its numeric flags, threads, and whether the installed
packages are the lock file's.  Provenance only: nothing here enters a fingerprint.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import os
import platform
import re
from pathlib import Path
from typing import Any, Mapping

from pipeline.artifacts.lineage import library_versions

try:  # numpy's own record of its SIMD dispatch (np.show_runtime reads it); private, so guarded
    from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__
    _NUMPY_CPU: tuple[list[str], dict[str, bool]] | None = (list(__cpu_dispatch__), dict(__cpu_features__))
except ImportError:
    _NUMPY_CPU = None

__all__ = ["THREAD_ENV_VARS", "cpu", "collect", "numerics_env", "numpy_simd", "training_runtime"]

ROOT = Path(__file__).resolve().parents[2]
LOCK_FILE = ROOT / "requirements" / "lock.txt"
#: libraries recorded beyond those every artifact records
EXTRA_LIBRARIES = ("pandas", "pydantic", "click", "dvc", "dvclive", "onnx", "onnxruntime", "openvino",
                   "transformers")

#: CPU flags that select different kernels, so possibly different rounding
NUMERIC_CPU_FLAGS = ("avx", "avx2", "fma", "f16c", "avx512f", "avx512bw", "avx512vl", "avx512_vnni",
                     "avx512_bf16", "avx512_fp16", "avx_vnni", "amx_tile", "amx_bf16", "amx_int8")

THREAD_ENV_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS",
                   "VECLIB_MAXIMUM_THREADS")

NUMERIC_ENV_VARS = ("OPENBLAS_CORETYPE", "OPENBLAS_L2_SIZE", "ATEN_CPU_CAPABILITY", "ONEDNN_MAX_CPU_ISA",
                    "DNNL_MAX_CPU_ISA", "ONEDNN_DEFAULT_FPMATH_MODE", "MKL_CBWR", "CUBLAS_WORKSPACE_CONFIG",
                    "NVIDIA_TF32_OVERRIDE", "NPY_DISABLE_CPU_FEATURES", "NPY_ENABLE_CPU_FEATURES",
                    "OPENCV_CPU_DISABLE")

#: torch build settings worth a line in a report
TORCH_SETTINGS = ("TORCH_VERSION", "COMMIT_SHA", "USE_CUDA", "CUDA_VERSION", "CUDNN_VERSION", "BLAS_INFO",
                  "LAPACK_INFO", "USE_MKL", "USE_MKLDNN", "USE_OPENMP")


def parse_cpuinfo(text: str) -> dict[str, Any]:
    """``/proc/cpuinfo`` -> ``{"model", "logical_cpus", "flags"}`` (the first CPU's :data:`NUMERIC_CPU_FLAGS`)."""
    model, flags, n = None, set(), 0
    for line in text.splitlines():
        key, _, value = line.partition(":")
        key = key.strip()
        if key == "processor":
            n += 1
        elif key == "model name" and model is None:
            model = value.strip()
        elif key in ("flags", "Features") and not flags:
            flags = set(value.split())
    return {"model": model, "logical_cpus": n, "flags": [f for f in NUMERIC_CPU_FLAGS if f in flags]}


def parse_torch_config(text: str) -> dict[str, Any]:
    """``torch.__config__.show()`` -> ``{"components": [...], "settings": {...}}`` (:data:`TORCH_SETTINGS`)."""
    components, settings = [], {}
    for line in text.splitlines():
        item = line.strip()
        if not item.startswith("- "):
            continue
        item = item[2:].strip()
        if item.startswith("Build settings:"):
            for part in item[len("Build settings:"):].split(", "):
                key, eq, value = part.partition("=")
                if eq and key.strip() in TORCH_SETTINGS:
                    settings[key.strip()] = value.strip().rstrip(",")
        else:
            components.append(item)
    return {"components": components, "settings": settings}


def normalize_name(name: str) -> str:
    """Put a distribution name in PEP 503 normal form (``Ruamel.YAML`` -> ``ruamel-yaml``)."""
    return re.sub(r"[-_.]+", "-", name).lower()


def parse_lock(text: str) -> dict[str, str]:
    """Read ``{normalized name: version}`` of the ``name==version`` lines of a requirements file."""
    out = {}
    for line in text.splitlines():
        m = re.match(r"^\s*([A-Za-z0-9][A-Za-z0-9._-]*)(?:\[[^\]]*\])?\s*==\s*([^\s;#]+)", line)
        if m:
            out[normalize_name(m.group(1))] = m.group(2)
    return out


def public_version(version: str) -> str:
    """Drop a version's local label (``2.13.0+cpu`` -> ``2.13.0``): keep the part a ``==`` pin compares."""
    return version.split("+", 1)[0]


def lock_status(pins: Mapping[str, str], installed: Mapping[str, str]) -> dict[str, Any]:
    """Compare the installed distributions with the lock's pins: ``pinned``, ``matching``, ``not_installed``, ``differ``.

    Public versions compare (``+cpu`` is the build, not the version).
    """
    differ, matching, absent = [], 0, 0
    for name, version in sorted(pins.items()):
        have = installed.get(name)
        if have is None:
            absent += 1
        elif public_version(have) == public_version(version):
            matching += 1
        else:
            differ.append({"package": name, "lock": version, "installed": have})
    return {"pinned": len(pins), "matching": matching, "not_installed": absent, "differ": differ}


def numerics_env(environ: Mapping[str, str]) -> dict[str, str]:
    """Select the thread-count and numerics environment variables that are set.

    Parameters
    ----------
    environ : Mapping
        An environment (``os.environ``).

    Returns
    -------
    dict
        ``{name: value}`` of :data:`THREAD_ENV_VARS` and :data:`NUMERIC_ENV_VARS` set there.
    """
    return {k: environ[k] for k in THREAD_ENV_VARS + NUMERIC_ENV_VARS if k in environ}


def cpu() -> dict[str, Any]:
    """Describe this machine's CPU: :func:`parse_cpuinfo` of it (model from :mod:`platform` where /proc is absent).

    Returns
    -------
    dict
        ``model``, ``logical_cpus`` and ``flags`` (those of :data:`NUMERIC_CPU_FLAGS` the CPU has).
    """
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        text = ""
    info = parse_cpuinfo(text)
    if info["model"] is None:
        info["model"] = platform.processor() or platform.machine() or None
    if not info["logical_cpus"]:
        info["logical_cpus"] = os.cpu_count() or 0
    return info


def numpy_simd() -> list[str] | None:
    """Name the SIMD targets numpy dispatches to on this CPU, beyond its build's baseline (``np.show_runtime``'s).

    They decide the last bits of numpy's vectorised ``exp``, ``sin``, ``cos``...: the synthetic benchmark renders
    its images with them, so another level can render a pixel one 8-bit step apart (docs/stability.md, "The
    benchmark's own data across CPU kinds").

    Returns
    -------
    list of str or None
        The dispatch targets found and enabled (``NPY_DISABLE_CPU_FEATURES`` removes some), in numpy's order;
        None where this numpy does not say.
    """
    if _NUMPY_CPU is None:
        return None
    dispatch, features = _NUMPY_CPU
    return [f for f in dispatch if features.get(f)]


def installed_versions() -> dict[str, str]:
    """Map every distribution importable here: ``{normalized name: version}``."""
    out = {}
    for dist in importlib.metadata.distributions():
        name = dist.metadata["Name"]
        if name:
            out.setdefault(normalize_name(name), dist.version)
    return out


def torch_build() -> dict[str, Any]:
    """Describe the torch build: version, commit, CUDA, CPU kernel level, MKL/oneDNN, components, settings, GPUs."""
    import torch

    out = {"version": torch.__version__, "git": getattr(torch.version, "git_version", None),
           "cuda": torch.version.cuda, "cpu_capability": torch.backends.cpu.get_cpu_capability(),
           "mkl": bool(torch.backends.mkl.is_available()), "mkldnn": bool(torch.backends.mkldnn.is_available()),
           **parse_torch_config(torch.__config__.show())}
    out["gpus"] = ([torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())]
                   if torch.cuda.is_available() else [])
    return out


def lock_record(path: str | Path = LOCK_FILE, installed: Mapping[str, str] | None = None) -> dict[str, Any]:
    """Record the lock file (path, sha256) and :func:`lock_status` against it; ``found: False`` without one."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError:
        return {"file": str(path), "found": False}
    status = lock_status(parse_lock(data.decode()), installed_versions() if installed is None else installed)
    shown = path.resolve().relative_to(ROOT).as_posix() if path.resolve().is_relative_to(ROOT) else str(path)
    return {"file": shown, "found": True,
            "sha256": hashlib.sha256(data).hexdigest(), **status}


def collect(lock: str | Path = LOCK_FILE) -> dict[str, Any]:
    """Collect everything about this machine and installation that can change a published number.

    Parameters
    ----------
    lock : str or Path
        The lock file the installation is compared with.

    Returns
    -------
    dict
        ``python``, ``platform``, ``libraries`` (the project's and :data:`EXTRA_LIBRARIES`), ``torch`` (its build),
        ``cpu``, ``numpy_simd`` (:func:`numpy_simd`), ``threads`` (torch's intra- and inter-op), ``env`` (the numerics variables set) and ``lock``.
    """
    import torch

    libs = {k: v for k, v in library_versions().items() if k != "python"}
    installed = installed_versions()
    for name in EXTRA_LIBRARIES:
        if normalize_name(name) in installed:
            libs[name] = installed[normalize_name(name)]
    return {"python": f"{platform.python_implementation()} {platform.python_version()}",
            "platform": platform.platform(), "libraries": libs, "torch": torch_build(), "cpu": cpu(),
            "numpy_simd": numpy_simd(),
            "threads": {"torch": torch.get_num_threads(), "torch_interop": torch.get_num_interop_threads()},
            "env": numerics_env(os.environ), "lock": lock_record(lock, installed)}


def training_runtime(device) -> dict[str, Any]:
    """Record what a train run ran on (device, threads, torch, CPU), for its checkpoint's ``extra.runtime``.

    Parameters
    ----------
    device : str or torch.device
        The device the run trained on.

    Returns
    -------
    dict
        The runtime record.
    """
    import torch

    dev = torch.device(device)
    info = cpu()
    out = {"device": str(dev), "num_threads": torch.get_num_threads(), "torch": torch.__version__,
           "cpu_capability": torch.backends.cpu.get_cpu_capability(), "cpu_model": info["model"],
           "cpu_flags": info["flags"]}
    if dev.type == "cuda":
        out["gpu"] = torch.cuda.get_device_name(dev)
    return out
