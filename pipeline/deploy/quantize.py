"""The int8 mask path.

ONNX Runtime static QDQ quantisation calibrated on training images (never masks), and its agreement gate
against PyTorch on every checked instruction set (docs/decisions.md, "int8").
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import logging
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Literal, Mapping, Sequence

import numpy as np

from pipeline import catalog
from pipeline.artifacts.store import open_artifact, read_chunk_rows
from pipeline.datasets.loading import resize_image
from pipeline.deploy import openvino_engine
from pipeline.deploy.mask_path import ONNX_INPUT, ort_session, torch_logits
from pipeline.artifacts.provenance import cpu
from pipeline.runtime.errors import InputError
from pipeline.evaluation.inference import images_to_tensor
from pipeline.metrics import image_ious
from pipeline.model import mask_path_model
from pipeline.params import INT8_CALIBRATIONS, INT8_WEIGHT_BITS, validate
from pipeline.thresholds import logit_threshold

__all__ = ["Int8Settings", "calibration_rows", "read_calibration_images", "int8_agreement", "check_int8_parity",
           "int8_miss", "host_isa", "EMULATED_ISAS", "openvino_logits", "CALIBRATION_CHUNK", "quantize_onnx_int8",
           "output_convolutions", "int8_description"]


@dataclasses.dataclass(frozen=True)
class Int8Settings:
    """The int8 export settings: the ``deploy`` params named ``int8_*``.

    They keep the same names from params.yaml down to :func:`quantize_onnx_int8`.  No defaults and no bounds
    here: both are the schema's (:class:`pipeline.params.DeployParams`), which every instance is checked against.

    Attributes
    ----------
    int8_calibration_images : int
        ``deploy.int8_calibration_images``: training-split images (never masks) the activation ranges come from.
    int8_calibration : str
        ``deploy.int8_calibration``: how a range is read from them, ``percentile`` or ``minmax``.
    int8_percentile : float
        ``deploy.int8_percentile``: the percentile of the ``percentile`` calibration.
    int8_weight_bits : int
        ``deploy.int8_weight_bits``: 7 (no int16 saturation on CPUs without VNNI) or 8.
    int8_min_mask_iou : float
        ``deploy.int8_min_mask_iou``: below this mean int8-vs-PyTorch mask IoU the bundle ships fp32 only.

    Raises
    ------
    InputError
        A value the schema refuses, naming ``params: deploy.<key>``.
    """

    int8_calibration_images: int
    int8_calibration: Literal[INT8_CALIBRATIONS]
    int8_percentile: float
    int8_weight_bits: Literal[INT8_WEIGHT_BITS]
    int8_min_mask_iou: float

    def __post_init__(self):
        """Check the values against the schema (the class docstring's Raises)."""
        validate({"deploy": dataclasses.asdict(self)})  # the schema's rules, the only ones

    @classmethod
    def from_params(cls, cfg: Mapping) -> Int8Settings:
        """Read the int8 settings of a validated ``deploy`` section.

        Parameters
        ----------
        cfg : Mapping
            The validated ``deploy:`` section.

        Returns
        -------
        Int8Settings
            Its ``int8_*`` values.
        """
        return cls(**{f.name: cfg[f.name] for f in dataclasses.fields(cls)})


def calibration_rows(splits: Sequence[str], n: int) -> np.ndarray:
    """Pick the calibration rows: up to ``n`` training-split rows, evenly spaced in manifest order.

    Parameters
    ----------
    splits : Sequence of str
        The manifest's ``split`` column.
    n : int
        The most rows picked (``deploy.int8_calibration_images``).

    Returns
    -------
    np.ndarray
        The picked row indices, ascending.
    """
    train = np.flatnonzero(np.asarray(splits).astype(str) == "train")
    if len(train) <= n:
        return train
    return train[np.unique(np.linspace(0, len(train) - 1, int(n)).round().astype(int))]


def read_calibration_images(art: str | Path, n: int, resolution: int | None = None):
    """Read the int8 calibration images: the :func:`calibration_rows` of images.zarr.

    Parameters
    ----------
    art : str or Path
        The artifacts directory (its ``manifest`` and ``images``).
    n : int
        The most images read (``deploy.int8_calibration_images``).
    resolution : int or None
        The side they are resized to, as segment resizes; None keeps the stored size.

    Returns
    -------
    tuple
        ``(images, opened, note)``: uint8 [M,R,R,3] (None when there are none), the artifacts opened (for the
        caller's lineage) and a line saying what was read, or why nothing was.
    """
    paths = (catalog.path("manifest", art), catalog.path("images", art))
    missing = [str(p) for p in paths if not p.exists()]
    if missing:
        return None, [], f"no training images for int8 calibration ({', '.join(missing)} missing)"
    manifest, images = open_artifact(paths[0], "manifest"), open_artifact(paths[1], "images")
    rows = calibration_rows(manifest.df["split"].to_numpy(), n)
    if rows.size == 0:
        return None, [manifest, images], f"no training-split rows in {paths[0]} for int8 calibration"
    calib = read_chunk_rows(images["image"], rows)
    if resolution is not None and calib.shape[1:3] != (resolution, resolution):
        calib = np.stack([resize_image(im, int(resolution)) for im in calib])
    return calib, [manifest, images], f"{len(calib)} training-split images of {paths[1]} (no masks)"


def int8_agreement(reference: np.ndarray, logits: np.ndarray, tau: float, min_mask_iou: float) -> dict:
    """Compare int8 logits with the PyTorch ``reference`` at tau (the masks of eq:inference-mask).

    Parameters
    ----------
    reference : np.ndarray
        The PyTorch mask path's logits [N, ...].
    logits : np.ndarray
        The int8 model's logits on the same inputs.
    tau : float
        The mask threshold.
    min_mask_iou : float
        The smallest mean per-image mask IoU that passes (``deploy.int8_min_mask_iou``).

    Returns
    -------
    dict
        ``passed`` (finite and mean IoU >= ``min_mask_iou``), max and mean |dZ|, the share of agreeing mask
        pixels, the mean and least per-image mask IoU, ``mask_pixels_differ`` and ``pixels`` (a shape mismatch
        fails, with a ``note``).
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
    per_image = (len(mask), 1, -1)  # each image one 2-D row: the same IoU for any layout
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
    """Check the int8 model against the PyTorch mask path on calibration images.

    Parameters
    ----------
    model : TinyUNet
        The student.
    int8_path : str or Path
        The int8 ONNX model.
    images : np.ndarray
        uint8 [N,R,R,3] images.
    tau : float
        The mask threshold.
    min_mask_iou : float
        The smallest mean per-image mask IoU that passes (``deploy.int8_min_mask_iou``).
    batch_size : int
        Images per forward pass.

    Returns
    -------
    dict
        :func:`int8_agreement` of the host's ONNX Runtime run, with ``images``, ``inputs`` and ``isas`` (the
        check per instruction set, :func:`isa_checks`).
    """
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
    """Say why the int8 model is left out of a bundle.

    Parameters
    ----------
    report : dict
        The failed :func:`int8_agreement` (or :func:`check_int8_parity`) result.
    where : str
        Where it failed (this host, an instruction set).

    Returns
    -------
    str
        The reason, for deploy.json and the log.
    """
    return (f"its masks overlap PyTorch's with a mean IoU of {report['mask_iou_mean']:.4f} on {where}, below "
            f"deploy.int8_min_mask_iou = {report['min_mask_iou']:g} (max |dZ| = {report['max_abs_diff']:.3g}): "
            "the bundle ships fp32 only")


def host_isa(flags=None) -> str:
    """Name the widest integer dot-product instruction set of a CPU.

    Parameters
    ----------
    flags : iterable of str or None
        The CPU's flags; None: this host's.

    Returns
    -------
    str
        ``amx_int8``, ``avx512_vnni``, ``avx_vnni``, ``avx2`` or ``baseline``.
    """
    flags = set(cpu()["flags"] if flags is None else flags)
    return next((isa for isa in ("amx_int8", "avx512_vnni", "avx_vnni", "avx2") if isa in flags), "baseline")


#: oneDNN instruction sets the int8 model is checked on besides the host's (a child process: oneDNN reads
#: ONEDNN_MAX_CPU_ISA once, when it loads)
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
    """Run the int8 model on OpenVINO restricted to one oneDNN instruction set, in a child process.

    Parameters
    ----------
    int8_path : str or Path
        The int8 ONNX model.
    x : np.ndarray
        float32 [N,3,H,W] RGB in [0, 1].
    isa : str
        The ``ONEDNN_MAX_CPU_ISA`` value (one of :data:`EMULATED_ISAS`).

    Returns
    -------
    np.ndarray
        The logits [N,1,H,W].

    Raises
    ------
    RuntimeError
        The child process failed (its last line of stderr).
    """
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
    """List the int8 check per instruction set.

    The host's check (``native``, ONNX Runtime) and one per :data:`EMULATED_ISAS` (OpenVINO, if installed).
    """
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


#: images per calibration pass: ONNX Runtime holds every activation of a pass (~375 MB per 384² image)
CALIBRATION_CHUNK = 4


def quantize_onnx_int8(onnx_path: str | Path, out_path: str | Path, calibration_images: np.ndarray,
                       int8_settings: Int8Settings) -> Path:
    """Quantise an ONNX mask path to a static QDQ int8 model.

    The input is pinned to scale 1/255 (exact for 8-bit images), u8 activation ranges come from
    ``calibration_images``, s8 per-channel weights, and the head stays fp32.

    Parameters
    ----------
    onnx_path : str or Path
        The fp32 ONNX mask path.
    out_path : str or Path
        The int8 model written.
    calibration_images : np.ndarray
        uint8 [N,H,W,3] training images (never masks).
    int8_settings : Int8Settings
        The calibration (``percentile`` or ``minmax``), its percentile, and the weight bits.

    Returns
    -------
    Path
        ``out_path``.

    Raises
    ------
    InputError
        ``calibration_images`` holds no image, or is not [N,H,W,3].
    """
    from onnxruntime.quantization import (CalibrationDataReader, CalibrationMethod, QuantFormat, QuantType,
                                          quantize_static)
    from onnxruntime.quantization.calibrate import create_calibrator
    from onnxruntime.quantization.registry import QDQRegistry, QLinearOpsRegistry
    from onnxruntime.quantization.shape_inference import quant_pre_process

    images = np.asarray(calibration_images)
    if images.ndim != 4 or len(images) == 0:
        raise InputError("int8 calibration needs at least one image (uint8 [N,H,W,3])")

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
            if int8_settings.int8_calibration == "percentile":
                method, options = CalibrationMethod.Percentile, {"percentile": float(int8_settings.int8_percentile)}
            calibrator = create_calibrator(pre, op_types, augmented_model_path=Path(td) / "augmented.onnx",
                                           calibrate_method=method, extra_options=options)
            for s in range(0, len(images), CALIBRATION_CHUNK):  # ranges merge over the passes
                calibrator.collect_data(_Reader(images[s:s + CALIBRATION_CHUNK]))
            for name, data in calibrator.compute_data().items():
                lo, hi = data.range_value
                overrides.setdefault(name, [{"rmin": np.array(lo, np.float32).reshape(()),
                                             "rmax": np.array(hi, np.float32).reshape(())}])
            del calibrator
            # every range is overridden: quantize_static's own pass only runs the graph
            quantize_static(str(pre), str(out_path), _Reader(images[:1]), quant_format=QuantFormat.QDQ,
                            nodes_to_exclude=output_convolutions(pre),
                            activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, per_channel=True,
                            reduce_range=int8_settings.int8_weight_bits == 7,
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
    """Name the convolutions that write a graph output (the mask head): they stay fp32.

    Parameters
    ----------
    onnx_path : str or Path
        The ONNX model.

    Returns
    -------
    list of str
        Their node names.
    """
    import onnx

    graph = onnx.load(str(onnx_path)).graph
    outputs = {o.name for o in graph.output}
    return [n.name for n in graph.node if n.op_type == "Conv" and set(n.output) & outputs]


def shapes_from_quantized(graph) -> int:
    """Point every Shape node reading a DequantizeLinear output at its integer input instead (same shape).

    A DQ with two consumers is not fused into the int8 kernels.  In place; returns the number of nodes moved.
    """
    producer = {out: node for node in graph.node for out in node.output}
    moved = 0
    for node in graph.node:
        src = producer.get(node.input[0]) if node.op_type == "Shape" else None
        if src is not None and src.op_type == "DequantizeLinear":
            node.input[0] = src.input[0]
            moved += 1
    return moved


def int8_description(int8_settings: Int8Settings) -> str:
    """Say in words how :func:`quantize_onnx_int8` quantises (deploy.json, contract.json).

    Parameters
    ----------
    int8_settings : Int8Settings
        The settings used.

    Returns
    -------
    str
        One sentence: the runtime, input scale, activation ranges and weights.
    """
    how = f"{int8_settings.int8_percentile:g}th-percentile" if int8_settings.int8_calibration == "percentile" \
        else "MinMax"
    weights = ("7-bit symmetric per-channel weights in [-64, 64] (no int16 saturation on CPUs without VNNI)"
               if int8_settings.int8_weight_bits == 7 else "8-bit symmetric per-channel weights (exact on VNNI/AMX CPUs only)")
    return ("ONNX Runtime static QDQ: input pinned to scale 1/255 (exact for 8-bit images), uint8 asymmetric "
            f"activations ({how} ranges on training images), {weights}")
