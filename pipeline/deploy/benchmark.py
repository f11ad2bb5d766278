"""Efficiency benchmark of the deployed mask path on this machine.

Per variant: parameters and GFLOPs, batch-1 latency (timed round-robin), best-batch throughput, peak memory and
the validation IoU change at the deployed tau (eq:inference-mask); the fast path and its verdicts
(docs/decisions.md).
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import math
import statistics
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from pipeline import catalog
from pipeline.artifacts.store import open_artifact, read_chunk_rows
from pipeline.deploy import quantize as q8
from pipeline.deploy.bundle import INT8_FILE, ONNX_FILE, read_deploy_info
from pipeline.deploy.engines import ENGINES, Source, unavailable
from pipeline.deploy.mask_path import export_onnx, onnx_unavailable_reason, parity_inputs
from pipeline.deploy.segmenter import load_segmenter
from pipeline.runtime.errors import InputError
from pipeline.evaluation.inference import images_to_tensor, load_student
from pipeline.metrics import image_ious
from pipeline.model import count_flops, count_parameters, mask_path_model
from pipeline.engine_table import BENCHMARK_VARIANTS, engine_name
from pipeline.thresholds import mask_from_probs, resolve_tau, tau_candidates

__all__ = ["BASELINE_VARIANT", "VARIANTS", "SLOW_FACTOR", "PROBE_CALLS", "OK", "SKIPPED", "CUDA_MAX_BATCH", "Variant",
           "time_calls", "interleaved_times", "build_variants", "slow_status", "variant_remark", "measure_variants",
           "Sweep", "throughput_batches", "throughput_sweep", "fastest_within", "benchmark_settings", "Target",
           "open_target", "read_benchmark_data", "prepare_onnx_models", "fast_path_summary", "fast_path_line",
           "format_table", "format_sweep", "benchmark_result"]

#: the variant every speed-up and IoU change is measured against
BASELINE_VARIANT = "fp32_eager_nchw"
#: every benchmark variant (pipeline.engine_table)
VARIANTS = tuple(BENCHMARK_VARIANTS)
#: a variant probed more than this many times slower than the baseline is not fully timed
SLOW_FACTOR = 4.0
#: timed batch-1 calls of the probe
PROBE_CALLS = 2
#: the status of a fully timed variant
OK = "ok"
#: the status of a variant never called on this host: "skipped: <why>"
SKIPPED = "skipped"
clock = time.perf_counter  # a module attribute: a test puts a fake clock in its place
#: the CUDA throughput sweep's largest batch
CUDA_MAX_BATCH = 256
INT8_VARIANTS = tuple(n for n in VARIANTS if ENGINES[n].needs == INT8_FILE)


@dataclasses.dataclass
class Variant:
    """One way of running the mask path.

    Attributes
    ----------
    name : str
        The engine's name.
    description : str
        What it runs.
    run : Callable
        ``run(x float32 NCHW tensor) -> logits``.
    device : str
        Where it runs (``cpu`` or ``cuda``).
    sync : Callable
        Waits for the device's queued work (CUDA), so that a timing covers it.
    """

    name: str
    description: str
    run: Callable
    device: str
    sync: Callable[[], None] = lambda: None


def _status_kb(field: str) -> int | None:
    with contextlib.suppress(OSError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1])
    return None


class PeakMemory:
    """Measure the peak memory growth (MiB) over a block: the CPU's VmHWM after a reset, CUDA's max_memory_allocated."""

    def __init__(self, device: str):
        self.device = device
        self.peak_mb = float("nan")
        self.method = "unavailable"

    def __enter__(self):
        if self.device.startswith("cuda"):
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
            self._base = torch.cuda.memory_allocated()
            self.method = "torch.cuda.max_memory_allocated - allocated before"
            return self
        with contextlib.suppress(Exception):  # not glibc: nothing to trim
            ctypes.CDLL("libc.so.6").malloc_trim(0)
        self._base = None
        with contextlib.suppress(OSError), open("/proc/self/clear_refs", "w") as f:
            f.write("5")  # resets VmHWM to the current RSS
            self._base = _status_kb("VmRSS")
            self.method = "peak RSS growth (VmHWM after - VmRSS before, /proc/self/clear_refs)"
        return self

    def __exit__(self, *exc):
        if self.device.startswith("cuda"):
            torch.cuda.synchronize()
            self.peak_mb = (torch.cuda.max_memory_allocated() - self._base) / 2**20
        elif self._base is not None:
            hwm = _status_kb("VmHWM")
            if hwm is not None:
                self.peak_mb = max(0, hwm - self._base) / 1024
        return False


def time_calls(fn: Callable, x, warmup: int, iters: int, sync: Callable[[], None]) -> list[float]:
    """Time ``iters`` calls after ``warmup`` untimed ones.

    Parameters
    ----------
    fn : Callable
        The function called as ``fn(x)``.
    x : Any
        Its argument.
    warmup : int
        Untimed calls first.
    iters : int
        Timed calls.
    sync : Callable
        Called after each call, inside its timing (a device synchronisation).

    Returns
    -------
    list of float
        The wall-clock seconds of each timed call (:data:`clock`).
    """
    for _ in range(warmup):
        fn(x)
    sync()
    times = []
    for _ in range(iters):
        t0 = clock()
        fn(x)
        sync()
        times.append(clock() - t0)
    return times


def interleaved_times(variants: Sequence["Variant"], x, iters: int, block: int = 3) -> dict[str, list[float]]:
    """Time every variant on ``x`` round-robin until each has ``iters`` calls.

    Per round each variant gets one untimed call and up to ``block`` timed ones, so a drift of the machine's
    load falls on all variants alike.

    Parameters
    ----------
    variants : Sequence of Variant
        The variants timed.
    x : Any
        Their input.
    iters : int
        Timed calls per variant.
    block : int
        The most timed calls of a variant per round.

    Returns
    -------
    dict
        Variant name -> the seconds of its ``iters`` calls.
    """
    times: dict[str, list[float]] = {v.name: [] for v in variants}
    while any(len(t) < iters for t in times.values()):
        for v in variants:
            need = min(block, iters - len(times[v.name]))
            if need > 0:
                times[v.name] += time_calls(v.run, x, 1, need, v.sync)
    return times


def build_variants(model, device, resolution: int, names: Sequence[str], onnx_path: str | Path | None = None,
                   int8_path: str | Path | None = None) -> tuple[list[Variant], dict[str, str]]:
    """Load the engines ``names`` (old names too) that can run here.

    Parameters
    ----------
    model : TinyUNet
        The student.
    device : str or torch.device
        The device asked for.
    resolution : int
        The working resolution.
    names : Sequence of str
        Benchmark variants (:data:`VARIANTS`).
    onnx_path : str or Path or None
        The fp32 ONNX model, for the ONNX variants.
    int8_path : str or Path or None
        The int8 ONNX model, for the int8 variants.

    Returns
    -------
    tuple
        ``(variants, skipped)``: the loaded :class:`Variant` list, and ``{name: why}`` of those that cannot run.

    Raises
    ------
    InputError
        A name is not a benchmark variant (``deploy.benchmark_variants``).
    """
    dev = torch.device(device)
    sync = (lambda: torch.cuda.synchronize()) if dev.type == "cuda" else (lambda: None)
    # ONNX Runtime sessions used for timing do not spin: idle pools must not steal the timed cores
    src = Source(model, dev, resolution, {ONNX_FILE: onnx_path, INT8_FILE: int8_path}, spinning=False)
    skipped: dict[str, str] = {}
    variants: list[Variant] = []
    for name in dict.fromkeys(map(engine_name, names)):
        if name not in VARIANTS or name not in ENGINES:
            raise InputError(f"deploy.benchmark_variants: unknown variant {name!r}")
        if (reason := unavailable(name, src)) is not None:
            skipped[name] = reason
            continue
        engine = ENGINES[name]
        where = engine.device(dev)
        variants.append(Variant(name, engine.description, engine.load(src).run, where,
                                sync if where == dev.type else (lambda: None)))
    return variants, skipped


def mean_image_iou(masks: np.ndarray, reference: np.ndarray) -> float:
    """Average the per-image IoU; NaN without images."""
    return float(np.mean(image_ious(masks, reference))) if len(masks) else float("nan")


def variant_probs(variant: Variant, images: np.ndarray, batch_size: int) -> np.ndarray:
    """Run a variant on uint8 images [N,H,W,3]: P = sigmoid(Z) float32 [N,H,W]."""
    out = np.empty(images.shape[:3], np.float32)
    for s in range(0, len(images), batch_size):
        z = variant.run(images_to_tensor(np.asarray(images[s:s + batch_size])))
        out[s:s + batch_size] = torch.sigmoid(torch.as_tensor(z).float())[:, 0].cpu().numpy()
    return out


def slow_status(probe_ms: float, baseline_probe_ms: float | None, factor: float = SLOW_FACTOR) -> str | None:
    """Mark a variant slow when its probe took more than ``factor`` x the baseline's.

    Parameters
    ----------
    probe_ms : float
        The variant's probe, ms.
    baseline_probe_ms : float or None
        The baseline's probe, ms (None: not probed).
    factor : float
        The slowdown beyond which a variant is not fully timed.

    Returns
    -------
    str or None
        The variant's status when too slow, else None (time it fully).
    """
    if baseline_probe_ms is None or not baseline_probe_ms > 0 or not probe_ms > factor * baseline_probe_ms:
        return None
    return (f"slow on this CPU (probe: {probe_ms:.1f} ms, {probe_ms / baseline_probe_ms:.1f}x the "
            f"{BASELINE_VARIANT} probe > {factor:g}x): not fully timed")


def variant_remark(status: str, probe_ms: float, baseline_probe_ms: float | None) -> str:
    """Say in the efficiency table why a variant was not run or not fully timed.

    Parameters
    ----------
    status : str
        The variant's status (:data:`OK`, :data:`SKIPPED` with its reason, or :func:`slow_status`).
    probe_ms : float
        Its probe, ms.
    baseline_probe_ms : float or None
        The baseline's probe, ms.

    Returns
    -------
    str
        The note; "" for a fully timed variant.
    """
    if status.startswith(SKIPPED):
        return "not run: " + status.split(": ", 1)[-1]
    if status == OK:
        return ""
    ratio = probe_ms / baseline_probe_ms if baseline_probe_ms else float("nan")
    return (f"not timed: probe {probe_ms:.0f} ms = {ratio:.0f}x the {BASELINE_VARIANT} probe "
            f"(pathologically slow on this CPU)")


def _row(name: str, description: str, device: str, params: int, gflops: float, resolution: int, status: str,
         probe: float = float("nan"), base_probe: float | None = None, mem: PeakMemory | None = None) -> dict:
    """Start a variant's row before its timing (every measurement NaN)."""
    nan = float("nan")
    return {"variant": name, "description": description, "device": device, "params": params, "gflops": gflops,
            "throughput": nan, "batch": 0, "peak_mb": mem.peak_mb if mem else nan,
            "peak_method": mem.method if mem else "", "iou": nan, "resolution": int(resolution), "probe_ms": probe,
            "status": status, "timed": status == OK, "remark": variant_remark(status, probe, base_probe)}


def measure_variants(model, *, resolution: int, device="cpu", variants: Sequence[str], warmup: int, iters: int,
                     batches: Sequence[int], tau: float | None = None, val_images: np.ndarray | None = None,
                     val_masks: np.ndarray | None = None, onnx_path=None, int8_path=None,
                     seed: int = 0,  # not a param: the timing inputs' random stream
                     on_variant: Callable[[str], None] = lambda name: None,
                     slow_factor: float | None = None) -> tuple[list[dict], dict]:
    """Measure every variant: memory, probe, latency, throughput and validation IoU.

    Per variant: ``peak_mb`` over ``max(1, warmup)`` warm-up calls, the probe, latency (median of ``iters``
    batch-1 calls, timed round-robin by :func:`interleaved_times`), throughput (best of
    :func:`throughput_sweep`), ``iou`` of [P >= tau] (eq:inference-mask) and, against the baseline,
    ``iou_delta``, ``iou_vs_fp32`` and ``speedup``.  Params and GFLOPs are the PyTorch graph's for every variant.

    Parameters
    ----------
    model : TinyUNet
        The student.
    resolution : int
        The side of the timed images.
    device : str or torch.device
        The device asked for.
    variants : Sequence of str
        The variants (``deploy.benchmark_variants``).
    warmup : int
        Untimed calls before the timing (``deploy.benchmark_warmup``).
    iters : int
        Timed batch-1 calls (``deploy.benchmark_iters``).
    batches : Sequence of int
        The batch sizes of the throughput sweep (``deploy.benchmark_batches``).
    tau : float or None
        The mask threshold; None: no IoU.
    val_images : np.ndarray or None
        uint8 [N,R,R,3] validation images; None: no IoU.
    val_masks : np.ndarray or None
        bool [N,R,R] their reference masks (accuracy only).
    onnx_path : str or Path or None
        The fp32 ONNX model.
    int8_path : str or Path or None
        The int8 ONNX model.
    seed : int
        The seed of the random timing inputs.
    on_variant : Callable
        Called with each variant's name before it is measured (progress).
    slow_factor : float or None
        The probe slowdown beyond which a variant is not fully timed; None: :data:`SLOW_FACTOR` as it is now.

    Returns
    -------
    tuple
        ``(rows, info)``: one dict per variant in the order of ``variants`` (skipped ones with their status),
        and the run's conditions (threads, device, timing, sweeps, slow and skipped variants).
    """
    slow_factor = SLOW_FACTOR if slow_factor is None else slow_factor  # None: the constant as it is at call time
    dev = torch.device(device)
    deployed = mask_path_model(model)
    params = count_parameters(deployed)
    gflops = count_flops(deployed, resolution, resolution) / 1e9
    built, skipped = build_variants(model, dev, resolution, variants, onnx_path, int8_path)
    g = torch.Generator().manual_seed(seed)
    x1 = torch.rand(1, deployed.config["in_channels"], resolution, resolution, generator=g)
    have_val = val_images is not None and val_masks is not None and len(val_images) > 0 and tau is not None
    rows: dict[str, dict] = {}
    masks: dict[str, np.ndarray] = {}
    sweeps: dict[str, Sweep] = {}
    base_probe = None
    for v in sorted(built, key=lambda v: v.name != BASELINE_VARIANT):  # the baseline is probed first
        on_variant(v.name)
        with PeakMemory(v.device) as mem:
            time_calls(v.run, x1, max(1, warmup), 0, v.sync)
        probe = statistics.median(time_calls(v.run, x1, 0, PROBE_CALLS, v.sync)) * 1e3
        base_probe = probe if v.name == BASELINE_VARIANT else base_probe
        rows[v.name] = row = _row(v.name, v.description, v.device, params, gflops, resolution,
                                  slow_status(probe, base_probe, slow_factor) or OK, probe, base_probe, mem)
        if row["status"] != OK:
            continue
        tried = throughput_batches(batches, v.device)
        if tried != [1]:  # at batch 1 alone the round-robin below measures it
            sweeps[v.name] = throughput_sweep(v, x1.shape[1], resolution, tried, iters, g)
            row["throughput"], row["batch"] = sweeps[v.name].best, sweeps[v.name].batch
        if have_val:
            masks[v.name] = mask_from_probs(variant_probs(v, val_images, max(batches)), tau)
            row["iou"] = mean_image_iou(masks[v.name], val_masks)
    for name, why in skipped.items():
        rows[name] = _row(name, ENGINES[name].description, ENGINES[name].device(dev), params, gflops, resolution,
                          f"{SKIPPED}: {why}")
    timed = [v for v in built if rows[v.name]["status"] == OK]
    times = interleaved_times(timed, x1, iters)
    base = rows.get(BASELINE_VARIANT)
    for name, r in rows.items():
        t = times.get(name)
        r["latency_ms"] = statistics.median(t) * 1e3 if t else float("nan")
        r["latency_min_ms"] = min(t) * 1e3 if t else float("nan")
        if t and name not in sweeps:
            sweeps[name] = Sweep({1: 1e3 / r["latency_ms"]}, 1e3 / r["latency_ms"], 1)
            r["throughput"], r["batch"] = sweeps[name].best, 1
    base_masks = masks.get(BASELINE_VARIANT)
    for name, r in rows.items():
        r["iou_delta"] = r["iou"] - base["iou"] if base is not None and have_val else float("nan")
        r["iou_vs_fp32"] = (mean_image_iou(masks[name], base_masks) if base_masks is not None and name in masks
                            else float("nan"))
        r["speedup"] = base["latency_ms"] / r["latency_ms"] if base else float("nan")
    info = {"threads": torch.get_num_threads(), "device": str(dev), "resolution": int(resolution),
            "warmup": int(warmup), "iters": int(iters), "batches": [int(b) for b in batches],
            "throughput_sweep": {n: sw.record() for n, sw in sweeps.items()},
            "latency_timing": "round-robin across variants (interleaved_times)",
            "probe": {"calls": PROBE_CALLS, "slow_factor": float(slow_factor)},
            "slow": {n: r["status"] for n, r in rows.items() if r["status"] != OK and n not in skipped},
            "tau": tau, "n_val": int(len(val_images)) if have_val else 0, "skipped": skipped}
    order = dict.fromkeys([*variants, *(v.name for v in built), *skipped])
    return [rows[n] for n in order if n in rows], info


@dataclasses.dataclass
class Sweep:
    """A throughput sweep.

    Attributes
    ----------
    images_per_s : dict
        Batch size -> images/s.
    best : float
        The best images/s.
    batch : int
        The batch size that gave it.
    oom_batch : int or None
        The batch that ran out of GPU memory and ended the sweep.
    """

    images_per_s: dict[int, float]
    best: float
    batch: int
    oom_batch: int | None = None

    def record(self) -> dict:
        """Record the sweep for JSON.

        Returns
        -------
        dict
            ``images_per_s`` (its batches as strings), ``best_batch`` and ``oom_batch``.
        """
        return {"images_per_s": {str(b): tp for b, tp in self.images_per_s.items()}, "best_batch": self.batch,
                "oom_batch": self.oom_batch}


def throughput_batches(batches: Sequence[int], device: str) -> list[int]:
    """List the batch sizes a throughput sweep tries.

    Parameters
    ----------
    batches : Sequence of int
        The configured batch sizes (``deploy.benchmark_batches``).
    device : str
        The variant's device.

    Returns
    -------
    list of int
        ``batches``, and on CUDA every power of two up to :data:`CUDA_MAX_BATCH` too, ascending.
    """
    tried = {int(b) for b in batches}
    if str(device).startswith("cuda"):
        tried |= {2 ** k for k in range(CUDA_MAX_BATCH.bit_length()) if 2 ** k <= CUDA_MAX_BATCH}
    return sorted(tried)


def throughput_sweep(variant: Variant, channels: int, resolution: int, batches: Sequence[int], iters: int,
                     generator) -> Sweep:
    """Measure the images/s of ``variant`` at each batch size.

    At batch b: b / the median of max(2, ceil(iters / b)) calls.  The first batch out of GPU memory ends the
    sweep (and is raised when it is the first batch).

    Parameters
    ----------
    variant : Variant
        The variant.
    channels : int
        The input's channels.
    resolution : int
        The input's side.
    batches : Sequence of int
        The batch sizes (:func:`throughput_batches`).
    iters : int
        The calls at batch 1; fewer at larger batches.
    generator : torch.Generator
        The random inputs' stream.

    Returns
    -------
    Sweep
        The images/s per batch, the best, and the batch out of memory.
    """
    tps: dict[int, float] = {}
    oom = None
    for b in sorted(int(b) for b in batches):
        xb = torch.rand(b, channels, resolution, resolution, generator=generator)
        try:
            tb = time_calls(variant.run, xb, 1, max(2, math.ceil(iters / b)), variant.sync)
        except torch.cuda.OutOfMemoryError:
            if not tps:
                raise
            del xb
            if torch.cuda.is_available():  # give the cached blocks of the failed batch back
                torch.cuda.synchronize()
                torch.cuda.empty_cache()
            oom = b
            break
        tps[b] = b / statistics.median(tb)
    best_b = max(tps, key=lambda b: tps[b])
    return Sweep(tps, tps[best_b], best_b, oom)


def fastest_within(rows: Sequence[dict], max_iou_drop: float) -> dict | None:
    """Pick the lowest-latency fully timed variant within the IoU budget.

    Parameters
    ----------
    rows : Sequence of dict
        :func:`measure_variants` rows.
    max_iou_drop : float
        The largest |iou_delta| allowed (``deploy.target_iou_drop``); a NaN delta passes.

    Returns
    -------
    dict or None
        The fastest such row, or None.
    """
    ok = [r for r in rows if r.get("status", OK) == OK and math.isfinite(r["latency_ms"])
          and not (abs(r["iou_delta"]) > max_iou_drop)]
    return min(ok, key=lambda r: r["latency_ms"]) if ok else None


def benchmark_settings(cfg: dict) -> dict:
    """Read the benchmark's settings from a validated ``deploy`` section.

    Parameters
    ----------
    cfg : dict
        The validated ``deploy:`` section.

    Returns
    -------
    dict
        ``warmup``, ``iters``, ``batches``, ``variants``, ``int8_settings``, ``target_ms``, ``max_drop``,
        ``target_res``, ``opset`` and ``resolution``.
    """
    return {"warmup": cfg["benchmark_warmup"], "iters": cfg["benchmark_iters"], "batches": cfg["benchmark_batches"],
            "variants": cfg["benchmark_variants"], "int8_settings": q8.Int8Settings.from_params(cfg),
            "target_ms": float(cfg["target_latency_ms"]),
            "max_drop": float(cfg["target_iou_drop"]), "target_res": cfg["target_resolution"],
            "opset": cfg["opset"], "resolution": cfg["benchmark_resolution"]}


@dataclasses.dataclass
class Target:
    """The model under test: from a deploy bundle or a checkpoint.

    Attributes
    ----------
    model : object
        The student, on the CPU.
    tau : float
        Its threshold (eq:inference-mask).
    tau_source : str
        Where ``tau`` came from.
    resolution : int or None
        Its recorded working resolution.
    onnx_path : Path or None
        The bundle's fp32 ONNX model.
    int8_path : Path or None
        The bundle's int8 ONNX model.
    int8_info : dict
        deploy.json's ``int8`` entry.
    inputs : list
        The artifacts opened, for the lineage.
    """

    model: object
    tau: float
    tau_source: str
    resolution: int | None
    onnx_path: Path | None
    int8_path: Path | None
    int8_info: dict
    inputs: list


def open_target(deploy_dir=None, checkpoint=None, thresholds=None, tau=None, params=None) -> Target:
    """Open the model under test: exactly one of a deploy bundle or a checkpoint folder, on the CPU.

    Parameters
    ----------
    deploy_dir : str or Path or None
        A deploy bundle (``--deploy``).
    checkpoint : str or Path or None
        A checkpoint folder (``--checkpoint``).
    thresholds : str or Path or None
        The checkpoint's thresholds table (a tau candidate).
    tau : float or None
        A threshold overriding the model's.
    params : dict or None
        Params whose ``calibrate.fixed_tau`` is the last tau candidate.

    Returns
    -------
    Target
        The model with its tau (eq:inference-mask) and files.

    Raises
    ------
    InputError
        Neither or both of ``deploy_dir`` and ``checkpoint`` are given.
    """
    if (deploy_dir is None) == (checkpoint is None):
        raise InputError("give exactly one of --deploy (a bundle) or --checkpoint")
    if deploy_dir is not None:
        d = Path(deploy_dir)
        inputs = [open_artifact(d, "deploy")]
        info = read_deploy_info(d)
        model, _ = load_student(d, "cpu")
        value, source = resolve_tau(option=tau, **tau_candidates(bundle=info, params=params))
        return Target(model, value, source, info["resolution"], d / ONNX_FILE if (d / ONNX_FILE).exists() else None,
                      d / INT8_FILE if (d / INT8_FILE).exists() else None, info.get("int8") or {}, inputs)
    seg = load_segmenter(checkpoint, "torch", "cpu", thresholds, params=params)
    model, _ = load_student(checkpoint, "cpu")
    value, source = seg.resolve_tau(option=tau)
    return Target(model, value, source, seg.resolution, None, None, {}, [open_artifact(checkpoint, "checkpoint")])


def read_benchmark_data(art: str | Path, n_calib: int):
    """Read the benchmark's data from an artifacts folder.

    The reference masks only measure accuracy here.

    Parameters
    ----------
    art : str or Path
        The artifacts folder.
    n_calib : int
        The most int8 calibration images (``deploy.int8_calibration_images``).

    Returns
    -------
    tuple
        ``(val_images, val_masks, calibration_images, opened)``: validation images and their masks, the int8
        calibration images as export picks them, and the artifacts opened; Nones and [] without the artifacts.
    """
    reference_path = catalog.path("reference", art)
    calib, opened, _ = q8.read_calibration_images(art, n_calib) if reference_path.exists() else (None, [], "")
    if not opened:
        return None, None, None, []
    (manifest, images), reference = opened, open_artifact(reference_path, "reference")
    val = np.flatnonzero((manifest.df["split"].to_numpy() == "val") & np.asarray(reference.numpy("has_mask"), bool))
    val_images = read_chunk_rows(images["image"], val) if val.size else None
    val_masks = read_chunk_rows(reference["mask"], val).astype(bool) if val.size else None
    return val_images, val_masks, calib, [manifest, images, reference]


def prepare_onnx_models(target: Target, variants: Sequence[str], workdir: str | Path, *, resolution: int,
                        opset: int, calibration_images: np.ndarray | None, int8_settings: q8.Int8Settings) -> tuple:
    """Find or make the ONNX models the variants need.

    The bundle's models, else exported or quantised into ``workdir``: int8 on ``calibration_images``, else on
    smooth noise, and only for an int8 variant.

    Parameters
    ----------
    target : Target
        The model under test.
    variants : Sequence of str
        The variants to run.
    workdir : str or Path
        A scratch folder for exported models.
    resolution : int
        The export's example size.
    opset : int
        The ONNX opset (``deploy.opset``).
    calibration_images : np.ndarray or None
        uint8 training images for int8 calibration.
    int8_settings : Int8Settings
        The int8 calibration.

    Returns
    -------
    tuple
        ``(onnx_path, int8_path, notes)``: the models (None when absent) and notes saying how they were made,
        or why there are none.
    """
    reason = onnx_unavailable_reason()
    if reason is not None:
        return None, None, {"onnx": reason}
    onnx_path = target.onnx_path or export_onnx(target.model, Path(workdir) / ONNX_FILE, resolution, opset)
    if not set(map(engine_name, variants)) & set(INT8_VARIANTS):
        return onnx_path, None, {}
    if target.int8_path is not None:
        return onnx_path, target.int8_path, {"int8_calibration": (
            f"deploy bundle's {INT8_FILE} (calibrated at export on "
            f"{target.int8_info.get('calibration_images', '?')} training-split images)")}
    calib = calibration_images
    note = f"{len(calib)} training-split images (no masks)" if calib is not None else \
        "no training images found: calibrated on synthetic smooth noise"
    if calib is None:
        calib = (parity_inputs(min(resolution, 128), n=4).permute(0, 2, 3, 1).numpy() * 255).round().astype(np.uint8)
    int8_path = q8.quantize_onnx_int8(onnx_path, Path(workdir) / "model_int8.onnx", calib, int8_settings)
    return onnx_path, int8_path, {"int8_calibration": note}


def clean(v):
    """Make a JSON value: non-finite floats -> None."""
    return None if isinstance(v, float) and not math.isfinite(v) else v


def fast_path_summary(rows: Sequence[dict], resolution: int, *, target_ms: float, target_res: int,
                      max_drop: float) -> dict | None:
    """Sum up the fast path (:func:`fastest_within`) and its verdicts.

    Parameters
    ----------
    rows : Sequence of dict
        :func:`measure_variants` rows.
    resolution : int
        The resolution timed.
    target_ms : float
        The latency target (``deploy.target_latency_ms``).
    target_res : int
        The resolution the target is judged at (``deploy.target_resolution``); at any other, not judged.
    max_drop : float
        The IoU budget (``deploy.target_iou_drop``).

    Returns
    -------
    dict or None
        The fast path's variant, latency, speed-up, IoU change and verdicts; None when no variant qualifies.
    """
    fast = fastest_within(rows, max_drop)
    if fast is None:
        return None
    meets = fast["latency_ms"] <= target_ms if resolution == target_res else None
    return {"variant": fast["variant"], "latency_ms": fast["latency_ms"], "speedup": fast["speedup"],
            "iou_delta": clean(fast["iou_delta"]), "meets_latency_target": meets,
            "within_iou_drop": None if math.isnan(fast["iou_delta"]) else abs(fast["iou_delta"]) <= max_drop,
            "verdict": "not judged at this size" if meets is None else "met" if meets else "NOT met"}


def fast_path_line(summary: dict, rows: Sequence[dict], resolution: int, target_ms: float, target_res: int) -> str:
    """Say the fast path, its speed-up over the baseline and the latency verdict in one line.

    Parameters
    ----------
    summary : dict
        :func:`fast_path_summary`.
    rows : Sequence of dict
        :func:`measure_variants` rows (the baseline's latency).
    resolution : int
        The resolution timed.
    target_ms : float
        The latency target.
    target_res : int
        The resolution the target is judged at.

    Returns
    -------
    str
        The line.
    """
    base = next((r for r in rows if r["variant"] == BASELINE_VARIANT), None)
    return (f"fast path: {summary['variant']} {summary['latency_ms']:.1f} ms/image at {resolution}px batch 1 "
            f"({summary['speedup']:.1f}x the {BASELINE_VARIANT} baseline"
            + (f" of {base['latency_ms']:.1f} ms" if base else "") + f"); target {target_ms:g} ms at "
            f"{target_res}px: {summary['verdict']}")


def _cell(v, spec: str, width: int) -> str:
    """Format ``v`` by ``spec``, or ``--`` when it is missing or not finite."""
    return format(v, spec) if v is not None and math.isfinite(v) else f"{'--':>{width}s}"


def format_table(rows: Sequence[dict]) -> str:
    """Format the efficiency table for stdout.

    A variant skipped or only probed shows its status; there are no IoU columns without any IoU.

    Parameters
    ----------
    rows : Sequence of dict
        :func:`measure_variants` rows.

    Returns
    -------
    str
        The table, its header and a footnote.
    """
    timed = [r for r in rows if r.get("status", OK) == OK]
    scored = any(_cell(r.get("iou"), ".4f", 1) != "--" for r in timed)
    head = (f"{'variant':22s} {'latency ms':>10s} {'x base':>7s} {'img/s':>8s} {'batch':>5s} {'peak MB':>8s}"
            + (f" {'IoU':>7s} {'dIoU':>8s} {'mIoU fp32':>9s}" if scored else ""))
    lines = [head, "-" * len(head)]
    for r in rows:
        if r.get("status", OK) != OK:
            lines.append(f"{r['variant']:22s} {r['status']}")
            continue
        lines.append(f"{r['variant']:22s} {_cell(r['latency_ms'], '10.2f', 10)} {_cell(r['speedup'], '7.2f', 7)} "
                     f"{_cell(r['throughput'], '8.2f', 8)} {r['batch']:5d} {_cell(r['peak_mb'], '8.1f', 8)}"
                     + (f" {_cell(r['iou'], '7.4f', 7)} {_cell(r['iou_delta'], '+8.4f', 8)} "
                        f"{_cell(r['iou_vs_fp32'], '9.4f', 9)}" if scored else "")
                     + (f"  ({r['remark']})" if r.get("remark") else ""))
    lines.append(f"(x base = {BASELINE_VARIANT} latency / variant latency, timed round-robin in the same run"
                 + (f"; mIoU fp32 = mean per-image IoU of the variant's masks with {BASELINE_VARIANT}'s)" if scored
                    else "; IoU columns not computed: no validation images with masks)"))
    return "\n".join(lines)


def format_sweep(run_info: dict) -> str:
    """Format one line per variant swept beyond ``deploy.benchmark_batches`` (CUDA).

    Parameters
    ----------
    run_info : dict
        :func:`measure_variants`' info.

    Returns
    -------
    str
        The lines; "" when no variant was.
    """
    configured = {str(b) for b in run_info["batches"]}
    lines = []
    for name, sw in run_info.get("throughput_sweep", {}).items():
        if set(sw["images_per_s"]) <= configured:
            continue
        cells = ", ".join(f"{b}: {tp:,.0f}" for b, tp in sw["images_per_s"].items())
        oom = f"; batch {sw['oom_batch']} ran out of memory" if sw["oom_batch"] is not None else ""
        lines.append(f"throughput sweep {name} (batch: images/s): {cells}; best at batch {sw['best_batch']}{oom}")
    return "\n".join(lines)


def benchmark_result(rows: Sequence[dict], run_info: dict, settings: dict, *, tau: float, summary: dict | None,
                     notes: dict) -> dict:
    """Build the JSON document of a benchmark run (non-finite numbers as null).

    Parameters
    ----------
    rows : Sequence of dict
        :func:`measure_variants` rows.
    run_info : dict
        :func:`measure_variants`' info.
    settings : dict
        :func:`benchmark_settings`.
    tau : float
        The threshold used.
    summary : dict or None
        :func:`fast_path_summary`.
    notes : dict
        How the ONNX models were made (:func:`prepare_onnx_models`).

    Returns
    -------
    dict
        The document.
    """
    return {
        "resolution": run_info["resolution"], "device": run_info["device"], "threads": run_info["threads"],
        "tau": tau, "n_val": run_info["n_val"], "warmup": settings["warmup"], "iters": settings["iters"],
        "batches": run_info["batches"], "baseline": BASELINE_VARIANT, "fast_path": summary,
        "target": {"latency_ms": settings["target_ms"], "max_iou_drop": settings["max_drop"], "batch": 1,
                   "resolution": settings["target_res"]},
        "peak_memory_method": next((r["peak_method"] for r in rows if r["peak_method"]), ""),
        "skipped": run_info["skipped"], "notes": notes,
        "probe": run_info["probe"], "slow": run_info["slow"], "throughput_sweep": run_info.get("throughput_sweep", {}),
        "variants": {r["variant"]: {k: clean(v) for k, v in r.items() if k != "variant"} for r in rows},
    }
