"""The deploy bundle (its files: :data:`pipeline.catalog.DEPLOY_BUNDLE`).

Writing it with its contract and golden pair, reading deploy.json, and a checkpoint's working resolution.
"""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path

import numpy as np
import torch

from pipeline.catalog import META_FILE, bundle_file
from pipeline.deploy.confidence import CONFIDENCE_BAND
from pipeline.deploy import quantize as q8
from pipeline.deploy.mask_path import (ONNX_INPUT, ONNX_OUTPUT, check_parity, export_onnx, export_torchscript,
                                    mask_path_model, onnx_unavailable_reason, require_parity, torch_logits)
from pipeline.runtime.errors import ArtifactError
from pipeline.model import count_flops, count_parameters
from pipeline.params import PAPER
from pipeline.thresholds import logit_threshold
from pipeline.artifacts.atomic import read_json
from pipeline.artifacts.weights import write_weights

__all__ = ["DEPLOY_JSON", "TORCHSCRIPT_FILE", "ONNX_FILE", "INT8_FILE", "CONTRACT_FILE", "GOLDEN_FILES",
           "CONTRACT_VERSION", "file_sha256", "write_bundle", "golden_frame", "write_contract", "frame_reading",
           "is_deploy_bundle", "read_deploy_info", "checkpoint_resolution"]

log = logging.getLogger(__name__)

#: the bundle's file names (pipeline.catalog.DEPLOY_BUNDLE)
DEPLOY_JSON = bundle_file("deploy_json")
TORCHSCRIPT_FILE = bundle_file("torchscript")
ONNX_FILE = bundle_file("onnx")
INT8_FILE = bundle_file("int8")
CONTRACT_FILE = bundle_file("contract")
GOLDEN_FILES = {k: bundle_file(f"golden_{k}") for k in ("input", "probs", "mask")}
#: the contract's version: a change of its meaning (not a new key) raises it
CONTRACT_VERSION = 1


def file_sha256(path: str | Path) -> str:
    """Hash a file.

    Parameters
    ----------
    path : str or Path
        The file.

    Returns
    -------
    str
        Its SHA-256, hexadecimal.
    """
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def write_bundle(tmp: str | Path, model, payload: dict, *, tau: float, tau_source: str, resolution: int,
                 opset: int, atol: float, onnx: bool = True, source: dict | None = None,
                 int8_settings: q8.Int8Settings, calibration_images: np.ndarray | None = None,
                 calibration_note: str | None = None, device=None, frames: dict | None = None) -> dict:
    """Fill the bundle folder ``tmp``: weights, TorchScript, ONNX, int8, contract, golden pair and deploy.json.

    The int8 model comes only with model.onnx and ``calibration_images`` (training split), and is left out when
    it misses ``int8_settings.int8_min_mask_iou`` on a checked instruction set (``int8_note`` says why).

    Parameters
    ----------
    tmp : str or Path
        The bundle folder being written (the caller makes it atomic).
    model : TinyUNet
        The student (its mask path is exported).
    payload : dict
        The checkpoint's payload (its method and seed are recorded).
    tau : float
        The mask threshold (eq:inference-mask).
    tau_source : str
        Where ``tau`` came from.
    resolution : int
        The working resolution.
    opset : int
        The ONNX opset (``deploy.opset``).
    atol : float
        The parity tolerance on the logits (``deploy.parity_atol``).
    onnx : bool
        Export ONNX (and so int8).
    source : dict or None
        deploy.json's ``source``: the checkpoint and fingerprints.
    int8_settings : Int8Settings
        The int8 calibration and its gate.
    calibration_images : np.ndarray or None
        uint8 [N,R,R,3] training-split images (never masks); None: no int8 model.
    calibration_note : str or None
        What the calibration images are, or why there are none.
    device : str or torch.device or None
        A CUDA device to report parity on as well.
    frames : dict or None
        How training frames were read (``data.bit_depth``, ``data.letterbox``; :func:`frame_reading`).

    Returns
    -------
    dict
        The deploy.json content.

    Raises
    ------
    ParityError
        TorchScript or ONNX does not reproduce the PyTorch mask path (:func:`pipeline.deploy.mask_path.require_parity`).
    """
    tmp = Path(tmp)
    deployed = mask_path_model(model)
    method, seed = payload.get("method"), payload.get("seed")
    write_weights(tmp, deployed.mask_path_state_dict(), deployed.config, None, method=method, seed=seed,
                  tau=float(tau), resolution=int(resolution))
    export_torchscript(deployed, tmp / TORCHSCRIPT_FILE, resolution)
    onnx_note = onnx_unavailable_reason() if onnx else "disabled"
    has_onnx = onnx_note is None
    if has_onnx:
        export_onnx(deployed, tmp / ONNX_FILE, resolution, opset)
    elif onnx:
        log.warning("export: %s", onnx_note)
    parity = check_parity(deployed, tau, resolution, atol, torchscript=tmp / TORCHSCRIPT_FILE,
                          onnx=tmp / ONNX_FILE if has_onnx else None, device=device)
    require_parity(parity)
    int8 = None
    if not has_onnx:
        int8_note = f"no {ONNX_FILE} ({onnx_note})"
    elif calibration_images is None or len(calibration_images) == 0:
        int8_note = calibration_note or "no calibration images given"
    else:
        q8.quantize_onnx_int8(tmp / ONNX_FILE, tmp / INT8_FILE, calibration_images, int8_settings)
        parity["int8"] = q8.check_int8_parity(deployed, tmp / INT8_FILE, calibration_images, tau,
                                              int8_settings.int8_min_mask_iou)
        int8_note = None
        if missed := [c for c in parity["int8"]["isas"] if c["passed"] is False]:  # the fp32 bundle still ships
            int8_note = q8.int8_miss({**parity["int8"], "mask_iou_mean": min(c["mask_iou_mean"] for c in missed)},
                                     ", ".join(c["isa"] for c in missed))
            (tmp / INT8_FILE).unlink()
            log.warning("export: int8 model left out: %s", int8_note)
        else:
            int8 = {"file": INT8_FILE, "calibration_images": int(len(calibration_images)),
                    "calibration": calibration_note or "training-split images (no masks)",
                    "calibration_method": int8_settings.int8_calibration,
                    "percentile": float(int8_settings.int8_percentile)
                    if int8_settings.int8_calibration == "percentile" else None,
                    "weight_bits": int8_settings.int8_weight_bits,
                    "quantization": q8.int8_description(int8_settings),
                    "verified_on": [c for c in parity["int8"]["isas"] if c["passed"]]}
    if int8_note is not None:
        log.info("export: int8 model skipped: %s", int8_note)
    write_contract(tmp, deployed, tau=tau, resolution=resolution, frames=frames, atol=atol,
                   onnx_file=ONNX_FILE if has_onnx else None, int8=int8, int8_note=int8_note)
    files = sorted(p.name for p in tmp.iterdir() if p.is_file())
    info = {
        "format_version": 1, "method": method, "seed": seed, "tau": float(tau), "tau_source": tau_source,
        "resolution": int(resolution), "frames": frame_reading(frames),
        "input": {"name": ONNX_INPUT, "dtype": "float32", "layout": "NCHW", "channels": "RGB",
                  "range": [0.0, 1.0], "size": "any (the model runs at the working resolution; "
                  "resize images to resolution x resolution with area interpolation)"},
        "output": {"name": ONNX_OUTPUT, "meaning": "mask logits Z [B,1,H,W]; mask = sigmoid(Z) >= tau "
                   "<=> Z >= logit(tau) (eq:inference-mask)", "logit_tau": logit_threshold(tau)},
        "config": dict(deployed.config), "params": count_parameters(deployed),
        "gflops": count_flops(deployed, resolution, resolution) / 1e9, "opset": int(opset) if has_onnx else None,
        "onnx_exporter": "torch.onnx.export(dynamo=False) (TorchScript-based)" if has_onnx else None,
        "onnx_note": onnx_note, "int8": int8, "int8_note": int8_note, "torch_version": torch.__version__,
        "parity": parity, "files": {f: file_sha256(tmp / f) for f in files}, "source": source or {},
    }
    (tmp / DEPLOY_JSON).write_text(json.dumps(info, indent=1, sort_keys=True))
    return info


def golden_frame(resolution: int) -> np.ndarray:
    """Draw the golden input: a lit ellipse with panels on a dark noisy background, seeded.

    Parameters
    ----------
    resolution : int
        R, its side.

    Returns
    -------
    np.ndarray
        RGB uint8 [R,R,3].
    """
    rng = np.random.default_rng(20261126)
    r = int(resolution)
    yy, xx = np.mgrid[0:r, 0:r] / max(r - 1, 1)
    body = ((yy - 0.5) / 0.22) ** 2 + ((xx - 0.5) / 0.14) ** 2 <= 1
    panels = (np.abs(yy - 0.5) < 0.06) & (np.abs(xx - 0.5) < 0.42)
    img = rng.normal(18, 6, (r, r, 3))
    img[panels] = [60, 80, 170]
    img[body] = 190 - 80 * xx[body][:, None] + rng.normal(0, 8, (int(body.sum()), 3))
    return np.clip(img, 0, 255).round().astype(np.uint8)


def write_contract(tmp: str | Path, deployed, *, tau: float, resolution: int, frames: dict | None = None,
                   atol: float = PAPER.deploy.parity_atol, onnx_file: str | None = ONNX_FILE, int8: dict | None = None,
                   int8_note: str | None = None) -> dict:
    """Write contract.json (enough to run model.onnx with numpy alone) and the golden pair (PyTorch fp32 on the CPU).

    Parameters
    ----------
    tmp : str or Path
        The bundle folder being written.
    deployed : TinyUNet
        The mask path (PyTorch, fp32, CPU) the golden pair comes from.
    tau : float
        The mask threshold (eq:inference-mask).
    resolution : int
        The working resolution R.
    frames : dict or None
        How frames are read (:func:`frame_reading`).
    atol : float
        The logits' parity tolerance (``deploy.parity_atol`` unless given), which bounds P's
        (|dP| <= |dZ| / 4).
    onnx_file : str or None
        The ONNX model's file name; None when the bundle has none.
    int8 : dict or None
        deploy.json's ``int8`` entry, when the bundle has the int8 model.
    int8_note : str or None
        Why it has none.

    Returns
    -------
    dict
        The contract written.
    """
    tmp = Path(tmp)
    r = int(resolution)
    frames = frame_reading(frames)
    golden = golden_frame(r)
    x = golden[None].transpose(0, 3, 1, 2).astype(np.float32) / np.float32(255.0)
    z = torch_logits(deployed, torch.from_numpy(x))[0, 0]
    probs = (1.0 / (1.0 + np.exp(-z.astype(np.float64)))).astype(np.float32)
    np.save(tmp / GOLDEN_FILES["input"], golden)
    np.save(tmp / GOLDEN_FILES["probs"], probs)
    np.save(tmp / GOLDEN_FILES["mask"], probs >= np.float32(tau))
    letterbox = frames["letterbox"]
    contract = {
        "contract_version": CONTRACT_VERSION,
        "model": {"onnx": onnx_file, "torchscript": TORCHSCRIPT_FILE, "weights": bundle_file("weights")},
        "frame_to_input": {
            "decode": "to RGB uint8 [H,W,3]: grey replicated to 3 channels, alpha dropped, BGR decoders' "
                      "channels reversed; float frames in [0,1] times 255, rounded",
            "bit_depth": frames["bit_depth"],
            "bit_depth_rule": "16-bit frames: auto or 16 -> round(v / 257); 10/12/14 -> round(min(v, 2**bits - 1) "
                              "* 255 / (2**bits - 1)); 8-bit frames as they are",
            "aspect": "letterbox" if letterbox else "squash",
            "aspect_rule": ("pad to a square side = max(H, W) with zeros (black), the frame at rows "
                            "(side - H) // 2 and columns (side - W) // 2, then resize" if letterbox
                            else "resize the whole frame to a square, ignoring its aspect ratio"),
            "resize": f"to {r} x {r} with area interpolation (OpenCV INTER_AREA)",
        },
        "input": {"name": ONNX_INPUT, "dtype": "float32", "layout": "NCHW", "shape": ["N", 3, r, r],
                  "channel_order": "RGB", "normalisation": "x = uint8 / 255 (no mean or std: the model "
                  "folds its own normalisation into its first convolution)", "range": [0.0, 1.0]},
        "output": {"name": ONNX_OUTPUT, "dtype": "float32", "shape": ["N", 1, r, r],
                   "meaning": "mask logits Z; P = sigmoid(Z) is the probability that a pixel is spacecraft; "
                              "the mask is P >= tau, i.e. Z >= logit_tau (eq:inference-mask)",
                   "tau": float(tau), "logit_tau": logit_threshold(tau),
                   "back_to_frame": ("resize P bilinearly to side x side, crop the pad, then threshold" if letterbox
                                     else "resize P bilinearly (OpenCV INTER_LINEAR) to H x W, then threshold")},
        "confidence": {"band": CONFIDENCE_BAND, "range": [0.0, 1.0],
                       "definition": "at the working resolution: m = (P - tau) / (1 - tau) where P >= tau, "
                                     "(tau - P) / tau elsewhere; score = mean of m over the mask [P >= tau] "
                                     "grown by `band` pixels (square neighbourhood), or over the whole frame "
                                     "when the mask is empty; low = do not trust this frame (it ranks frames, "
                                     "it is not a probability of being right)"},
        "int8": ({"model": int8["file"], "quantization": int8["quantization"], "verified_on": int8["verified_on"],
                  "rule": "masks agree with the golden pair's within the int8 gate (mean mask IoU), on every "
                          "instruction set listed"} if int8 else {"model": None, "why": int8_note}),
        "golden": {"input": GOLDEN_FILES["input"], "input_meaning": f"RGB uint8 [{r},{r},3], already at the "
                   "working resolution (no resize)", "probabilities": GOLDEN_FILES["probs"],
                   "mask": GOLDEN_FILES["mask"], "atol_probabilities": float(atol),
                   "mask_rule": "equal to P >= tau except where |P - tau| <= atol_probabilities",
                   "reference": "PyTorch fp32 on the CPU"},
    }
    (tmp / CONTRACT_FILE).write_text(json.dumps(contract, indent=1, sort_keys=True))
    return contract


def frame_reading(frames: dict | None = None) -> dict:
    """Complete deploy.json's ``frames``: an absent key as older bundles were made, before the key existed.

    Parameters
    ----------
    frames : dict or None
        ``bit_depth`` and ``letterbox``, either or both.

    Returns
    -------
    dict
        Both keys; an absent one takes its schema default (``data.bit_depth``, ``data.letterbox``: what every
        bundle made before the key was recorded used).
    """
    frames = frames or {}
    return {"bit_depth": frames.get("bit_depth", PAPER.data.bit_depth),
            "letterbox": bool(frames.get("letterbox", PAPER.data.letterbox))}


def is_deploy_bundle(path: str | Path) -> bool:
    """Whether ``path`` holds a deploy bundle: its meta.json records the ``deploy`` schema.

    The one bundle check of export (what it may replace) and of the engines (a bundle or a checkpoint folder).

    Parameters
    ----------
    path : str or Path
        A folder (it need not exist).

    Returns
    -------
    bool
        True for a deploy bundle.
    """
    return read_json(Path(path) / META_FILE).get("schema") == "deploy"


def read_deploy_info(path: str | Path) -> dict:
    """Read a bundle's deploy.json.

    Parameters
    ----------
    path : str or Path
        The bundle folder.

    Returns
    -------
    dict
        The deploy.json content.

    Raises
    ------
    ArtifactError
        There is no deploy.json, or it is unreadable.
    """
    p = Path(path) / DEPLOY_JSON
    try:
        return json.loads(p.read_text())
    except FileNotFoundError:
        raise ArtifactError(f"{path}: not a deploy bundle (no {DEPLOY_JSON})") from None
    except (OSError, ValueError) as e:
        raise ArtifactError(f"{p}: unreadable ({type(e).__name__})") from None


def checkpoint_resolution(path: str | Path, payload: dict) -> int | None:
    """Read the working resolution recorded with a checkpoint.

    Parameters
    ----------
    path : str or Path
        The checkpoint folder (its meta.json's ``extra``).
    payload : dict
        The checkpoint's payload, read first.

    Returns
    -------
    int or None
        Its ``resolution`` (or older ``image_size``), else None.
    """
    for record in (payload, read_json(Path(path) / META_FILE).get("extra") or {}):
        for key in ("resolution", "image_size"):
            if isinstance(record.get(key), int):
                return int(record[key])
    return None
