"""The deploy bundle: writing and reading it (deploy.json), and a checkpoint's working resolution.

Deploy bundle (directory artifact, schema ``deploy``; its layout, one table: pipeline.catalog.DEPLOY_BUNDLE)::

    model.safetensors + model.json  mask-path weights; config, method, seed, tau, resolution
                  -- the checkpoint format (pipeline.weights), so pipeline.inference.load_student() opens
                  the bundle too (bundles of older versions hold model.pt instead; still read)
    model.ts      TorchScript (traced) mask path; shape-generic (any batch and size)
    model.onnx    ONNX mask path, dynamic batch/height/width (only when onnx + onnxruntime import)
                  -- both traced from pipeline.model.ExportMaskPath (pipeline.deploy.export)
    model.int8.onnx  static int8 (QDQ) quantisation of model.onnx, calibrated on training-split images
                  (only when model.onnx exists and training images are given; the CPU fast path;
                  pipeline.deploy.quantize)
    deploy.json   tau (+ where it came from, pipeline.thresholds.resolve_tau), working resolution, model
                  config, parameters, GFLOPs, exporter, parity results (int8: agreement report), file
                  sha256s, source checkpoint and its fingerprint, the int8 file and its calibration image
                  count (or why skipped)
    meta.json     artifact metadata (fingerprint, lineage)
"""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path

import numpy as np

from pipeline.catalog import bundle_file
from pipeline.deploy import quantize as q8
from pipeline.deploy.export import (ONNX_INPUT, ONNX_OUTPUT, check_parity, export_onnx, export_torchscript,
                                    mask_path_model, onnx_unavailable_reason, require_parity)
from pipeline.errors import ArtifactError
from pipeline.model import count_flops, count_parameters
from pipeline.thresholds import logit_threshold
from pipeline.weights import write_weights

log = logging.getLogger(__name__)

#: the bundle's files as its writer and readers name them (the layout: pipeline.catalog.DEPLOY_BUNDLE)
DEPLOY_JSON = bundle_file("deploy_json")
TORCHSCRIPT_FILE = bundle_file("torchscript")
ONNX_FILE = bundle_file("onnx")
INT8_FILE = bundle_file("int8")


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
                 int8_percentile: float = 99.999, device=None) -> dict:
    """Fill a deploy bundle directory ``tmp`` (module docstring) and return its deploy.json content.

    Raises :class:`ParityError` when an exported format fails its parity check, and InputError when
    the int8 model's mean mask IoU against PyTorch is below ``int8_min_mask_iou``.  ``onnx=False`` (or
    onnx/onnxruntime missing) writes no model.onnx and records why in deploy.json.  model.int8.onnx
    is written when model.onnx exists and ``calibration_images`` (uint8 [N,R,R,3], training split,
    no masks) are given; otherwise ``int8_note`` says why not (``calibration_note`` when the caller
    found no images).
    """
    import torch

    tmp = Path(tmp)
    deployed = mask_path_model(model)
    method, seed = payload.get("method"), payload.get("seed")
    write_weights(tmp, deployed.mask_path_state_dict(), deployed.config, None, method=method, seed=seed,
                  tau=float(tau), resolution=int(resolution))
    export_torchscript(deployed, tmp / TORCHSCRIPT_FILE, resolution)
    onnx_note = None if onnx else "disabled"
    if onnx and (reason := onnx_unavailable_reason()) is None:
        export_onnx(deployed, tmp / ONNX_FILE, resolution, opset)
    elif onnx:
        onnx_note = reason
        log.warning("export: %s", reason)
    has_onnx = (tmp / ONNX_FILE).exists()
    parity = check_parity(deployed, tau, resolution, atol, torchscript=tmp / TORCHSCRIPT_FILE,
                          onnx=tmp / ONNX_FILE if has_onnx else None, device=device)
    require_parity(parity)
    int8 = None
    if not has_onnx:
        int8_note = f"no {ONNX_FILE} ({onnx_note})"
    elif calibration_images is None or len(calibration_images) == 0:
        int8_note = calibration_note or "no calibration images given"
    else:
        q8.quantize_onnx_int8(tmp / ONNX_FILE, tmp / INT8_FILE, calibration_images, int8_calibration, int8_percentile)
        parity["int8"] = q8.check_int8_parity(deployed, tmp / INT8_FILE, calibration_images, tau, int8_min_mask_iou)
        q8.require_int8_agreement(parity["int8"])
        int8_note = None
        int8 = {"file": INT8_FILE, "calibration_images": int(len(calibration_images)),
                "calibration": calibration_note or "training-split images (no masks)",
                "calibration_method": int8_calibration,
                "percentile": float(int8_percentile) if int8_calibration == "percentile" else None,
                "quantization": q8.int8_description(int8_calibration, int8_percentile)}
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
