"""Deployment of the student's mask path: export, segmentation of image files, CPU efficiency benchmark.

Only the TinyUNet mask path is deployed (paper, eq:inference-mask and the sentence after it: SAM 3,
the SDF head and the skeleton head are absent from deployment).  The deployed function is

    Z = f(x)            x float32 [B,3,H,W], RGB in [0, 1] (normalisation is inside the model)
    M = [sigmoid(Z) >= tau]  <=>  [Z >= logit(tau)]                                (eq:inference-mask)

with tau the validation-calibrated threshold of the exported (method, seed).

Deploy bundle (directory artifact, schema ``deploy``)::

    model.pt      {"state_dict": mask-path weights, "config", "method", "seed", "tau", "resolution"}
                  -- the checkpoint format, so pipeline.inference.load_student() opens the bundle too
    model.ts      TorchScript (traced) mask path; shape-generic (any batch and size)
    model.onnx    ONNX mask path, dynamic batch/height/width (only when onnx + onnxruntime import)
                  -- both traced from pipeline.model.ExportMaskPath: the same function with the input
                  normalisation folded into the first convolution (the graph input is the image)
    model.int8.onnx  static int8 (QDQ) quantisation of model.onnx, calibrated on training-split images
                  (only when model.onnx exists and training images are given; the CPU fast path)
    deploy.json   tau (+ where it came from), working resolution, model config, parameters, GFLOPs,
                  exporter, parity results (int8: agreement report), file sha256s, source checkpoint
                  and its fingerprint, the int8 file and its calibration image count (or why skipped)
    meta.json     artifact metadata (fingerprint, lineage)

Decisions (the paper is silent on deployment formats):

* TorchScript is produced by ``torch.jit.trace`` of the mask path (TinyUNet holds a class-level
  normalisation constant and an optional training-only module, which ``torch.jit.script`` rejects);
  the traced graph reads sizes from the input, so it is batch- and size-generic.  It is saved
  unfrozen so that it still moves between devices.
* ONNX uses the TorchScript-based exporter (``torch.onnx.export(..., dynamo=False)``): torch 2.13
  defaults to the dynamo exporter, which needs ``onnxscript`` (not a dependency, not installed here).
* Parity (export time and tests): PyTorch, TorchScript and ONNX Runtime logits on deterministic
  smooth random images at the working resolution (batch 2, exercising the dynamic batch axis).
  Passing needs finite logits with max |dZ| <= ``atol``; then a mask pixel can only differ where the
  PyTorch logit lies within ``atol`` of logit(tau), i.e. by float round-off alone.  Strict mask
  equality at tau (``masks_identical``) and the number of differing pixels are reported alongside
  (and the tests require identical masks on their inputs).
* Segment: images are read by :func:`pipeline.datasets.loading.read_rgb` and resized to the working
  resolution exactly as the training images were (:func:`~pipeline.datasets.loading.resize_image`,
  area interpolation, square); the probability map is resized back to the original size
  (bilinear) and thresholded there, which keeps boundaries smoother than resizing a binary mask.
* int8: ONNX Runtime static quantisation (QDQ format, uint8 asymmetric activations, int8 symmetric
  per-channel weights; activation ranges from TRAINING-split images -- images only, no masks --
  clipped at the ``deploy.int8_percentile`` of their histograms, or MinMax), which runs on the
  VNNI int8 kernels of x86 CPUs.  The graph input is pinned to scale 1/255, zero point 0: with the
  normalisation folded into the first convolution (ExportMaskPath) 8-bit images enter exactly.
  Measured on the reduced protocol's student (validation Image IoU change vs fp32): quantising the
  normalised input instead cost 0.035 (the model reacts to half-grey-level shifts of its black
  background); MinMax ranges gave a mean int8-vs-fp32 mask IoU of 0.949, 99.999th-percentile ranges
  0.970.  Chosen over ``torch.ao`` eager/FX quantisation, which
  is deprecated in torch 2.x, and over dynamic quantisation, which does not quantise convolutions
  in ORT's CPU kernels.  The export writes it into the bundle (``model.int8.onnx``), so that segment
  and the benchmark use the same file.  Calibration images: up to ``deploy.int8_calibration_images``
  training-split rows of images.zarr, evenly spaced in manifest order (:func:`calibration_rows`),
  resized to the working resolution like every other input.  Manual/reference masks are never read.
* int8 parity: int8 is an approximation, never bit-exact, so it is held to a mask gate, not to
  ``parity_atol``: on the calibration images, max and mean |Z_int8 - Z_torch|, the fraction of
  agreeing mask pixels, and the per-image IoU between the int8 and the PyTorch mask at tau (mean and
  minimum).  The export fails (InputError naming the param) when the mean mask IoU is below
  ``deploy.int8_min_mask_iou`` (0.9 by default).  The images are in-sample for the activation
  ranges; the held-out effect (validation Image IoU change, and mask IoU against fp32) is measured by
  the benchmark.
* Engines (segment ``--engine``): ``torch`` (model.pt / checkpoint), ``torchscript``, ``onnx`` and
  ``int8`` (bundle only); ``auto`` = onnx when the bundle holds it and onnxruntime imports, else
  torch -- exact engines only (:func:`resolve_engine`).  Every engine receives the same preprocessed tensor and the
  same tau; only the function Z = f(x) differs.
* Peak memory: CPU -- growth of the process's peak resident set (Linux ``/proc/self/clear_refs``
  reset of VmHWM, then VmHWM - VmRSS before the run, after ``malloc_trim``); CUDA --
  ``torch.cuda.max_memory_allocated`` after ``reset_peak_memory_stats``.  Where neither is
  available, NaN.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import hashlib
import io
import json
import logging
import math
import os
import statistics
import tempfile
import time
import uuid
import warnings
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from pipeline.errors import ArtifactError, InputError

log = logging.getLogger(__name__)

ONNX_INPUT = "image"
ONNX_OUTPUT = "logits"
DEPLOY_JSON = "deploy.json"
INT8_FILE = "model.int8.onnx"
ENGINES = ("auto", "torch", "torchscript", "onnx", "int8")
BASELINE_VARIANT = "fp32_eager_nchw"
VARIANTS = ("fp32_eager_nchw", "fp32_channels_last", "bf16_autocast", "bf16_channels_last", "torchscript_frozen",
            "onnxruntime_fp32", "onnxruntime_int8")


class ParityError(RuntimeError):
    """An exported model does not reproduce the PyTorch mask path (a bug, not a user error)."""


# --------------------------------------------------------------------------------------------------
# Thresholding (eq:inference-mask)
# --------------------------------------------------------------------------------------------------
def logit_threshold(tau: float) -> float:
    """logit(tau) = log(tau / (1 - tau)): [sigmoid(Z) >= tau] == [Z >= logit(tau)] (eq:inference-mask).

    tau = 0 -> -inf (everything foreground), tau = 1 -> +inf (nothing).
    """
    tau = float(tau)
    if not 0.0 <= tau <= 1.0:
        raise InputError(f"tau={tau}: must lie in [0, 1]")
    if tau == 0.0:
        return -math.inf
    if tau == 1.0:
        return math.inf
    return math.log(tau / (1.0 - tau))


def mask_from_probs(probs: np.ndarray, tau: float) -> np.ndarray:
    """M = [P >= tau] (eq:inference-mask), bool with the shape of ``probs``."""
    return np.asarray(probs) >= float(tau)


def check_tau(tau, where: str) -> float:
    try:
        t = float(tau)
    except (TypeError, ValueError):
        raise InputError(f"{where}={tau!r}: not a number") from None
    if not 0.0 <= t <= 1.0 or math.isnan(t):
        raise InputError(f"{where}={tau!r}: must lie in [0, 1]")
    return t


def lookup_tau(thresholds_df, method: str, seed: int) -> float | None:
    """The calibrated tau of (method, seed) in a thresholds table, or None when the row is absent."""
    df = thresholds_df
    rows = df[(df["method"].astype(str) == str(method)) & (df["seed"].astype(int) == int(seed))]
    if rows.empty:
        return None
    return float(rows["tau"].iloc[0])


# --------------------------------------------------------------------------------------------------
# The mask path as a standalone module
# --------------------------------------------------------------------------------------------------
def mask_path_model(model):
    """A float32 CPU copy of the deployed mask path (TinyUNet without the geometry heads), eval mode."""
    from pipeline.model import TinyUNet

    deployed = TinyUNet(**model.config)
    deployed.load_state_dict(model.mask_path_state_dict())
    return deployed.float().eval().requires_grad_(False)


def export_module(model):
    """The exported form of the mask path (:class:`pipeline.model.ExportMaskPath`: same function,
    input normalisation folded into the first convolution), float32 CPU, eval mode."""
    from pipeline.model import ExportMaskPath

    return ExportMaskPath(mask_path_model(model)).eval().requires_grad_(False)


def parity_inputs(resolution: int, n: int = 2, seed: int = 0):
    """Deterministic smooth random RGB images float32 [n,3,R,R] in [0,1] (blobs plus fine noise),
    so that the parity check sees both foreground-like and background-like logits."""
    import torch

    g = torch.Generator().manual_seed(seed)
    low = torch.rand(n, 3, max(2, resolution // 8), max(2, resolution // 8), generator=g)
    x = torch.nn.functional.interpolate(low, size=(resolution, resolution), mode="bilinear",
                                        align_corners=False)
    x = 0.85 * x + 0.15 * torch.rand(n, 3, resolution, resolution, generator=g)
    return x.clamp_(0, 1).contiguous()


# --------------------------------------------------------------------------------------------------
# Export
# --------------------------------------------------------------------------------------------------
def onnx_unavailable_reason() -> str | None:
    """None when ONNX export and ONNX Runtime work here, else a one-line reason (install the extra)."""
    missing = []
    for mod in ("onnx", "onnxruntime"):
        try:
            __import__(mod)
        except Exception:  # noqa: BLE001 -- ImportError or a broken binary wheel
            missing.append(mod)
    if missing:
        return (f"{' and '.join(missing)} not importable; ONNX export/benchmark skipped "
                f"(install the extra: pip install 'geodistill-refine[onnx]')")
    return None


def export_torchscript(model, path: str | Path, resolution: int) -> Path:
    """Trace the mask path on a [1,3,R,R] example and save it (unfrozen, CPU weights)."""
    import torch

    deployed = export_module(model)
    example = torch.zeros(1, deployed.config["in_channels"], resolution, resolution)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # TracerWarning; torch 2.13's deprecation notice for torch.jit
        traced = torch.jit.trace(deployed, example, check_trace=False)
    traced.save(str(path))
    return Path(path)


def export_onnx(model, path: str | Path, resolution: int, opset: int) -> Path:
    """Export the mask path to ONNX (input ``image`` [B,3,H,W] float32, output ``logits`` [B,1,H,W]),
    batch, height and width dynamic, with the TorchScript-based exporter (module docstring)."""
    import torch

    deployed = export_module(model)
    example = torch.zeros(1, deployed.config["in_channels"], resolution, resolution)
    axes = {0: "batch", 2: "height", 3: "width"}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # deprecation notice of the TorchScript-based exporter
        torch.onnx.export(deployed, (example,), str(path), opset_version=int(opset), dynamo=False,
                          input_names=[ONNX_INPUT], output_names=[ONNX_OUTPUT],
                          dynamic_axes={ONNX_INPUT: axes, ONNX_OUTPUT: axes}, do_constant_folding=True)
    return Path(path)


def ort_session(path: str | Path, threads: int | None = None, optimize: bool = True):
    """ONNX Runtime CPU session; ``threads`` defaults to torch's intra-op thread count (same budget)."""
    import onnxruntime as ort
    import torch

    so = ort.SessionOptions()
    so.intra_op_num_threads = int(threads or torch.get_num_threads())
    so.inter_op_num_threads = 1
    so.log_severity_level = 3
    so.graph_optimization_level = (ort.GraphOptimizationLevel.ORT_ENABLE_ALL if optimize
                                   else ort.GraphOptimizationLevel.ORT_DISABLE_ALL)
    return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])


def load_torchscript(path: str | Path, device="cpu"):
    """torch.jit.load in eval mode (torch 2.13 marks TorchScript deprecated; the notice is silenced)."""
    import torch

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return torch.jit.load(str(path), map_location=device).eval()


def torch_logits(model, x) -> np.ndarray:
    import torch

    with torch.inference_mode():
        return model(x).float().cpu().numpy()


def compare_logits(reference: np.ndarray, logits: np.ndarray, tau: float, atol: float) -> dict:
    """Parity of exported ``logits`` against the PyTorch ``reference`` at threshold tau (module docstring)."""
    reference = np.asarray(reference, np.float64)
    logits = np.asarray(logits, np.float64)
    if reference.shape != logits.shape:
        return {"passed": False, "max_abs_diff": float("inf"), "atol": float(atol), "masks_identical": False,
                "mask_pixels_differ": -1, "note": f"shape {logits.shape} != {reference.shape}"}
    finite = bool(np.isfinite(logits).all())
    diff = float(np.max(np.abs(reference - logits))) if reference.size and finite else (0.0 if finite else float("inf"))
    z_tau = logit_threshold(tau)
    differ = (reference >= z_tau) != (logits >= z_tau)
    return {"passed": bool(finite and diff <= atol), "max_abs_diff": diff, "atol": float(atol),
            "masks_identical": bool(not differ.any()), "mask_pixels_differ": int(np.count_nonzero(differ)),
            "pixels": int(reference.size)}


def check_parity(model, tau: float, resolution: int, atol: float, torchscript: str | Path | None = None,
                 onnx: str | Path | None = None) -> dict:
    """Run the parity check of the exported files against the PyTorch mask path (module docstring).

    Returns ``{"inputs": ..., "torchscript": {...}, "onnx": {...}}`` (a format's entry is absent when its
    file is not given).  Does not raise; see :func:`require_parity`.
    """
    import torch

    x = parity_inputs(resolution)
    ref = torch_logits(mask_path_model(model), x)
    out: dict = {"inputs": f"{x.shape[0]} deterministic smooth random images {resolution}x{resolution} (seed 0)",
                 "tau": float(tau)}
    if torchscript is not None:
        ts = load_torchscript(torchscript, "cpu")
        out["torchscript"] = compare_logits(ref, torch_logits(ts, x), tau, atol)
    if onnx is not None:
        sess = ort_session(onnx)
        out["onnx"] = compare_logits(ref, sess.run(None, {ONNX_INPUT: x.numpy()})[0], tau, atol)
    return out


def require_parity(parity: dict) -> None:
    """Raise :class:`ParityError` when a checked format failed its parity check."""
    for fmt in ("torchscript", "onnx"):
        res = parity.get(fmt)
        if res is not None and not res["passed"]:
            raise ParityError(f"{fmt} export differs from PyTorch: max |dZ| = {res['max_abs_diff']:.3g} "
                              f"(atol {res.get('atol')}), {res['mask_pixels_differ']} mask pixels differ at tau")


# --------------------------------------------------------------------------------------------------
# int8 calibration data and parity report
# --------------------------------------------------------------------------------------------------
def calibration_rows(splits: Sequence[str], n: int) -> np.ndarray:
    """Row indices of up to ``n`` TRAINING-split images, evenly spaced over the training rows in
    manifest order (deterministic; all of them when there are at most ``n``).  Empty when none."""
    train = np.flatnonzero(np.asarray(splits).astype(str) == "train")
    if len(train) <= n:
        return train
    return train[np.unique(np.linspace(0, len(train) - 1, int(n)).round().astype(int))]


def read_calibration_images(art: str | Path, n: int, resolution: int | None = None):
    """``(images uint8 [M,R,R,3] or None, opened artifacts, note)`` for int8 calibration.

    Reads ``art/manifest.parquet`` and ``art/images.zarr`` only -- images, never masks (the
    reference masks are not an input of quantisation).  ``resolution`` resizes with the segment
    preprocessing (area interpolation) when images.zarr is at another size.  None (with the reason
    in ``note``) when the artifacts are absent or hold no training rows.
    """
    from pipeline.artifacts import open_artifact, read_chunk_rows
    from pipeline.datasets.loading import resize_image

    art = Path(art)
    paths = (art / "manifest.parquet", art / "images.zarr")
    missing = [str(p) for p in paths if not p.exists()]
    if missing:
        return None, [], f"no training images for int8 calibration ({', '.join(missing)} missing)"
    manifest = open_artifact(paths[0], "manifest")
    images = open_artifact(paths[1], "images")
    rows = calibration_rows(manifest.df["split"].to_numpy(), n)
    if rows.size == 0:
        return None, [manifest, images], f"no training-split rows in {paths[0]} for int8 calibration"
    calib = read_chunk_rows(images["image"], rows)
    if resolution is not None and calib.shape[1:3] != (resolution, resolution):
        calib = np.stack([resize_image(im, int(resolution)) for im in calib])
    return calib, [manifest, images], f"{len(calib)} training-split images of {paths[1]} (no masks)"


def int8_agreement(reference: np.ndarray, logits: np.ndarray, tau: float, min_mask_iou: float) -> dict:
    """int8 parity report (module docstring) of logits [N,...] against the PyTorch ``reference``.

    Masks are M = [Z >= logit(tau)] (eq:inference-mask).  Reports max/mean |Z - Z_ref|, the fraction of
    pixels whose mask agrees, and the per-image mask IoU between the two models (image_iou; both
    empty -> 1): its mean and minimum.  ``passed`` = finite logits and mean mask IoU >= ``min_mask_iou``
    -- a gate on masks rather than pixels, because a pixel fraction hides a small object that int8
    loses (it is 0.1 % of the pixels and 100 % of that image's mask).
    """
    from pipeline.metrics import image_ious

    reference = np.asarray(reference, np.float64)
    logits = np.asarray(logits, np.float64)
    if reference.shape != logits.shape or reference.size == 0:
        return {"passed": False, "max_abs_diff": float("inf"), "mean_abs_diff": float("inf"),
                "mask_agreement": 0.0, "mask_iou_mean": 0.0, "mask_iou_min": 0.0,
                "min_mask_iou": float(min_mask_iou), "mask_pixels_differ": -1, "pixels": int(reference.size),
                "note": f"shape {logits.shape} vs {reference.shape}"}
    finite = bool(np.isfinite(logits).all())
    err = np.abs(reference - logits)
    z_tau = logit_threshold(tau)
    ref_mask, mask = reference >= z_tau, logits >= z_tau
    differ = int(np.count_nonzero(ref_mask != mask))
    per_image = (len(mask), 1, -1)  # each image's mask as one 2-D row: same IoU, any layout [N,(1,)H,W]
    ious = image_ious(mask.reshape(per_image), ref_mask.reshape(per_image))
    iou_mean = float(ious.mean()) if finite else 0.0
    return {"passed": bool(finite and iou_mean >= min_mask_iou),
            "max_abs_diff": float(err.max()) if finite else float("inf"),
            "mean_abs_diff": float(err.mean()) if finite else float("inf"),
            "mask_agreement": float(1.0 - differ / reference.size),
            "mask_iou_mean": iou_mean, "mask_iou_min": float(ious.min()) if finite else 0.0,
            "min_mask_iou": float(min_mask_iou), "mask_pixels_differ": differ, "pixels": int(reference.size)}


def check_int8_parity(model, int8_path: str | Path, images: np.ndarray, tau: float, min_mask_iou: float,
                      batch_size: int = 8) -> dict:
    """:func:`int8_agreement` of the int8 ONNX model against the PyTorch mask path on uint8 images
    [N,R,R,3] (the calibration images at export).  Does not raise; see :func:`require_int8_agreement`."""
    from pipeline.inference import images_to_tensor

    deployed = mask_path_model(model)
    sess = ort_session(int8_path)
    ref, got = [], []
    for s in range(0, len(images), batch_size):
        x = images_to_tensor(np.asarray(images[s:s + batch_size]))
        ref.append(torch_logits(deployed, x))
        got.append(sess.run(None, {ONNX_INPUT: x.numpy()})[0])
    out = int8_agreement(np.concatenate(ref), np.concatenate(got), tau, min_mask_iou)
    out["images"] = int(len(images))
    out["inputs"] = f"{len(images)} int8 calibration images (training split), tau = {float(tau):.6g}"
    return out


def require_int8_agreement(report: dict) -> None:
    """InputError naming ``deploy.int8_min_mask_iou`` when the int8 model's masks stray from PyTorch's."""
    if not report["passed"]:
        raise InputError(f"deploy.int8_min_mask_iou={report['min_mask_iou']}: the int8 model's masks overlap "
                         f"PyTorch's with a mean IoU of only {report['mask_iou_mean']:.4f} "
                         f"(max |dZ| = {report['max_abs_diff']:.3g}); lower the param or export with --no-int8")


def file_sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def write_bundle(tmp: str | Path, model, payload: dict, *, tau: float, tau_source: str, resolution: int,
                 opset: int, atol: float, onnx: bool = True, source: dict | None = None,
                 calibration_images: np.ndarray | None = None, calibration_note: str | None = None,
                 int8_min_mask_iou: float = 0.9, int8_calibration: str = "percentile",
                 int8_percentile: float = 99.999) -> dict:
    """Fill a deploy bundle directory ``tmp`` (module docstring) and return its deploy.json content.

    Raises :class:`ParityError` when an exported format fails its parity check, and InputError when
    the int8 model's mean mask IoU against PyTorch is below ``int8_min_mask_iou``.  ``onnx=False`` (or
    onnx/onnxruntime missing) writes no model.onnx and records why in deploy.json.  model.int8.onnx
    is written when model.onnx exists and ``calibration_images`` (uint8 [N,R,R,3], training split,
    no masks) are given; otherwise ``int8_note`` says why not (``calibration_note`` when the caller
    found no images).
    """
    import torch

    from pipeline.model import count_flops, count_parameters

    tmp = Path(tmp)
    deployed = mask_path_model(model)
    method, seed = payload.get("method"), payload.get("seed")
    torch.save({"state_dict": deployed.mask_path_state_dict(), "geometry_state_dict": None,
                "config": dict(deployed.config), "method": method, "seed": seed,
                "tau": float(tau), "resolution": int(resolution)}, tmp / "model.pt")
    export_torchscript(deployed, tmp / "model.ts", resolution)
    onnx_note = None if onnx else "disabled"
    if onnx and (reason := onnx_unavailable_reason()) is None:
        export_onnx(deployed, tmp / "model.onnx", resolution, opset)
    elif onnx:
        onnx_note = reason
        log.warning("export: %s", reason)
    has_onnx = (tmp / "model.onnx").exists()
    parity = check_parity(deployed, tau, resolution, atol, torchscript=tmp / "model.ts",
                          onnx=tmp / "model.onnx" if has_onnx else None)
    require_parity(parity)
    int8 = None
    if not has_onnx:
        int8_note = f"no model.onnx ({onnx_note})"
    elif calibration_images is None or len(calibration_images) == 0:
        int8_note = calibration_note or "no calibration images given"
    else:
        quantize_onnx_int8(tmp / "model.onnx", tmp / INT8_FILE, calibration_images, int8_calibration, int8_percentile)
        parity["int8"] = check_int8_parity(deployed, tmp / INT8_FILE, calibration_images, tau, int8_min_mask_iou)
        require_int8_agreement(parity["int8"])
        int8_note = None
        int8 = {"file": INT8_FILE, "calibration_images": int(len(calibration_images)),
                "calibration": calibration_note or "training-split images (no masks)",
                "calibration_method": int8_calibration,
                "percentile": float(int8_percentile) if int8_calibration == "percentile" else None,
                "quantization": int8_description(int8_calibration, int8_percentile)}
    if int8_note is not None:
        log.info("export: int8 model skipped: %s", int8_note)
    files = sorted(p.name for p in tmp.iterdir() if p.is_file())
    info = {
        "format_version": 1,
        "method": method, "seed": seed,
        "tau": float(tau), "tau_source": tau_source,
        "resolution": int(resolution),
        "input": {"name": ONNX_INPUT, "dtype": "float32", "layout": "NCHW", "channels": "RGB",
                  "range": [0.0, 1.0], "size": "any (the model runs at the working resolution; "
                  "resize images to resolution x resolution with area interpolation)"},
        "output": {"name": ONNX_OUTPUT, "meaning": "mask logits Z [B,1,H,W]; mask = sigmoid(Z) >= tau "
                   "<=> Z >= logit(tau) (eq:inference-mask)", "logit_tau": logit_threshold(tau)},
        "config": dict(deployed.config),
        "params": count_parameters(deployed),
        "gflops": count_flops(deployed, resolution, resolution) / 1e9,
        "opset": int(opset) if has_onnx else None,
        "onnx_exporter": "torch.onnx.export(dynamo=False) (TorchScript-based)" if has_onnx else None,
        "onnx_note": onnx_note,
        "int8": int8,
        "int8_note": int8_note,
        "torch_version": torch.__version__,
        "parity": parity,
        "files": {f: file_sha256(tmp / f) for f in files},
        "source": source or {},
    }
    (tmp / DEPLOY_JSON).write_text(json.dumps(info, indent=1, sort_keys=True))
    return info


# --------------------------------------------------------------------------------------------------
# Loading a checkpoint or a deploy bundle for inference
# --------------------------------------------------------------------------------------------------
@dataclasses.dataclass
class Segmenter:
    """A loaded mask path: ``predict_probs(images uint8 [N,R,R,3]) -> P float32 [N,R,R]``.

    ``engine`` is what computes Z = f(x): torch, torchscript, onnx or int8 (module docstring)."""

    engine: str
    resolution: int | None
    tau: float | None
    tau_source: str
    predict_logits: Callable  # float32 tensor [N,3,R,R] -> numpy float32 [N,1,R,R]
    info: dict

    def predict_probs(self, images: np.ndarray, batch_size: int = 8) -> np.ndarray:
        from pipeline.inference import images_to_tensor

        images = np.asarray(images)
        out = np.empty(images.shape[:3], np.float32)
        for s in range(0, len(images), batch_size):
            z = np.asarray(self.predict_logits(images_to_tensor(images[s:s + batch_size])), np.float32)
            out[s:s + batch_size] = 1.0 / (1.0 + np.exp(-z[:, 0]))
        return out


def is_deploy_bundle(path: str | Path) -> bool:
    return (Path(path) / DEPLOY_JSON).is_file()


def read_deploy_info(path: str | Path) -> dict:
    p = Path(path) / DEPLOY_JSON
    try:
        return json.loads(p.read_text())
    except FileNotFoundError:
        raise ArtifactError(f"{path}: not a deploy bundle (no {DEPLOY_JSON})") from None
    except (OSError, ValueError) as e:
        raise ArtifactError(f"{p}: unreadable ({type(e).__name__})") from None


def checkpoint_resolution(path: str | Path, payload: dict) -> int | None:
    """Working resolution recorded with a checkpoint (payload or meta.json extra), else None."""
    for key in ("resolution", "image_size"):
        if isinstance(payload.get(key), int):
            return int(payload[key])
    mp = Path(path) / "meta.json"
    if Path(path).is_dir() and mp.exists():
        try:
            extra = json.loads(mp.read_text()).get("extra", {}) or {}
        except ValueError:
            extra = {}
        for key in ("resolution", "image_size"):
            if isinstance(extra.get(key), int):
                return int(extra[key])
    return None


def resolve_engine(path: str | Path, engine: str) -> str:
    """The engine ``auto`` stands for (module docstring), or ``engine`` itself after validation.

    auto: bundle -> onnx when model.onnx exists and onnxruntime imports, else torch; checkpoint
    directory -> torch (the only engine a checkpoint supports: anything else is an InputError naming
    --engine).  Decision: ``auto`` only picks engines whose masks are identical to PyTorch's; int8 is
    about 3x faster than ONNX fp32 but not exact (reduced synthetic protocol: validation Image IoU
    +0.002, yet a mean per-image IoU of 0.97 between its masks and fp32's), so it must be asked for
    with ``--engine int8`` after checking ``geodistill benchmark``'s IoU columns on your data.
    """
    path = Path(path)
    if engine not in ENGINES:
        raise InputError(f"--engine {engine!r}: expected one of {', '.join(ENGINES)}")
    if not is_deploy_bundle(path):
        if engine not in ("auto", "torch"):
            raise InputError(f"--engine {engine}: needs a deploy bundle (geodistill export); {path} is a "
                             f"checkpoint directory, which supports --engine torch only")
        return "torch"
    if engine != "auto":
        return engine
    if onnx_unavailable_reason() is None and (path / "model.onnx").exists():
        return "onnx"
    return "torch"


def load_segmenter(path: str | Path, engine: str = "auto", device="cpu",
                   thresholds: str | Path | None = None) -> Segmenter:
    """Open a checkpoint directory or a deploy bundle for inference with one engine.

    ``engine``: ``auto`` (:func:`resolve_engine`), ``torch`` (model.pt or the checkpoint),
    ``torchscript`` / ``onnx`` / ``int8`` (bundle only).  tau and resolution come from deploy.json;
    for a checkpoint, tau is looked up in ``thresholds`` (a thresholds.parquet) by the checkpoint's
    (method, seed) and the resolution from its payload or metadata -- either may stay None, for the
    caller to fill (``--tau``, ``--resolution``, params).  ONNX engines run on the CPU.
    """
    import torch

    from pipeline.inference import load_student

    path = Path(path)
    if not path.exists():
        raise InputError(f"--checkpoint {path}: not found")
    engine = resolve_engine(path, engine)
    device = torch.device(device)
    if is_deploy_bundle(path):
        info = read_deploy_info(path)
        tau, tau_source = info.get("tau"), f"deploy bundle ({info.get('tau_source', '?')})"
        resolution = info.get("resolution")
    else:
        info, tau, tau_source, resolution = {}, None, "", None

    if engine == "torch":
        model, payload = load_student(path, device)
        if device.type == "cpu":
            model = model.to(memory_format=torch.channels_last)
        if resolution is None:
            resolution = checkpoint_resolution(path, payload)
        if tau is None and payload.get("tau") is not None:
            tau, tau_source = float(payload["tau"]), "checkpoint payload"
        if tau is None and thresholds is not None and Path(thresholds).exists():
            from pipeline.artifacts import open_artifact

            found = lookup_tau(open_artifact(thresholds, "thresholds").df, payload.get("method"), payload.get("seed"))
            if found is not None:
                tau, tau_source = found, f"{thresholds} ({payload.get('method')}, seed {payload.get('seed')})"

        def run(x):
            # fp32, channels_last: the same path calibrate used to choose tau
            return predict_logits_torch(model, x, device)
        info = info or {"method": payload.get("method"), "seed": payload.get("seed")}
        return Segmenter("torch", resolution, tau, tau_source, run, info)

    if engine == "torchscript":
        ts_path = path / "model.ts"
        if not ts_path.exists():
            raise ArtifactError(f"{path}: no model.ts")
        ts = load_torchscript(ts_path, device)

        def run(x):
            with torch.inference_mode():
                return ts(x.to(device)).float().cpu().numpy()
        return Segmenter("torchscript", resolution, tau, tau_source, run, info)

    reason = onnx_unavailable_reason()
    if reason is not None:
        raise InputError(f"--engine {engine}: {reason}")
    onnx_file = path / (INT8_FILE if engine == "int8" else "model.onnx")
    if not onnx_file.exists():
        why = (info.get("int8_note") or "exported without it") if engine == "int8" else \
            (info.get("onnx_note") or "exported without onnx")
        raise ArtifactError(f"{path}: no {onnx_file.name} ({why}); use --engine torch")
    sess = ort_session(onnx_file)

    def run(x):
        return sess.run(None, {ONNX_INPUT: np.ascontiguousarray(x.numpy(), np.float32)})[0]
    return Segmenter(engine, resolution, tau, tau_source, run, info)


def predict_logits_torch(model, x, device) -> np.ndarray:
    """fp32 logits of a PyTorch TinyUNet; on CPU the input goes channels_last (as in
    pipeline.inference.predict_probs, which calibrate uses), the model is converted by the caller."""
    import torch

    with torch.inference_mode():
        x = x.to(device)
        if device.type == "cpu":
            x = x.contiguous(memory_format=torch.channels_last)
        return model(x).float().cpu().numpy()


# --------------------------------------------------------------------------------------------------
# Segment image files
# --------------------------------------------------------------------------------------------------
def discover_images(input_path: str | Path) -> tuple[Path, list[Path]]:
    """(root, image files): a single file (any suffix; the reader decides), or every file with a
    supported image suffix under a folder, recursively, sorted, hidden entries skipped."""
    from pipeline.datasets.loading import SUPPORTED_SUFFIXES

    p = Path(input_path)
    if not p.exists():
        raise InputError(f"--input {p}: not found")
    if p.is_file():
        return p.parent, [p]
    files = sorted(f for f in p.rglob("*") if f.is_file() and f.suffix.lower() in SUPPORTED_SUFFIXES
                   and not any(part.startswith(".") for part in f.relative_to(p).parts))
    return p, files


def _is_within(child: Path, parent: Path) -> bool:
    try:
        child.relative_to(parent)
        return True
    except ValueError:
        return False


def plan_outputs(root: Path, files: Sequence[Path], out_dir: str | Path, input_is_dir: bool) -> list[Path]:
    """Output stem per input (``out/<relative folder>/<stem>``; ``<stem>_<ext>`` where two inputs of a
    folder share a stem).  Refuses (InputError) an output folder equal to or inside an input folder,
    and any output file that would be one of the inputs."""
    out = Path(out_dir).resolve()
    root_r = root.resolve()
    if input_is_dir and (out == root_r or _is_within(out, root_r)):
        raise InputError(f"--output {out_dir}: inside the input folder {root}; outputs must not mix with inputs")
    rel = [f.resolve().relative_to(root_r) if input_is_dir else Path(f.name) for f in files]
    counts: dict[tuple[Path, str], int] = {}
    for r in rel:
        counts[(r.parent, r.stem)] = counts.get((r.parent, r.stem), 0) + 1
    stems = []
    for r in rel:
        name = r.stem if counts[(r.parent, r.stem)] == 1 else f"{r.stem}_{r.suffix.lstrip('.').lower()}"
        stems.append(out / r.parent / name)
    inputs = {f.resolve() for f in files}
    for s in stems:
        for suffix in OUTPUT_SUFFIXES:
            target = s.with_name(s.name + suffix)
            if target in inputs:
                raise InputError(f"--output {out_dir}: would overwrite the input {target}")
    return stems


OUTPUT_SUFFIXES = ("_mask.png", "_prob.png", "_overlay.png")


def probs_to_size(probs: np.ndarray, height: int, width: int) -> np.ndarray:
    """Bilinear resize of a probability map [R,R] to the original [height, width] (values stay in [0,1])."""
    import cv2

    if probs.shape == (height, width):
        return probs
    return np.clip(cv2.resize(probs, (width, height), interpolation=cv2.INTER_LINEAR), 0.0, 1.0)


def overlay_image(image: np.ndarray, mask: np.ndarray, color=(255, 40, 40), alpha: float = 0.45) -> np.ndarray:
    """RGB uint8 overlay: mask tinted with ``color`` at ``alpha``, its inner contour drawn opaque."""
    import cv2

    out = image.astype(np.float32)
    col = np.asarray(color, np.float32)
    out[mask] = (1 - alpha) * out[mask] + alpha * col
    edge = mask & ~cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    out[edge] = col
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def write_png(path: Path, array: np.ndarray) -> None:
    """Write a PNG atomically (temp name, then rename); RGB arrays are converted to OpenCV's BGR."""
    import cv2

    arr = array[..., ::-1] if array.ndim == 3 else array
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(arr))
    if not ok:
        raise InputError(f"{path}: PNG encoding failed")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{uuid.uuid4().hex[:8]}")
    try:
        tmp.write_bytes(buf.tobytes())
        os.replace(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise InputError(f"{path}: cannot write ({e.strerror or e})") from None


@dataclasses.dataclass
class SegmentResult:
    written: list[Path]
    skipped: list[tuple[str, str]]  # (input path, reason)
    model_seconds: float = 0.0      # wall time inside the engine (Z = f(x) and sigmoid), all batches
    total_seconds: float = 0.0      # wall time of the whole loop (reading, resizing, PNG writing included)


def segment_files(segmenter: Segmenter, files: Sequence[Path], stems: Sequence[Path], *, tau: float,
                  resolution: int, batch_size: int = 8, save_prob: bool = False, overlay: bool = False,
                  on_skip: Callable[[str, str], None] | None = None) -> SegmentResult:
    """Segment image files in batches: read -> resize to R x R -> P = sigmoid(f(x)) -> resize P back
    to the original size -> M = [P >= tau] (eq:inference-mask) -> ``<stem>_mask.png`` (0/255), and
    optionally ``<stem>_prob.png`` (P as uint8, 255 = 1.0) and ``<stem>_overlay.png``.

    A file the reader rejects (InputError) is recorded in ``skipped`` and the rest go on.
    """
    from pipeline.datasets.loading import read_rgb, resize_image
    from pipeline.progress import progress

    written: list[Path] = []
    skipped: list[tuple[str, str]] = []
    model_s = 0.0
    t_start = time.perf_counter()
    bar = progress(total=len(files), desc="segment", unit="img")
    try:
        for s in range(0, len(files), batch_size):
            batch = []
            for f, stem in zip(files[s:s + batch_size], stems[s:s + batch_size]):
                try:
                    img = read_rgb(f)
                except InputError as e:
                    reason = str(e).splitlines()[0] if str(e) else type(e).__name__
                    reason = reason[len(f"{f}: "):] if reason.startswith(f"{f}: ") else reason
                    skipped.append((str(f), reason))
                    if on_skip is not None:
                        on_skip(str(f), reason)
                    bar.update(1)
                    continue
                batch.append((stem, img))
            if not batch:
                continue
            work = np.stack([resize_image(img, resolution) for _, img in batch])
            t0 = time.perf_counter()
            probs = segmenter.predict_probs(work, batch_size=batch_size)
            model_s += time.perf_counter() - t0
            for (stem, img), p in zip(batch, probs):
                h, w = img.shape[:2]
                p_full = probs_to_size(p, h, w)
                mask = mask_from_probs(p_full, tau)
                out = stem.with_name(stem.name + "_mask.png")
                write_png(out, mask.astype(np.uint8) * 255)
                written.append(out)
                if save_prob:
                    write_png(stem.with_name(stem.name + "_prob.png"),
                              np.round(p_full * 255).astype(np.uint8))
                if overlay:
                    write_png(stem.with_name(stem.name + "_overlay.png"), overlay_image(img, mask))
                bar.update(1)
    finally:
        bar.close()
    return SegmentResult(written, skipped, model_s, time.perf_counter() - t_start)


def write_skipped_csv(path: str | Path, skipped: Iterable[tuple[str, str]]) -> Path:
    """``skipped.csv`` (columns path, reason), written atomically; header only when nothing was skipped."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{uuid.uuid4().hex[:8]}")
    with open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["path", "reason"])
        w.writerows(skipped)
    os.replace(tmp, path)
    return path


# --------------------------------------------------------------------------------------------------
# int8 quantisation (ONNX Runtime static, QDQ)
# --------------------------------------------------------------------------------------------------
INT8_CALIBRATIONS = ("percentile", "minmax")


CALIBRATION_CHUNK = 4  # images per calibration pass: ORT keeps every activation of a pass in memory
                       # (about 375 MB per 384x384 image for TinyUNet), so passes bound the memory


def quantize_onnx_int8(onnx_path: str | Path, out_path: str | Path, calibration_images: np.ndarray,
                       calibration: str = "percentile", percentile: float = 99.999) -> Path:
    """Static int8 quantisation of an exported ONNX mask path (module docstring).

    QDQ format, uint8 asymmetric activations, int8 symmetric per-channel weights.  The graph input
    (the image, x = k/255, :class:`pipeline.model.ExportMaskPath`) is pinned to scale 1/255 and zero
    point 0, so 8-bit images enter the integer model exactly.  Every other activation range comes from
    ``calibration_images`` (uint8 [N,H,W,3], training images only -- never masks), fed in order in
    passes of :data:`CALIBRATION_CHUNK` images to ORT's calibrator, whose statistics merge over the
    passes (memory stays that of one pass): ``calibration="percentile"`` clips each range at the
    ``percentile`` of its histogram (a few outlier activations no longer stretch the 256 levels),
    ``"minmax"`` uses the observed extremes.  The ranges then enter ``quantize_static`` as
    per-tensor overrides.  Both are deterministic for the same images.
    """
    from onnxruntime.quantization import (CalibrationDataReader, CalibrationMethod, QuantFormat, QuantType,
                                          quantize_static)
    from onnxruntime.quantization.calibrate import create_calibrator
    from onnxruntime.quantization.registry import QDQRegistry, QLinearOpsRegistry
    from onnxruntime.quantization.shape_inference import quant_pre_process

    from pipeline.inference import images_to_tensor

    images = np.asarray(calibration_images)
    if images.ndim != 4 or len(images) == 0:
        raise InputError("int8 calibration needs at least one image (uint8 [N,H,W,3])")
    if calibration not in INT8_CALIBRATIONS:
        raise InputError(f"deploy.int8_calibration={calibration!r}: one of {', '.join(INT8_CALIBRATIONS)}")
    if not 50.0 < float(percentile) <= 100.0:
        raise InputError(f"deploy.int8_percentile={percentile!r}: must lie in (50, 100]")

    class _Reader(CalibrationDataReader):
        def __init__(self, batch: np.ndarray):
            self._batch, self._it = batch, iter(range(len(batch)))

        def get_next(self):
            i = next(self._it, None)
            return None if i is None else {ONNX_INPUT: images_to_tensor(self._batch[i:i + 1]).numpy()}

    overrides = {ONNX_INPUT: [{"scale": np.array(1.0 / 255.0, np.float32), "zero_point": np.array(0, np.uint8)}]}
    op_types = sorted(set(QLinearOpsRegistry) | set(QDQRegistry))  # what quantize_static calibrates
    root = logging.getLogger()
    level = root.level
    root.setLevel(logging.ERROR)  # the quantiser warns about every integer shape tensor it leaves alone
    try:
        with tempfile.TemporaryDirectory() as td, contextlib.redirect_stdout(io.StringIO()):
            # (redirect: the histogram calibrators print progress lines on stdout)
            pre = Path(td) / "pre.onnx"
            quant_pre_process(str(onnx_path), str(pre))
            method, options = CalibrationMethod.MinMax, {}
            if calibration == "percentile":
                method, options = CalibrationMethod.Percentile, {"percentile": float(percentile)}
            calibrator = create_calibrator(pre, op_types, augmented_model_path=Path(td) / "augmented.onnx",
                                           calibrate_method=method, extra_options=options)
            for s in range(0, len(images), CALIBRATION_CHUNK):  # ranges merge over the passes
                calibrator.collect_data(_Reader(images[s:s + CALIBRATION_CHUNK]))
            for name, data in calibrator.compute_data().items():
                lo, hi = data.range_value
                overrides.setdefault(name, [{"rmin": np.array(lo, np.float32).reshape(()),
                                             "rmax": np.array(hi, np.float32).reshape(())}])
            del calibrator
            # every range is overridden: quantize_static's own calibration pass only has to run the graph
            quantize_static(str(pre), str(out_path), _Reader(images[:1]), quant_format=QuantFormat.QDQ,
                            activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, per_channel=True,
                            calibrate_method=CalibrationMethod.MinMax, op_types_to_quantize=op_types,
                            extra_options={"TensorQuantOverrides": overrides})
    finally:
        root.setLevel(level)
    import onnx

    quantized = onnx.load(str(out_path))
    if shapes_from_quantized(quantized.graph):
        onnx.save(quantized, str(out_path))
    return Path(out_path)


def shapes_from_quantized(graph) -> int:
    """Let every Shape node that reads a DequantizeLinear output read the DQ's integer input instead.

    Same values (quantise/dequantise keep the shape), one consumer fewer: the exporter's bilinear
    Resize takes the shape of its own input, and a DQ with two consumers is not fused into the int8
    kernels, so ONNX Runtime dequantised and transposed those feature maps just to read their shape
    (about 2 ms of 40 at 384x384).  Edits ``graph`` in place; returns the number of Shape nodes moved.
    """
    producer = {out: node for node in graph.node for out in node.output}
    moved = 0
    for node in graph.node:
        src = producer.get(node.input[0]) if node.op_type == "Shape" else None
        if src is not None and src.op_type == "DequantizeLinear":
            node.input[0] = src.input[0]
            moved += 1
    return moved


def int8_params(cfg: dict) -> dict:
    """The int8 settings of the ``deploy`` params section, checked (InputError names the param):
    ``calibration`` (deploy.int8_calibration) and ``percentile`` (deploy.int8_percentile)."""
    from pipeline.params import require

    calibration = require(cfg, "int8_calibration", "deploy", kind=str)
    if calibration not in INT8_CALIBRATIONS:
        raise InputError(f"params: deploy.int8_calibration={calibration!r}: one of {', '.join(INT8_CALIBRATIONS)}")
    percentile = float(require(cfg, "int8_percentile", "deploy", kind=(int, float), lo=50.0, hi=100.0))
    return {"calibration": calibration, "percentile": percentile}


def int8_description(calibration: str, percentile: float) -> str:
    how = f"{percentile:g}th-percentile" if calibration == "percentile" else "MinMax"
    return ("ONNX Runtime static QDQ: input pinned to scale 1/255 (exact for 8-bit images), uint8 asymmetric "
            f"activations ({how} ranges on training images), int8 symmetric per-channel weights")


# --------------------------------------------------------------------------------------------------
# Efficiency benchmark
# --------------------------------------------------------------------------------------------------
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
        import ctypes

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
        t0 = time.perf_counter()
        fn(x)
        sync()
        times.append(time.perf_counter() - t0)
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
    """Variants of the mask path to compare; returns (variants, {skipped name: reason}).

    fp32_eager_nchw          plain PyTorch, contiguous NCHW (the baseline)
    fp32_channels_last       PyTorch, channels_last model and input
    bf16_autocast            PyTorch NCHW under bf16 autocast
    bf16_channels_last       bf16 autocast + channels_last
    torchscript_frozen       traced, frozen, torch.jit.optimize_for_inference (CPU: oneDNN fusions)
    onnxruntime_fp32         ONNX Runtime CPU, all graph optimisations
    onnxruntime_int8         ONNX Runtime CPU on the static int8 QDQ model (quantize_onnx_int8)
    """
    import torch

    dev = torch.device(device)
    skipped: dict[str, str] = {}
    variants: list[Variant] = []
    sync = (lambda: torch.cuda.synchronize()) if dev.type == "cuda" else (lambda: None)
    base = mask_path_model(model).to(dev)
    cl = mask_path_model(model).to(dev).to(memory_format=torch.channels_last)
    cl_fmt = torch.channels_last

    def eager(m, to_cl=False, bf16=False):
        def run(x):
            x = x.to(dev, non_blocking=True)
            if to_cl:
                x = x.contiguous(memory_format=cl_fmt)
            with torch.inference_mode(), (torch.autocast(dev.type, dtype=torch.bfloat16) if bf16
                                          else contextlib.nullcontext()):
                return m(x).float()
        return run

    for name in names:
        if name == "fp32_eager_nchw":
            variants.append(Variant(name, "PyTorch eager fp32, NCHW (baseline)", eager(base), dev.type, sync))
        elif name == "fp32_channels_last":
            variants.append(Variant(name, "PyTorch eager fp32, channels_last", eager(cl, True), dev.type, sync))
        elif name == "bf16_autocast":
            variants.append(Variant(name, "PyTorch eager, bf16 autocast, NCHW", eager(base, bf16=True), dev.type, sync))
        elif name == "bf16_channels_last":
            variants.append(Variant(name, "PyTorch eager, bf16 autocast, channels_last", eager(cl, True, True),
                                    dev.type, sync))
        elif name == "torchscript_frozen":
            example = torch.zeros(1, base.config["in_channels"], resolution, resolution, device=dev)
            with torch.no_grad(), warnings.catch_warnings():
                warnings.simplefilter("ignore")
                ts = torch.jit.freeze(torch.jit.trace(mask_path_model(model).to(dev), example, check_trace=False))
                if dev.type == "cpu":
                    ts = torch.jit.optimize_for_inference(ts)
            variants.append(Variant(name, "TorchScript traced + frozen + optimize_for_inference, fp32",
                                    eager(ts), dev.type, sync))
        elif name in ("onnxruntime_fp32", "onnxruntime_int8"):
            reason = onnx_unavailable_reason()
            path = onnx_path if name == "onnxruntime_fp32" else int8_path
            if reason is None and path is None:
                reason = "no ONNX model"
            if reason is not None:
                skipped[name] = reason
                continue
            sess = ort_session(path)

            def run(x, sess=sess):
                return torch.from_numpy(sess.run(None, {ONNX_INPUT: np.ascontiguousarray(x.cpu().numpy())})[0])
            desc = ("ONNX Runtime CPU fp32, graph optimisations ORT_ENABLE_ALL" if name == "onnxruntime_fp32" else
                    "ONNX Runtime CPU int8 (static QDQ model.int8.onnx: u8 activations, s8 per-channel "
                    "weights, ranges calibrated on training images)")
            variants.append(Variant(name, desc, run, "cpu"))
        else:
            raise InputError(f"deploy.benchmark_variants: unknown variant {name!r}")
    return variants, skipped


def mean_image_iou(masks: np.ndarray, reference: np.ndarray) -> float:
    """Mean over images of image_iou(masks[i], reference[i]) (pipeline.metrics; both empty -> 1); NaN if none."""
    from pipeline.metrics import image_ious

    return float(np.mean(image_ious(masks, reference))) if len(masks) else float("nan")


def variant_probs(variant: Variant, images: np.ndarray, batch_size: int) -> np.ndarray:
    """P = sigmoid(Z) float32 [N,H,W] of a variant on uint8 images [N,H,W,3]."""
    import torch

    from pipeline.inference import images_to_tensor

    out = np.empty(images.shape[:3], np.float32)
    for s in range(0, len(images), batch_size):
        z = variant.run(images_to_tensor(np.asarray(images[s:s + batch_size])))
        out[s:s + batch_size] = torch.sigmoid(torch.as_tensor(z).float())[:, 0].cpu().numpy()
    return out


def benchmark(model, *, resolution: int, device="cpu", variants: Sequence[str], warmup: int, iters: int,
              batches: Sequence[int], tau: float | None = None, val_images: np.ndarray | None = None,
              val_masks: np.ndarray | None = None, onnx_path=None, int8_path=None, seed: int = 0,
              on_variant: Callable[[str], None] | None = None) -> tuple[list[dict], dict]:
    """Measure every variant; returns (rows, info).

    Per variant: ``latency_ms`` = median of ``iters`` batch-1 calls on a random input at ``resolution``,
    timed round-robin across the variants after ``warmup`` calls each (:func:`interleaved_times`);
    ``throughput`` (images/s) = best over ``batches`` of b / median call time (1 warm-up, then
    max(2, ceil(iters / b)) calls); ``peak_mb`` = peak memory growth during the warm-up calls
    (:class:`PeakMemory`); ``iou`` = mean Image IoU on the validation images at tau and ``iou_delta``
    = iou - iou of the fp32 baseline; ``iou_vs_fp32`` = mean per-image IoU between the variant's mask
    and the baseline's (1 = the same masks; NaN without validation data or baseline); ``speedup`` =
    baseline latency / latency.  params and GFLOPs are counted on the PyTorch graph
    (pipeline.model.count_parameters / count_flops) and shared by every variant: they compute the
    same function (int8 replaces multiply-adds by integer ones, it does not remove them).
    """
    import torch

    from pipeline.model import count_flops, count_parameters

    dev = torch.device(device)
    deployed = mask_path_model(model)
    params = count_parameters(deployed)
    gflops = count_flops(deployed, resolution, resolution) / 1e9
    built, skipped = build_variants(model, dev, resolution, variants, onnx_path, int8_path)
    g = torch.Generator().manual_seed(seed)
    x1 = torch.rand(1, deployed.config["in_channels"], resolution, resolution, generator=g)
    rows = []
    masks: dict[str, np.ndarray] = {}
    have_val = val_images is not None and val_masks is not None and len(val_images) > 0 and tau is not None
    for v in built:
        if on_variant is not None:
            on_variant(v.name)
        with PeakMemory(v.device) as mem:
            time_calls(v.run, x1, max(1, warmup), 0, v.sync)
        best_tp, best_b = 0.0, 1
        for b in batches:
            xb = torch.rand(int(b), x1.shape[1], resolution, resolution, generator=g)
            tb = time_calls(v.run, xb, 1, max(2, math.ceil(iters / int(b))), v.sync)
            tp = int(b) / statistics.median(tb)
            if tp > best_tp:
                best_tp, best_b = tp, int(b)
        iou = float("nan")
        if have_val:
            masks[v.name] = mask_from_probs(variant_probs(v, val_images, max(batches)), tau)
            iou = mean_image_iou(masks[v.name], val_masks)
        rows.append({"variant": v.name, "description": v.description, "device": v.device, "params": params,
                     "gflops": gflops, "throughput": best_tp, "batch": best_b, "peak_mb": mem.peak_mb,
                     "peak_method": mem.method, "iou": iou, "resolution": int(resolution)})
    times = interleaved_times(built, x1, iters)
    for r in rows:
        r["latency_ms"] = statistics.median(times[r["variant"]]) * 1e3
        r["latency_min_ms"] = min(times[r["variant"]]) * 1e3
    base = next((r for r in rows if r["variant"] == BASELINE_VARIANT), None)
    base_masks = masks.get(BASELINE_VARIANT)
    for r in rows:
        r["iou_delta"] = r["iou"] - base["iou"] if base is not None and have_val else float("nan")
        r["iou_vs_fp32"] = mean_image_iou(masks[r["variant"]], base_masks) if base_masks is not None else float("nan")
        r["speedup"] = base["latency_ms"] / r["latency_ms"] if base else float("nan")
    info = {"threads": torch.get_num_threads(), "device": str(dev), "resolution": int(resolution),
            "warmup": int(warmup), "iters": int(iters), "batches": [int(b) for b in batches],
            "latency_timing": "round-robin across variants (interleaved_times)",
            "tau": tau, "n_val": int(len(val_images)) if have_val else 0, "skipped": skipped}
    return rows, info


def fastest_within(rows: Sequence[dict], max_iou_drop: float) -> dict | None:
    """The lowest-latency variant whose |iou_delta| <= ``max_iou_drop`` (any variant without IoU data)."""
    ok = [r for r in rows if not (abs(r["iou_delta"]) > max_iou_drop)]  # NaN passes: no data to judge
    return min(ok, key=lambda r: r["latency_ms"]) if ok else None
