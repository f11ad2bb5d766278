"""int8 deployment: static ONNX Runtime quantisation of the exported mask path, its calibration images,
and its agreement gate against PyTorch.

Decisions (the paper is silent on deployment formats):

* int8: ONNX Runtime static quantisation (QDQ format, uint8 asymmetric activations, symmetric
  per-channel weights; activation ranges from TRAINING-split images -- images only, no masks --
  clipped at the ``deploy.int8_percentile`` of their histograms, or MinMax).
* The convolutions that write the logits (the mask head) stay fp32 (:func:`output_convolutions`).
* Weights in 7 bits by default (``deploy.int8_weight_bits``; ORT's ``reduce_range``), so that every x86
  CPU computes the same integers: without VNNI (SSE, AVX2, AVX-512 without VNNI) ORT's and oneDNN's
  u8*s8 kernels add two products into a saturating int16 (``vpmaddubsw``), and 2 * 255 * 127 = 64770
  overflows it, while 2 * 255 * 64 = 32640 does not.  Measured on an AVX2-only host: 8-bit weights
  gave a mean mask IoU of 0.83 against fp32, 7-bit 0.95; on VNNI hosts 8-bit gave 0.97.  Chosen over
  u8u8, which oneDNN (OpenVINO) does not run in int8.  The export checks the masks on the host's own
  instruction set and, with OpenVINO installed, under ``ONEDNN_MAX_CPU_ISA=AVX2`` (:func:`isa_checks`),
  and records both in contract.json.  The graph input is pinned to scale 1/255, zero point 0: with the
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
  minimum).  When the mean mask IoU is below ``deploy.int8_min_mask_iou`` (0.9 by default) on any
  checked instruction set, the bundle ships without the int8 model (fp32 only) and says why: the
  training already spent is never wasted on an approximation.  The images are in-sample for the activation
  ranges; the held-out effect (validation Image IoU change, and mask IoU against fp32) is measured by
  the benchmark.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Sequence

import numpy as np

from pipeline import catalog
from pipeline.artifacts.store import open_artifact, read_chunk_rows
from pipeline.datasets.loading import resize_image
from pipeline.deploy import openvino_engine
from pipeline.deploy.mask_path import ONNX_INPUT, mask_path_model, ort_session, torch_logits
from pipeline.runtime.environment import cpu
from pipeline.runtime.errors import InputError
from pipeline.evaluation.inference import images_to_tensor
from pipeline.metrics import image_ious
from pipeline.params import INT8_CALIBRATIONS
from pipeline.thresholds import logit_threshold


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
    paths = (catalog.path("manifest", art), catalog.path("images", art))
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
    """int8 parity report (module docstring, "int8 parity") of logits [N,...] against the PyTorch ``reference``.

    Masks are M = [Z >= logit(tau)] (eq:inference-mask).  Reports max/mean |Z - Z_ref|, the fraction of
    pixels whose mask agrees, and the per-image mask IoU between the two models (image_iou; both
    empty -> 1): its mean and minimum.  ``passed`` = finite logits and mean mask IoU >= ``min_mask_iou``
    -- a gate on masks rather than pixels, because a pixel fraction hides a small object that int8
    loses (it is 0.1 % of the pixels and 100 % of that image's mask).
    """
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
    [N,R,R,3] (the calibration images at export), with ``isas``: the same check on every instruction
    set of :func:`isa_checks`.  Does not raise."""
    deployed = mask_path_model(model)
    sess = ort_session(int8_path)
    ref, got = [], []
    for s in range(0, len(images), batch_size):
        x = images_to_tensor(np.asarray(images[s:s + batch_size]))
        ref.append(torch_logits(deployed, x))
        got.append(sess.run(None, {ONNX_INPUT: x.numpy()})[0])
    ref = np.concatenate(ref)
    out = int8_agreement(ref, np.concatenate(got), tau, min_mask_iou)
    out["images"] = int(len(images))
    out["inputs"] = f"{len(images)} int8 calibration images (training split), tau = {float(tau):.6g}"
    out["isas"] = isa_checks(out, int8_path, images_to_tensor(np.asarray(images)).numpy(), ref, tau, min_mask_iou)
    return out


def int8_miss(report: dict, where: str) -> str:
    """Why the int8 model is left out of a bundle: its masks missed the gate ``deploy.int8_min_mask_iou``."""
    return (f"its masks overlap PyTorch's with a mean IoU of {report['mask_iou_mean']:.4f} on {where}, below "
            f"deploy.int8_min_mask_iou = {report['min_mask_iou']:g} (max |dZ| = {report['max_abs_diff']:.3g}): "
            "the bundle ships fp32 only")


def host_isa(flags=None) -> str:
    """The widest integer dot-product instruction set of this CPU: amx_int8, avx512_vnni, avx_vnni, avx2 or
    baseline (``flags``: /proc/cpuinfo flags; default this machine's)."""
    if flags is None:
        flags = cpu()["flags"]
    flags = set(flags)
    return next((isa for isa in ("amx_int8", "avx512_vnni", "avx_vnni", "avx2") if isa in flags), "baseline")


#: instruction sets a bundle's int8 model is checked on besides the host's (oneDNN ISA names, set through
#: ONEDNN_MAX_CPU_ISA for OpenVINO in a child process: oneDNN reads it once, when it loads)
EMULATED_ISAS = ("AVX2",)

# the child loads openvino_engine.py by its path: importing the pipeline.deploy package would load torch
_OPENVINO_CHILD = """
import importlib.util, sys, numpy as np
spec = importlib.util.spec_from_file_location("openvino_engine", sys.argv[4])
engine = importlib.util.module_from_spec(spec); spec.loader.exec_module(engine)
x = np.load(sys.argv[2]); run = engine.OpenVinoRunner(sys.argv[1], threads=1)
np.save(sys.argv[3], np.concatenate([run(x[i:i + 8]) for i in range(0, len(x), 8)]))
"""


def openvino_logits(int8_path: str | Path, x: np.ndarray, isa: str) -> np.ndarray:
    """The int8 model's logits on OpenVINO's CPU plugin restricted to the oneDNN instruction set ``isa``
    (a child process with ``ONEDNN_MAX_CPU_ISA=isa``); x float32 [N,3,H,W]."""
    with tempfile.TemporaryDirectory() as td:
        xin, out = Path(td) / "x.npy", Path(td) / "z.npy"
        np.save(xin, np.asarray(x, np.float32))
        done = subprocess.run([sys.executable, "-c", _OPENVINO_CHILD, str(int8_path), str(xin), str(out),
                               openvino_engine.__file__], env={**os.environ, "ONEDNN_MAX_CPU_ISA": isa},
                              capture_output=True, text=True)
        if done.returncode != 0:
            raise RuntimeError(done.stderr.strip().splitlines()[-1] if done.stderr.strip() else "failed")
        return np.load(out)


def isa_checks(native: dict, int8_path: str | Path, x: np.ndarray, reference: np.ndarray, tau: float,
               min_mask_iou: float) -> list[dict]:
    """The instruction sets the int8 model's masks were checked on: the host's (ONNX Runtime, the
    ``native`` :func:`int8_agreement` report) and each of :data:`EMULATED_ISAS` (OpenVINO, when it is
    installed), each with its mean mask IoU against PyTorch's ``reference`` logits on the inputs ``x``."""
    import onnxruntime

    checks = [{"isa": host_isa(), "runtime": f"onnxruntime {onnxruntime.__version__}", "how": "this host",
               "mask_iou_mean": native["mask_iou_mean"], "passed": native["passed"]}]
    if (reason := openvino_engine.openvino_unavailable_reason()) is not None:
        return checks + [{"isa": isa.lower(), "runtime": None, "how": reason, "passed": None} for isa in EMULATED_ISAS]
    import openvino

    for isa in EMULATED_ISAS:
        try:
            rep = int8_agreement(reference, openvino_logits(int8_path, x, isa), tau, min_mask_iou)
        except RuntimeError as e:
            checks.append({"isa": isa.lower(), "runtime": None, "how": f"OpenVINO failed: {e}", "passed": None})
            continue
        checks.append({"isa": isa.lower(), "runtime": f"openvino {openvino.__version__}",
                       "how": f"ONEDNN_MAX_CPU_ISA={isa}", "mask_iou_mean": rep["mask_iou_mean"],
                       "max_abs_diff": rep["max_abs_diff"], "passed": rep["passed"]})
    return checks


CALIBRATION_CHUNK = 4  # images per calibration pass: ORT keeps every activation of a pass in memory
                       # (about 375 MB per 384x384 image for TinyUNet), so passes bound the memory


def quantize_onnx_int8(onnx_path: str | Path, out_path: str | Path, calibration_images: np.ndarray,
                       calibration: str = "percentile", percentile: float = 99.999, weight_bits: int = 7) -> Path:
    """Static int8 quantisation of an exported ONNX mask path (module docstring, "int8").

    QDQ format, uint8 asymmetric activations, symmetric per-channel weights in ``weight_bits`` bits (7:
    [-64, 64], ORT's ``reduce_range``, no saturation without VNNI; 8: [-127, 127]).  The graph input
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

    images = np.asarray(calibration_images)
    if images.ndim != 4 or len(images) == 0:
        raise InputError("int8 calibration needs at least one image (uint8 [N,H,W,3])")
    if calibration not in INT8_CALIBRATIONS:
        raise InputError(f"deploy.int8_calibration={calibration!r}: one of {', '.join(INT8_CALIBRATIONS)}")
    if not 50.0 < float(percentile) <= 100.0:
        raise InputError(f"deploy.int8_percentile={percentile!r}: must lie in (50, 100]")
    if int(weight_bits) not in (7, 8):
        raise InputError(f"deploy.int8_weight_bits={weight_bits!r}: 7 or 8")

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
                            nodes_to_exclude=output_convolutions(pre),
                            activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, per_channel=True,
                            reduce_range=int(weight_bits) == 7,
                            calibrate_method=CalibrationMethod.MinMax, op_types_to_quantize=op_types,
                            extra_options={"TensorQuantOverrides": overrides})
    finally:
        root.setLevel(level)
    import onnx

    quantized = onnx.load(str(out_path))
    if shapes_from_quantized(quantized.graph):
        onnx.save(quantized, str(out_path))
    return Path(out_path)


def output_convolutions(onnx_path: str | Path) -> list[str]:
    """Names of the convolutions that write a graph output (TinyUNet's 1x1 mask head): they stay fp32.

    Why: the logits are what the mask thresholds, and the head's 8-bit output grid and 7-bit weights cost
    most of the int8 error; in fp32 it is 0.03 % of the FLOPs.  Measured on the demo's Plain Student (64^2,
    64 training images): mean mask IoU against fp32 0.888 with every convolution in int8, 0.965 with the
    head in fp32 (7-bit weights, the same on AVX-512-VNNI and under AVX2)."""
    import onnx

    graph = onnx.load(str(onnx_path)).graph
    outputs = {o.name for o in graph.output}
    return [n.name for n in graph.node if n.op_type == "Conv" and set(n.output) & outputs]


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
    """The int8 settings of the (schema-validated) ``deploy`` params: ``calibration``
    (deploy.int8_calibration), ``percentile`` (deploy.int8_percentile), ``weight_bits``
    (deploy.int8_weight_bits)."""
    return {"calibration": cfg["int8_calibration"], "percentile": float(cfg["int8_percentile"]),
            "weight_bits": int(cfg["int8_weight_bits"])}


def int8_description(calibration: str, percentile: float, weight_bits: int = 7) -> str:
    how = f"{percentile:g}th-percentile" if calibration == "percentile" else "MinMax"
    weights = ("7-bit symmetric per-channel weights in [-64, 64] (no int16 saturation on CPUs without VNNI)"
               if int(weight_bits) == 7 else "8-bit symmetric per-channel weights (exact on VNNI/AMX CPUs only)")
    return ("ONNX Runtime static QDQ: input pinned to scale 1/255 (exact for 8-bit images), uint8 asymmetric "
            f"activations ({how} ranges on training images), {weights}")
