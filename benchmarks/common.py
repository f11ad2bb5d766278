"""What the benchmark scripts share: round-robin timing, its medians and minima; the studies' JSON output and
their training jobs, resumed from the runs already finished."""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import statistics
import time
from pathlib import Path
from typing import Any, Callable, Mapping

from pipeline.artifacts.provenance import cpu, numerics_env, numpy_simd
from pipeline.runtime.device import cpu_bf16_native, cpu_flags, cpu_vendor

#: the options the benchmarks share: name -> ``add_argument`` keywords (each script gives the default)
OPTIONS: dict[str, dict] = {
    "artifacts": {"help": "an artifacts directory with prepare .. consensus done (else built in --workdir)"},
    "workdir": {"help": "where the data stages write without --artifacts"},
    "profile": {"help": "the params profile: data sizes and training settings"},
    "resolution": {"type": int, "help": "data.resolution"},
    "set": {"dest": "sets", "action": "append", "metavar": "KEY=VALUE", "help": "a params override (repeatable)"},
    "seeds": {"type": int, "nargs": "+"},
    "epochs": {"type": int, "help": "train.epochs_stage1 (default: the profile's)"},
    "device": {},
    "jobs": {"type": int, "help": "training processes at a time"},
    "threads": {"type": int, "help": "torch threads per process"},
    "repeats": {"type": int, "help": "round-robin rounds"},
    "out": {"help": "the JSON output"},
}


def parser(doc: str, **defaults: Any) -> argparse.ArgumentParser:
    """A benchmark's parser, its docstring as the help, with the :data:`OPTIONS` named in ``defaults``."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    for name, default in defaults.items():
        ap.add_argument(f"--{name}", default=default, **OPTIONS[name])
    return ap


def seconds(fn: Callable[[], object]) -> float:
    """Wall seconds of ``fn()``."""
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def best_of(fn: Callable[[], object], repeats: int) -> float:
    return min(seconds(fn) for _ in range(max(1, repeats)))


def round_robin(cases: dict[str, Callable[[int], object]], rounds: int, order: str = "fixed") -> dict[str, list]:
    """``{case: [its result per round]}``; every round calls each case once with the round's index, in a
    ``fixed`` order, or reversed every other round (``alternate``), or shifted by one each round (``rotate``),
    so that load from other processes on a shared machine hits every case alike."""
    names = list(cases)
    out: dict[str, list] = {n: [] for n in names}
    for i in range(rounds):
        k = i % len(names) if order == "rotate" else 0
        seq = names[::-1] if order == "alternate" and i % 2 else names[k:] + names[:k]
        for name in seq:
            out[name].append(cases[name](i))
    return out


def medians(times: dict[str, list[float]]) -> dict[str, float]:
    return {k: statistics.median(v) for k, v in times.items()}


def minima(times: dict[str, list[float]]) -> dict[str, float]:
    return {k: min(v) for k, v in times.items()}


def read_json(path: Path, default: Any = None) -> Any:
    """The JSON document at ``path``; ``default`` (else ``{}``) when there is none, None when it cannot be read."""
    try:
        return json.loads(path.read_text()) if path.exists() else ({} if default is None else default)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None


def run_jobs(jobs: list[dict], artifacts: str, base: dict, n_jobs: int, threads: int, init, run):
    """Yield the results of ``jobs`` as they finish, here or in ``n_jobs`` spawned processes (each loading the
    study data once with ``init``; jobs run by ``run``)."""
    if not jobs:
        return
    if n_jobs <= 1:
        init(artifacts, base, threads)
        yield from map(run, jobs)
        return

    with mp.get_context("spawn").Pool(n_jobs, initializer=init, initargs=(artifacts, base, threads)) as pool:
        yield from pool.imap_unordered(run, jobs, chunksize=1)
        pool.close()  # let the workers exit on their own (terminate() leaves a semaphore behind)
        pool.join()


def _run_key(run: Mapping[str, Any]) -> tuple:
    return run["variant"], run["method"], run["seed"]


def resumed_runs(out: str | Path, info: Mapping[str, Any], jobs: list[dict], run_all) -> dict:
    """``{(variant, method, seed): run}`` of ``jobs``: those in ``<out>.runs.jsonl`` (JSON lines after a line of
    ``info``'s settings) when it was written with the same settings (else the file restarts), the others run by
    ``run_all(todo)`` and appended as they finish: a long study survives an interruption."""
    partial = Path(str(out) + ".runs.jsonl")
    settings = {k: info[k] for k in ("artifacts", "device", "resolution", "profile", "epochs", "n_train")}
    lines = [json.loads(x) for x in partial.read_text().splitlines() if x.strip()] if partial.exists() else []
    if lines and lines[0].get("info") != json.loads(json.dumps(settings)):
        partial.unlink()
        lines = []
    done = {_run_key(r): r for r in lines[1:]}
    with partial.open("a") as sink:
        if not lines:  # a new file (one holding only its settings line has none to repeat)
            sink.write(json.dumps({"info": settings}) + "\n")
        for r in run_all([j for j in jobs if _run_key(j) not in done]):
            sink.write(json.dumps(r) + "\n")
            sink.flush()
            done[_run_key(r)] = r
    return done


#: CPU flags that tell which matrix units a host has (/proc/cpuinfo names)
LIMIT_FLAGS = ("avx2", "fma", "avx512f", "avx512_bf16", "amx_tile", "amx_bf16")


def matmul_peak(dtype, n: int = 2048, repeats: int = 5) -> tuple[float, float]:
    """(best, median) GFLOP/s of an n x n matmul in ``dtype`` on this process's threads: the measured limit."""
    import torch

    a, b = torch.randn(n, n).to(dtype), torch.randn(n, n).to(dtype)
    a @ b
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        a @ b
        ts.append(time.perf_counter() - t0)
    return 2 * n ** 3 / min(ts) / 1e9, 2 * n ** 3 / statistics.median(ts) / 1e9


def host_record() -> dict[str, Any]:
    """Say where a benchmark ran, for its JSON: two hosts' runs are paired only knowing this.

    Returns
    -------
    dict
        ``date`` (UTC), ``node``, ``cpu`` (model), ``vendor``, ``logical_cpus``, ``flags`` (the numeric kernels'
        CPU flags, :func:`pipeline.artifacts.provenance.cpu`), ``numpy_simd`` (numpy's dispatch targets: they
        decide the synthetic benchmark's rendered pixels), ``torch``, ``torch_threads`` and ``env`` (the thread
        and numerics variables set).
    """
    import torch

    c = cpu()
    return {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "node": platform.node(), "cpu": c["model"],
            "vendor": cpu_vendor(), "logical_cpus": c["logical_cpus"], "flags": c["flags"],
            "numpy_simd": numpy_simd(), "torch": torch.__version__, "torch_threads": torch.get_num_threads(),
            "env": numerics_env(os.environ)}


def host_limits() -> dict:
    """The host's fp32 / bf16 / AMX limits: which its flags allow, and the measured matmul peaks (a bf16 matmul
    runs on the AMX tiles where the host has them, so the AMX row is the bf16 peak there, n/a elsewhere)."""
    import torch


    flags = cpu_flags()
    has = {f: f in flags for f in LIMIT_FLAGS}
    fp32 = matmul_peak(torch.float32)
    # native bf16 by the one rule (the flags, and an ONEDNN_MAX_CPU_ISA cap): emulated bf16 is no limit
    bf16 = matmul_peak(torch.bfloat16) if cpu_bf16_native() else None
    return {"flags": has, "threads": torch.get_num_threads(),
            "fp32_gflops": fp32[0], "fp32_gflops_median": fp32[1],
            "bf16_gflops": bf16[0] if bf16 else None, "bf16_gflops_median": bf16[1] if bf16 else None,
            "amx_gflops": bf16[0] if bf16 and has["amx_bf16"] else None}
