"""Efficiency benchmark of the deployed mask path on this machine: variants, timing, peak memory, the
fast path and its verdicts.

Per variant (:func:`build_variants`): parameters and GFLOPs counted on the graph, batch-1 latency
(median, timed round-robin across the variants), best-batch throughput, peak memory, and the change of
the mean validation Image IoU against the fp32 baseline at the deployed tau (eq:inference-mask).

Decisions:

* Never call what the host cannot run natively.  A variant the host cannot run (a missing package or
  file, CUDA on a CPU, bf16 on a CPU without the native-bf16 flags -- emulated, up to a minute per
  384² image: :func:`pipeline.deploy.engines.unavailable`) is decided before any call and gets a row
  whose ``status`` is "skipped: <why>" (:data:`SKIPPED`), every number NaN.
* Probe first.  Every other variant gets its warm-up and :data:`PROBE_CALLS` timed batch-1 calls before
  any full timing.  A variant whose probe median is more than :data:`SLOW_FACTOR` times the
  baseline's is not timed further: its row keeps the probe (``probe_ms``), ``status`` says "slow on
  this CPU (...)", and latency, throughput and the IoU columns are NaN (batch 0).  It can never be the
  fast path.  For the report, every row also has ``timed`` (fully timed) and ``remark``
  (:func:`variant_remark`: "not run: ...", "not timed: ... pathologically slow on this CPU" or "").
* ONNX Runtime sessions used for timing do not spin (:func:`pipeline.deploy.mask_path.ort_session`,
  ``spinning=False``): an idle spinning pool would steal the cores the round-robin measures others on.
* Throughput on CUDA: the batches sweep ``deploy.benchmark_batches`` and every power of two up to
  :data:`CUDA_MAX_BATCH` (256), stopping at the first batch that raises ``torch.cuda.OutOfMemoryError``;
  the best is reported (:func:`throughput_batches`, :func:`throughput_sweep`).  A small model fills a
  GPU only at large batches; on a CPU the configured batches are kept as they are.
* Peak memory: CPU -- growth of the process's peak resident set (Linux ``/proc/self/clear_refs``
  reset of VmHWM, then VmHWM - VmRSS before the run, after ``malloc_trim``); CUDA --
  ``torch.cuda.max_memory_allocated`` after ``reset_peak_memory_stats``.  Where neither is
  available, NaN.
* The latency target (``deploy.target_latency_ms``) is defined at ``deploy.target_resolution``, batch 1:
  at another size it is "not judged", never "met" (:func:`fast_path_summary`).  Timings are
  measurements of this machine and its load: nothing asserts a target, the results record whether it
  was met.
* int8: the bundle's ``model.int8.onnx`` (calibrated at export) when it has one -- the very file
  segment runs; otherwise the ONNX model is quantised here with the same code
  (pipeline.deploy.quantize) on training-split images only (no masks), or on synthetic smooth noise
  when there are none (:func:`prepare_onnx_models`).
"""

from __future__ import annotations

import ctypes
import dataclasses
import math
import statistics
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

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
from pipeline.deploy.engine_table import BENCHMARK_VARIANTS, engine_name
from pipeline.thresholds import mask_from_probs, resolve_tau, tau_candidates

BASELINE_VARIANT = "fp32_eager_nchw"
VARIANTS = tuple(BENCHMARK_VARIANTS)  # the engine table's benchmark variants (deploy.benchmark_variants)
SLOW_FACTOR = 4.0  # a variant probed more than this many times slower than the baseline is not fully timed
PROBE_CALLS = 2    # timed batch-1 calls of the probe (after the warm-up)
OK = "ok"
SKIPPED = "skipped"  # the status of a variant never called on this host: "skipped: <why>"
#: the timer of every measurement (a module attribute so that a test can put a fake clock in its place)
clock = time.perf_counter
CUDA_MAX_BATCH = 256  # on CUDA the throughput sweep goes up to this batch, or to the first out-of-memory one
INT8_VARIANTS = tuple(n for n in VARIANTS if ENGINES[n].needs == INT8_FILE)  # run the bundle's int8 model


@dataclasses.dataclass
class Variant:
    """One way of running the mask path: ``run(x float32 NCHW tensor) -> logits`` (tensor or array)."""

    name: str
    description: str
    run: Callable
    device: str
    sync: Callable[[], None] = lambda: None


def _malloc_trim() -> None:
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except Exception:  # noqa: BLE001 -- not glibc: nothing to trim
        pass


def _status_kb(field: str) -> int | None:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


class PeakMemory:
    """Peak memory growth (MiB) over a block: CPU via VmHWM reset, CUDA via max_memory_allocated."""

    def __init__(self, device: str):
        self.device = device
        self.peak_mb = float("nan")
        self.method = "unavailable"

    def __enter__(self):
        import torch

        if self.device.startswith("cuda"):
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
            self._base = torch.cuda.memory_allocated()
            self.method = "torch.cuda.max_memory_allocated - allocated before"
            return self
        _malloc_trim()
        self._base = None
        try:
            with open("/proc/self/clear_refs", "w") as f:
                f.write("5")  # resets VmHWM to the current RSS
            self._base = _status_kb("VmRSS")
            self.method = "peak RSS growth (VmHWM after - VmRSS before, /proc/self/clear_refs)"
        except OSError:
            pass
        return self

    def __exit__(self, *exc):
        import torch

        if self.device.startswith("cuda"):
            torch.cuda.synchronize()
            self.peak_mb = (torch.cuda.max_memory_allocated() - self._base) / 2**20
        elif self._base is not None:
            hwm = _status_kb("VmHWM")
            if hwm is not None:
                self.peak_mb = max(0, hwm - self._base) / 1024
        return False


def time_calls(fn: Callable, x, warmup: int, iters: int, sync: Callable[[], None]) -> list[float]:
    """Wall-clock seconds of ``iters`` calls after ``warmup`` untimed ones."""
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
    """Call times (s) of every variant on ``x``, measured round-robin until each has ``iters``.

    Each round gives every variant one untimed call (its caches refill after the others ran) and then
    up to ``block`` timed calls.  Measuring variant after variant instead lets a slow drift of the
    machine's load -- other tenants of a shared CPU -- fall on some variants and not on others; in
    rounds it falls on all alike, which keeps the ratios to the baseline fair.
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
    """Variants of the mask path to compare; returns (variants, {skipped name: reason}).  Each name is
    an engine of the registry (pipeline.deploy.engines.ENGINES: what it runs and how) or an old name of one:

    fp32_eager_nchw          plain PyTorch, contiguous NCHW (the baseline)
    fp32_channels_last       PyTorch, channels_last model and input
    bf16_autocast            PyTorch NCHW under bf16 autocast
    bf16_channels_last       bf16 autocast + channels_last
    torchscript_frozen       traced, frozen, torch.jit.optimize_for_inference (CPU: oneDNN fusions)
    onnxruntime_fp32         ONNX Runtime CPU, all graph optimisations
    onnxruntime_int8         ONNX Runtime CPU on the static int8 QDQ model (quantize_onnx_int8)
    openvino_int8            the same int8 file on OpenVINO's CPU plugin (pipeline.deploy.openvino_engine)
    cuda_graph_bf16          CUDA only: bf16 + channels_last + CUDA graphs (pipeline.deploy.cuda_engine)
    """
    import torch

    dev = torch.device(device)
    sync = (lambda: torch.cuda.synchronize()) if dev.type == "cuda" else (lambda: None)
    # ONNX Runtime sessions used for timing do not spin: idle pools must not steal the timed cores
    src = Source(model, dev, resolution, {ONNX_FILE: onnx_path, INT8_FILE: int8_path}, spinning=False)
    skipped: dict[str, str] = {}
    variants: list[Variant] = []
    for name in dict.fromkeys(map(engine_name, names)):
        if name not in VARIANTS or name not in ENGINES:
            raise InputError(f"deploy.benchmark_variants: unknown variant {name!r}")
        reason = unavailable(name, src)
        if reason is not None:
            skipped[name] = reason
            continue
        engine = ENGINES[name]
        where = engine.device(dev)
        variants.append(Variant(name, engine.description, engine.load(src).run, where,
                                sync if where == dev.type else (lambda: None)))
    return variants, skipped


def mean_image_iou(masks: np.ndarray, reference: np.ndarray) -> float:
    """Mean over images of image_iou(masks[i], reference[i]) (pipeline.metrics; both empty -> 1); NaN if none."""
    return float(np.mean(image_ious(masks, reference))) if len(masks) else float("nan")


def variant_probs(variant: Variant, images: np.ndarray, batch_size: int) -> np.ndarray:
    """P = sigmoid(Z) float32 [N,H,W] of a variant on uint8 images [N,H,W,3]."""
    import torch

    out = np.empty(images.shape[:3], np.float32)
    for s in range(0, len(images), batch_size):
        z = variant.run(images_to_tensor(np.asarray(images[s:s + batch_size])))
        out[s:s + batch_size] = torch.sigmoid(torch.as_tensor(z).float())[:, 0].cpu().numpy()
    return out


def slow_status(probe_ms: float, baseline_probe_ms: float | None, factor: float = SLOW_FACTOR) -> str | None:
    """The status of a variant whose probe is more than ``factor`` x the baseline's probe
    ("slow on this CPU (probe: X ms, Y x the baseline)"), else None (time it fully; also when there is
    no baseline probe to compare with)."""
    if baseline_probe_ms is None or not baseline_probe_ms > 0 or not probe_ms > factor * baseline_probe_ms:
        return None
    return (f"slow on this CPU (probe: {probe_ms:.1f} ms, {probe_ms / baseline_probe_ms:.1f}x the "
            f"{BASELINE_VARIANT} probe > {factor:g}x): not fully timed")


def variant_remark(status: str, probe_ms: float, baseline_probe_ms: float | None) -> str:
    """A short note for the efficiency table ("" when there is nothing to say): why a variant was not
    run (``status`` "skipped: <why>") or not fully timed."""
    if status.startswith(SKIPPED):
        return "not run: " + status.split(": ", 1)[-1]
    if status == OK:
        return ""
    ratio = probe_ms / baseline_probe_ms if baseline_probe_ms else float("nan")
    return (f"not timed: probe {probe_ms:.0f} ms = {ratio:.0f}x the {BASELINE_VARIANT} probe "
            f"(pathologically slow on this CPU)")


def skipped_row(name: str, why: str, device: str, params: int, gflops: float, resolution: int) -> dict:
    """The row of a variant never called on this host (``status`` "skipped: <why>", every measurement NaN)."""
    nan = float("nan")
    status = f"{SKIPPED}: {why}"
    return {"variant": name, "description": ENGINES[name].description if name in ENGINES else name,
            "device": device, "params": params, "gflops": gflops, "throughput": nan, "batch": 0, "peak_mb": nan,
            "peak_method": "", "iou": nan, "resolution": int(resolution), "probe_ms": nan, "status": status,
            "timed": False, "remark": variant_remark(status, nan, None)}


def measure_variants(model, *, resolution: int, device="cpu", variants: Sequence[str], warmup: int, iters: int,
                     batches: Sequence[int], tau: float | None = None, val_images: np.ndarray | None = None,
                     val_masks: np.ndarray | None = None, onnx_path=None, int8_path=None, seed: int = 0,
                     on_variant: Callable[[str], None] | None = None,
                     slow_factor: float | None = None) -> tuple[list[dict], dict]:
    """Measure every variant; returns (rows in the order of ``variants``, info).

    A variant the host cannot run is never called: its row is :func:`skipped_row` (``info["skipped"]``:
    name -> why).  Per other variant: ``peak_mb`` = peak memory growth during ``max(1, warmup)`` warm-up calls
    (:class:`PeakMemory`); ``probe_ms`` = median of :data:`PROBE_CALLS` batch-1 calls right after (the
    baseline is probed first).  A variant probed more than ``slow_factor`` x the baseline stops there
    (``status`` from :func:`slow_status`; latency, throughput and IoU columns NaN, batch 0).  The
    others (``status`` = "ok"): ``latency_ms`` = median of ``iters`` batch-1 calls on a random input at
    ``resolution``, timed round-robin across them (:func:`interleaved_times`); ``throughput``
    (images/s) = best over ``batches`` -- on CUDA, over the sweep of :func:`throughput_batches` up to
    :data:`CUDA_MAX_BATCH` or the first out-of-memory batch -- of b / median call time (1 warm-up, then
    max(2, ceil(iters / b)) calls; :func:`throughput_sweep`; every batch's images/s in
    ``info["throughput_sweep"]``; batches of 1 alone: 1 / latency, no extra calls); ``iou`` = mean Image IoU of [P >= tau] (eq:inference-mask) on the validation images and
    ``iou_delta`` = iou - iou of the fp32 baseline; ``iou_vs_fp32`` = mean per-image IoU between the
    variant's mask and the baseline's (1 = the same masks; NaN without validation data or baseline);
    ``speedup`` = baseline latency / latency.  params and GFLOPs are counted on the PyTorch graph
    (pipeline.model.count_parameters / count_flops) and shared by every variant: they compute the
    same function (int8 replaces multiply-adds by integer ones, it does not remove them).
    """
    import torch

    slow_factor = SLOW_FACTOR if slow_factor is None else float(slow_factor)
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
    for v in sorted(built, key=lambda v: v.name != BASELINE_VARIANT):  # the baseline's probe comes first
        if on_variant is not None:
            on_variant(v.name)
        with PeakMemory(v.device) as mem:
            time_calls(v.run, x1, max(1, warmup), 0, v.sync)
        probe = statistics.median(time_calls(v.run, x1, 0, PROBE_CALLS, v.sync)) * 1e3
        base_probe = probe if v.name == BASELINE_VARIANT else base_probe
        row = {"variant": v.name, "description": v.description, "device": v.device, "params": params,
               "gflops": gflops, "throughput": float("nan"), "batch": 0, "peak_mb": mem.peak_mb,
               "peak_method": mem.method, "iou": float("nan"), "resolution": int(resolution), "probe_ms": probe,
               "status": slow_status(probe, base_probe, slow_factor) or OK}
        row["timed"], row["remark"] = row["status"] == OK, variant_remark(row["status"], probe, base_probe)
        rows[v.name] = row
        if row["status"] != OK:
            continue
        tried = throughput_batches(batches, v.device)
        if tried != [1]:  # at batch 1 alone, throughput is 1 / latency: the round-robin below measures it
            sweeps[v.name] = throughput_sweep(v, x1.shape[1], resolution, tried, iters, g)
            row["throughput"], row["batch"] = sweeps[v.name].best, sweeps[v.name].batch
        if have_val:
            masks[v.name] = mask_from_probs(variant_probs(v, val_images, max(batches)), tau)
            row["iou"] = mean_image_iou(masks[v.name], val_masks)
    for name, why in skipped.items():
        rows[name] = skipped_row(name, why, ENGINES[name].device(dev), params, gflops, resolution)
    timed = [v for v in built if rows[v.name]["status"] == OK]
    times = interleaved_times(timed, x1, iters)
    base = rows.get(BASELINE_VARIANT)
    for name, r in rows.items():
        t = times.get(name)
        r["latency_ms"] = statistics.median(t) * 1e3 if t else float("nan")
        r["latency_min_ms"] = min(t) * 1e3 if t else float("nan")
        if t and name not in sweeps:  # batch 1 only: images/s from the latency calls
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
    order = dict.fromkeys([*variants, *(v.name for v in built), *skipped])  # the given order, then the rest
    return [rows[n] for n in order if n in rows], info


@dataclasses.dataclass
class Sweep:
    """A throughput sweep: images/s per batch tried (ascending), the best, and the batch that ran out of
    memory (None: every batch ran)."""

    images_per_s: dict[int, float]
    best: float
    batch: int
    oom_batch: int | None = None

    def record(self) -> dict:
        """JSON-friendly: the batches as strings."""
        return {"images_per_s": {str(b): tp for b, tp in self.images_per_s.items()}, "best_batch": self.batch,
                "oom_batch": self.oom_batch}


def throughput_batches(batches: Sequence[int], device: str) -> list[int]:
    """The batches the throughput of a variant running on ``device`` is measured at, ascending.

    Decision: on a CPU, ``deploy.benchmark_batches`` as given (a CPU is busy from batch 1 or 4 on, and
    every large batch costs seconds per call).  On CUDA, those and every power of two up to
    :data:`CUDA_MAX_BATCH`: a 0.26 M-parameter model keeps a GPU busy only at batches of hundreds
    (at 16 the launches, not the arithmetic, set the pace); the sweep stops at the first batch that
    runs out of GPU memory (:func:`throughput_sweep`)."""
    tried = {int(b) for b in batches}
    if str(device).startswith("cuda"):
        tried |= {2 ** k for k in range(CUDA_MAX_BATCH.bit_length()) if 2 ** k <= CUDA_MAX_BATCH}
    return sorted(tried)


def _release_after_oom() -> None:
    """Give the cached blocks of a failed large batch back, so that the variant can go on at small ones."""
    import torch

    if torch.cuda.is_available():
        torch.cuda.synchronize()
        torch.cuda.empty_cache()


def throughput_sweep(variant: Variant, channels: int, resolution: int, batches: Sequence[int], iters: int,
                     generator) -> Sweep:
    """Images/s of ``variant`` at each of ``batches`` in ascending order: b / median call time on random
    inputs (1 warm-up, then max(2, ceil(iters / b)) calls per batch size); the best of them.  A batch
    raising ``torch.cuda.OutOfMemoryError`` ends the sweep (no larger batch is tried) and is recorded
    as ``oom_batch``; when even the first batch runs out of memory the OOM error is raised."""
    import torch

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
            _release_after_oom()
            oom = b
            break
        tps[b] = b / statistics.median(tb)
    best_b = max(tps, key=lambda b: tps[b])
    return Sweep(tps, tps[best_b], best_b, oom)


def fastest_within(rows: Sequence[dict], max_iou_drop: float) -> dict | None:
    """The lowest-latency fully timed variant (status "ok") whose |iou_delta| <= ``max_iou_drop``
    (any such variant without IoU data: NaN passes, there is nothing to judge)."""
    ok = [r for r in rows if r.get("status", OK) == OK and math.isfinite(r["latency_ms"])
          and not (abs(r["iou_delta"]) > max_iou_drop)]
    return min(ok, key=lambda r: r["latency_ms"]) if ok else None


# --------------------------------------------------------------------------------------------------
# What the benchmark stage runs: settings, the model under test, data, ONNX models, verdicts, results
# --------------------------------------------------------------------------------------------------
def benchmark_settings(cfg: dict) -> dict:
    """The benchmark's ``deploy`` params (validated by the params schema before any stage runs)."""
    return {"warmup": cfg["benchmark_warmup"], "iters": cfg["benchmark_iters"], "batches": cfg["benchmark_batches"],
            "variants": cfg["benchmark_variants"], "n_calib": cfg["int8_calibration_images"],
            "int8": q8.int8_params(cfg), "target_ms": float(cfg["target_latency_ms"]),
            "max_drop": float(cfg["target_iou_drop"]), "target_res": cfg["target_resolution"],
            "opset": cfg["opset"], "resolution": cfg["benchmark_resolution"]}


@dataclasses.dataclass
class Target:
    """The model under test: from a deploy bundle or a checkpoint."""

    model: object
    tau: float
    tau_source: str
    resolution: int | None      # its working resolution, when recorded
    onnx_path: Path | None      # the bundle's model.onnx
    int8_path: Path | None      # the bundle's model.int8.onnx
    int8_info: dict
    inputs: list                # opened artifacts (lineage)


def open_target(deploy_dir=None, checkpoint=None, thresholds=None, tau=None, params=None) -> Target:
    """Open exactly one of a deploy bundle or a checkpoint directory on the CPU.  tau by
    :func:`pipeline.thresholds.tau_candidates` and :func:`pipeline.thresholds.resolve_tau`: ``tau``
    (--tau) > the bundle's > the checkpoint's payload > its row in ``thresholds`` > ``calibrate.fixed_tau``
    of ``params``."""
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
    """(val images, val masks, int8 calibration images, opened artifacts) from ``art``; Nones (and no
    artifacts) when manifest.parquet, images.zarr or reference.zarr is absent.

    Validation: split == 'val' rows with a reference mask (reference masks only measure accuracy here,
    never train).  Calibration: the export's selection of training rows (:func:`q8.calibration_rows`)."""
    paths = [catalog.path(name, art) for name in ("manifest", "images", "reference")]
    if not all(p.exists() for p in paths):
        return None, None, None, []
    manifest = open_artifact(paths[0], "manifest")
    images = open_artifact(paths[1], "images")
    reference = open_artifact(paths[2], "reference")
    splits = manifest.df["split"].to_numpy()
    val = np.flatnonzero((splits == "val") & np.asarray(reference.numpy("has_mask"), bool))
    train = q8.calibration_rows(splits, n_calib)
    val_images = read_chunk_rows(images["image"], val) if val.size else None
    val_masks = read_chunk_rows(reference["mask"], val).astype(bool) if val.size else None
    calib = read_chunk_rows(images["image"], train) if train.size else None
    return val_images, val_masks, calib, [manifest, images, reference]


def prepare_onnx_models(target: Target, variants: Sequence[str], workdir: str | Path, *, resolution: int,
                        opset: int, calibration_images: np.ndarray | None, int8: dict) -> tuple:
    """(onnx_path, int8_path, notes): the ONNX models the ORT variants run (module docstring).

    model.onnx: the bundle's, else exported into ``workdir``.  int8 (only when ``onnxruntime_int8`` is
    asked for, or ``openvino_int8``): the bundle's model.int8.onnx, else quantised into ``workdir`` on
    the training-split ``calibration_images`` or, without any, on synthetic smooth noise.  ``notes`` holds
    ``int8_calibration`` (how) or ``onnx`` (why there is no ONNX model: onnx not importable).
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
    int8_path = q8.quantize_onnx_int8(onnx_path, Path(workdir) / "model_int8.onnx", calib,
                                      int8["calibration"], int8["percentile"], int8["weight_bits"])
    return onnx_path, int8_path, {"int8_calibration": note}


def clean(v):
    """JSON value: non-finite floats -> None."""
    return None if isinstance(v, float) and not math.isfinite(v) else v


def fast_path_summary(rows: Sequence[dict], resolution: int, *, target_ms: float, target_res: int,
                      max_drop: float) -> dict | None:
    """The fast path (:func:`fastest_within`) and its verdicts, or None when no variant qualifies.

    ``meets_latency_target``: latency_ms <= target_ms at ``target_res`` -- None ("not judged") at any
    other resolution; ``within_iou_drop``: |iou_delta| <= max_drop (None without IoU data);
    ``verdict``: "met" | "NOT met" | "not judged at this size"."""
    fast = fastest_within(rows, max_drop)
    if fast is None:
        return None
    meets = fast["latency_ms"] <= target_ms if resolution == target_res else None
    return {"variant": fast["variant"], "latency_ms": fast["latency_ms"], "speedup": fast["speedup"],
            "iou_delta": clean(fast["iou_delta"]), "meets_latency_target": meets,
            "within_iou_drop": None if math.isnan(fast["iou_delta"]) else abs(fast["iou_delta"]) <= max_drop,
            "verdict": "not judged at this size" if meets is None else "met" if meets else "NOT met"}


def fast_path_line(summary: dict, rows: Sequence[dict], resolution: int, target_ms: float, target_res: int) -> str:
    """One line: the fast path, its speed-up over the baseline and the latency verdict."""
    base = next((r for r in rows if r["variant"] == BASELINE_VARIANT), None)
    return (f"fast path: {summary['variant']} {summary['latency_ms']:.1f} ms/image at {resolution}px batch 1 "
            f"({summary['speedup']:.1f}x the {BASELINE_VARIANT} baseline"
            + (f" of {base['latency_ms']:.1f} ms" if base else "") + f"); target {target_ms:g} ms at "
            f"{target_res}px: {summary['verdict']}")


def _cell(v, spec: str, width: int) -> str:
    """``v`` formatted by ``spec``, or ``--`` (right-aligned to ``width``) when it is missing or not finite."""
    try:
        ok = v is not None and math.isfinite(float(v))
    except (TypeError, ValueError):
        ok = False
    return format(v, spec) if ok else f"{'--':>{width}s}"


def format_table(rows: Sequence[dict]) -> str:
    """The efficiency table for stdout; a variant that was skipped or only probed shows its status instead.  The
    IoU columns are left out when no variant has one (no validation masks: nothing was scored), and a
    single missing number shows as ``--``, never ``nan``."""
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
    """One line per variant whose throughput was measured at more batches than ``deploy.benchmark_batches``
    (the CUDA sweep): images/s per batch, the best, and the batch that ran out of memory; "" when none was."""
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
    """The JSON document of a benchmark run (non-finite numbers as null)."""
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
