"""The export stage's logic: one checkpoint -> its deploy bundle.

The bundle is written atomically with its parity checks first (a failure leaves nothing behind), and
:func:`export_lines` says what export prints about it.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Mapping

from pipeline.artifacts.atomic import read_json
from pipeline.artifacts.store import artifact_dir, open_artifact
from pipeline.catalog import META_FILE, bundle_file
from pipeline.evaluation.inference import load_student
from pipeline.params import section
from pipeline.thresholds import resolve_resolution, resolve_tau, tau_candidates

__all__ = ["bundle_files", "ExportPlan", "plan_export", "write_export", "export_lines"]


def bundle_files(path) -> set[str]:
    """List the files of the deploy bundle in ``path``: what export may replace there.

    Parameters
    ----------
    path : str or Path
        A folder.

    Returns
    -------
    set of str
        The files deploy.json lists, deploy.json and meta.json; empty when ``path`` holds no bundle.
    """
    from pipeline.deploy.bundle import is_deploy_bundle  # torch

    if not is_deploy_bundle(path):
        return set()
    listed = read_json(Path(path) / bundle_file("deploy_json")).get("files") or {}
    return {str(f) for f in listed} | {bundle_file("deploy_json"), META_FILE}


@dataclasses.dataclass
class ExportPlan:
    """What :func:`write_export` writes, decided by :func:`plan_export` before anything is written.

    Attributes
    ----------
    model : torch.nn.Module
        The student, on the CPU.
    payload : dict
        The checkpoint's payload.
    source : dict
        deploy.json's ``source`` (checkpoint, its fingerprint, epoch, stage, thresholds), less the bundle's
        fingerprint.
    tau : float
        The threshold the bundle records (eq:inference-mask).
    tau_source : str
        Where ``tau`` came from.
    resolution : int
        The working resolution.
    resolution_source : str
        Where ``resolution`` came from.
    onnx : bool
        Whether to export ONNX.
    calibration_images : numpy.ndarray or None
        The int8 calibration images; None: no int8 model.
    calibration_note : str or None
        Why there are no calibration images.
    settings : dict
        ``write_bundle``'s keyword arguments (opset, parity tolerance, int8 settings, frame reading).
    inputs : list
        The artifacts read, for the fingerprint.
    params : dict
        The fingerprinted params.
    """

    model: Any
    payload: dict
    source: dict            # deploy.json's ``source``, less the bundle's fingerprint
    tau: float
    tau_source: str
    resolution: int
    resolution_source: str
    onnx: bool
    calibration_images: Any
    calibration_note: str | None
    settings: dict          # write_bundle's keyword arguments
    inputs: list
    params: dict


def plan_export(checkpoint, params: Mapping, *, thresholds=None, tau: float | None = None, artifacts=None,
                onnx: bool = True, int8: bool = True) -> ExportPlan:
    """Decide everything export writes, before writing.

    tau: ``tau`` > the payload's > ``thresholds`` > the fixed tau (eq:inference-mask); the resolution: the
    checkpoint's recorded one, else ``data.resolution``; the int8 calibration images: the training split of
    ``artifacts``, read only when ONNX and int8 are on and onnxruntime is installed.

    Parameters
    ----------
    checkpoint : str or Path
        The checkpoint artifact.
    params : mapping
        Validated params (``deploy``, ``data``, ``calibrate`` sections).
    thresholds : str or Path, optional
        The thresholds table (read only when ``tau`` is None).
    tau : float, optional
        An explicit threshold.
    artifacts : str or Path, optional
        The artifacts folder whose training images calibrate the int8 model.
    onnx : bool, optional
        Export ONNX (default True).
    int8 : bool, optional
        Export the int8 model (default True).

    Returns
    -------
    ExportPlan
        The plan.

    Raises
    ------
    InputError
        No tau or resolution is found, or one is invalid.
    ArtifactError
        The checkpoint or thresholds table is missing or invalid.
    """
    from pipeline.deploy.bundle import checkpoint_resolution, frame_reading  # torch
    from pipeline.deploy.mask_path import onnx_unavailable_reason
    from pipeline.deploy.quantize import Int8Settings, read_calibration_images

    cfg = section(params, "deploy")
    int8_settings = Int8Settings.from_params(cfg)
    ckpt = open_artifact(checkpoint, "checkpoint")
    model, payload = load_student(checkpoint, "cpu")
    table = open_artifact(thresholds, "thresholds") if thresholds is not None and tau is None else None
    inputs = [ckpt] + ([table] if table is not None else [])
    value, source = resolve_tau(option=tau, **tau_candidates(payload=payload, thresholds=table, params=params))
    resolution, res_source = resolve_resolution(recorded=(checkpoint_resolution(checkpoint, payload), "checkpoint"),
                                                params=params["data"]["resolution"])
    calib, calib_note = None, None
    if not onnx or not int8:
        calib_note = "--no-onnx" if not onnx else "--no-int8"
    elif artifacts is None:
        calib_note = "no --artifacts given (training images calibrate the int8 model)"
    elif (reason := onnx_unavailable_reason()) is not None:
        calib_note = reason
    else:
        calib, calib_inputs, calib_note = read_calibration_images(artifacts, int8_settings.int8_calibration_images,
                                                                  int(resolution))
        inputs += calib_inputs
    frames = frame_reading({k: params["data"][k] for k in ("bit_depth", "letterbox")})  # validated: both there
    settings = {"opset": cfg["opset"], "atol": cfg["parity_atol"], "int8_settings": int8_settings, "frames": frames}
    deploy_params = {"opset": cfg["opset"], "parity_atol": cfg["parity_atol"], "onnx": onnx, "int8": calib is not None,
                     **dataclasses.asdict(int8_settings)}
    fingerprinted = {"deploy": deploy_params, "tau": value, "tau_source": source, "resolution": int(resolution)}
    if frames != frame_reading():  # only when set: earlier bundles' fingerprints stay
        fingerprinted["frames"] = frames
    origin = {"checkpoint": str(checkpoint), "checkpoint_fingerprint": ckpt.fingerprint,
              "selected_epoch": payload.get("selected_epoch"), "stage": payload.get("stage"),
              "thresholds": str(thresholds) if thresholds else None, "resolution_source": res_source}
    return ExportPlan(model, payload, origin, value, source, int(resolution), res_source, onnx, calib, calib_note,
                      settings, inputs, fingerprinted)


def write_export(plan: ExportPlan, out, meta, device=None) -> dict:
    """Write the bundle of ``plan`` to ``out``, replaced whole.

    Parameters
    ----------
    plan : ExportPlan
        From :func:`plan_export`.
    out : str or Path
        The bundle's folder.
    meta : pipeline.artifacts.lineage.Meta
        The bundle's metadata (its fingerprint is recorded in deploy.json).
    device : str or torch.device, optional
        A device for the parity check besides the CPU.

    Returns
    -------
    dict
        The deploy.json content.
    """
    from pipeline.deploy.bundle import write_bundle  # torch

    with artifact_dir(out, meta) as tmp:
        return write_bundle(tmp, plan.model, plan.payload, tau=plan.tau, tau_source=plan.tau_source,
                            resolution=plan.resolution, onnx=plan.onnx,
                            source={**plan.source, "bundle_fingerprint": meta.fingerprint},
                            calibration_images=plan.calibration_images, calibration_note=plan.calibration_note,
                            device=device, **plan.settings)


def export_lines(plan: ExportPlan, info: Mapping, out) -> list[str]:
    """Say what export prints about the bundle it wrote.

    Parameters
    ----------
    plan : ExportPlan
        The plan written.
    info : mapping
        The deploy.json content (:func:`write_export`).
    out : str or Path
        The bundle's folder.

    Returns
    -------
    list of str
        The summary with parity figures, the ONNX note, device parity and the int8 model's line.
    """
    from pipeline.deploy.bundle import INT8_FILE

    par = info["parity"]
    summary = ", ".join(f"{fmt}: max|dZ|={par[fmt]['max_abs_diff']:.2e}, masks identical={par[fmt]['masks_identical']}"
                        for fmt in ("torchscript", "onnx") if fmt in par)
    lines = [f"export: {plan.payload.get('method')} seed {plan.payload.get('seed')}, tau={plan.tau:.4g}, "
             f"{plan.resolution}px -> {out} ({summary})"]
    if info.get("onnx_note") and plan.onnx:
        lines.append(f"export: {info['onnx_note']}")
    for name, d in (par.get("device") or {}).items():
        if isinstance(d, dict):
            lines.append(f"export: parity on {par['device']['device']}: {name} max|dZ|={d['max_abs_diff']:.2e}, "
                         f"mask IoU vs fp32 {d['mask_iou']:.4f}")
    if "int8" in par and info.get("int8"):
        q = par["int8"]
        lines.append(f"export: int8 model {INT8_FILE}: {q['images']} calibration images, "
                     f"max|dZ|={q['max_abs_diff']:.3g}, mask IoU vs PyTorch mean {q['mask_iou_mean']:.4f} "
                     f"(gate {q['min_mask_iou']:g}), min {q['mask_iou_min']:.4f}")
    else:
        lines.append(f"export: int8 model skipped: {info['int8_note']}")
    return lines
