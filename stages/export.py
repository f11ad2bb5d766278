"""Stage export: the deployed mask path of one checkpoint -> artifacts/deploy/ (TorchScript, ONNX, tau).

tau is the validation-calibrated threshold of the checkpoint's (method, seed) in thresholds.parquet
(eq:inference-mask).  Fallback, recorded as ``tau_source`` in deploy.json with a warning: without
``--thresholds`` or without a row for that run, ``calibrate.fixed_tau`` (the paper's fixed-threshold
setting, 0.5); ``--tau`` overrides both (pipeline.thresholds.resolve_tau).  The working resolution comes from the checkpoint when it
records one, else ``data.resolution``.  The parity check (pipeline.deploy.check_parity) runs here and a
failure stops the stage before anything is written.  ONNX needs the ``onnx`` extra; without it the
bundle holds TorchScript only and deploy.json says why.

int8: with ``--artifacts DIR`` (manifest.parquet + images.zarr), up to ``deploy.int8_calibration_images``
TRAINING-split images (images only, never reference masks) calibrate a static int8 ONNX model,
``model.int8.onnx`` (pipeline.deploy.quantize_onnx_int8, the same code the benchmark uses; ranges by
``deploy.int8_calibration`` / ``deploy.int8_percentile``).  Its agreement with PyTorch on those images
(max |dZ|, per-image mask IoU at tau) goes into deploy.json; the stage fails only when the mean mask
IoU is below ``deploy.int8_min_mask_iou``.  Without onnx, without
the artifacts, or with ``--no-int8`` the bundle has no int8 model and deploy.json (and stderr) say why.
"""

from __future__ import annotations

import json
from pathlib import Path

import click

from pipeline.artifacts import artifact_dir, open_artifact
from pipeline.catalog import dvc_path
from pipeline.device import resolve_device
from pipeline.inference import load_student
from pipeline.ownership import refuse_unowned
from pipeline.params import section
from pipeline.thresholds import lookup_tau, lookup_tau_source, resolve_resolution, resolve_tau
from stages._common import overwrite_option, stage_command, stage_context


def is_bundle_dir(path) -> bool:
    """Whether ``path`` is a folder holding a deploy artifact's meta.json (export's own output)."""
    try:
        return json.loads((Path(path) / "meta.json").read_text()).get("schema") == "deploy"
    except (OSError, ValueError, AttributeError):
        return False


@stage_command("export")
@click.option("--checkpoint", required=True, type=click.Path(), help="checkpoint dir artifacts/checkpoints/<method>/<seed>")
@click.option("--thresholds", default=None, type=click.Path(dir_okay=False),
              help="thresholds.parquet with the calibrated tau (default: fall back to calibrate.fixed_tau)")
@click.option("--tau", type=float, default=None, help="override tau (recorded as the tau source)")
@click.option("--out", default=dvc_path("deploy"), show_default=True, type=click.Path(file_okay=False))
@click.option("--artifacts", "art", default=None, type=click.Path(file_okay=False),
              help="folder with manifest.parquet + images.zarr: training images calibrate model.int8.onnx "
                   "(default: no int8 model)")
@click.option("--no-onnx", is_flag=True, help="write TorchScript only")
@click.option("--no-int8", is_flag=True, help="skip the int8 ONNX model")
@overwrite_option
def main(params, device, checkpoint, thresholds, tau, out, art, no_onnx, no_int8, overwrite):
    """Export the mask path (TorchScript + ONNX) with its calibrated tau and a parity check.  --out is
    replaced whole when it holds an earlier bundle (its meta.json); anything else there is refused
    unless --overwrite."""
    from pipeline import deploy  # torch: this module stays torch-free at import (--help)

    refuse_unowned([out], [out] if is_bundle_dir(out) else [], command="export", option="--out", where=out,
                   why="no deploy bundle's meta.json in it", overwrite=overwrite)
    cfg = section(params, "deploy")
    opset, atol = cfg["opset"], cfg["parity_atol"]
    n_calib, min_iou = cfg["int8_calibration_images"], cfg["int8_min_mask_iou"]
    q8 = deploy.int8_params(cfg)
    ckpt = open_artifact(checkpoint, "checkpoint")
    model, payload = load_student(checkpoint, "cpu")
    method, seed = payload.get("method"), payload.get("seed")
    inputs = [ckpt]
    table = open_artifact(thresholds, "thresholds") if thresholds is not None and tau is None else None
    inputs += [table] if table is not None else []
    found = lookup_tau(table.df, method, seed) if table is not None else None
    how = (lookup_tau_source(table.df, method, seed) if table is not None else None) or "calibrated on the validation split"
    tau, tau_source = resolve_tau(
        option=tau,
        thresholds=(found, f"{how} ({thresholds}: {method}, seed {seed})"),
        fixed=(section(params, "calibrate").get("fixed_tau"),
               f"calibrate.fixed_tau (no calibrated row for {method} seed {seed} in {thresholds})"
               if thresholds else "calibrate.fixed_tau (no --thresholds given)"))
    resolution, res_source = resolve_resolution(recorded=(deploy.checkpoint_resolution(checkpoint, payload), "checkpoint"),
                                                params=params["data"]["resolution"])

    calib, calib_note = None, None
    if no_onnx or no_int8:
        calib_note = "--no-onnx" if no_onnx else "--no-int8"
    elif art is None:
        calib_note = "no --artifacts given (training images calibrate the int8 model)"
    elif (reason := deploy.onnx_unavailable_reason()) is not None:
        calib_note = reason
    else:
        calib, calib_inputs, calib_note = deploy.read_calibration_images(art, n_calib, int(resolution))
        inputs += calib_inputs

    deploy_params = {"opset": opset, "parity_atol": atol, "onnx": not no_onnx, "int8": calib is not None,
                     "int8_calibration_images": n_calib, "int8_min_mask_iou": min_iou,
                     "int8_calibration": q8["calibration"], "int8_percentile": q8["percentile"]}
    meta = stage_context("export", __file__, params).meta(
        "deploy", inputs, params={"deploy": deploy_params, "tau": tau, "tau_source": tau_source,
                                  "resolution": int(resolution)})
    source = {"checkpoint": str(checkpoint), "checkpoint_fingerprint": ckpt.fingerprint,
              "selected_epoch": payload.get("selected_epoch"), "stage": payload.get("stage"),
              "thresholds": str(thresholds) if thresholds else None, "resolution_source": res_source,
              "bundle_fingerprint": meta.fingerprint}
    with artifact_dir(out, meta) as tmp:
        info = deploy.write_bundle(tmp, model, payload, tau=tau, tau_source=tau_source, resolution=int(resolution),
                                   opset=opset, atol=atol, onnx=not no_onnx, source=source,
                                   calibration_images=calib, calibration_note=calib_note,
                                   int8_min_mask_iou=min_iou, int8_calibration=q8["calibration"],
                                   int8_percentile=q8["percentile"], device=resolve_device(device))
    par = info["parity"]
    summary = ", ".join(f"{fmt}: max|dZ|={par[fmt]['max_abs_diff']:.2e}, masks identical={par[fmt]['masks_identical']}"
                        for fmt in ("torchscript", "onnx") if fmt in par)
    click.echo(f"export: {method} seed {seed}, tau={tau:.4g}, {resolution}px -> {out} ({summary})", err=True)
    if info.get("onnx_note") and not no_onnx:
        click.echo(f"export: {info['onnx_note']}", err=True)
    for name, d in (par.get("device") or {}).items():
        if isinstance(d, dict):
            click.echo(f"export: parity on {par['device']['device']}: {name} max|dZ|={d['max_abs_diff']:.2e}, "
                       f"mask IoU vs fp32 {d['mask_iou']:.4f}", err=True)
    if "int8" in par:
        q = par["int8"]
        click.echo(f"export: int8 model {deploy.INT8_FILE}: {q['images']} calibration images, "
                   f"max|dZ|={q['max_abs_diff']:.3g}, mask IoU vs PyTorch mean {q['mask_iou_mean']:.4f} "
                   f"(gate {q['min_mask_iou']:g}), min {q['mask_iou_min']:.4f}", err=True)
    else:
        click.echo(f"export: int8 model skipped: {info['int8_note']}", err=True)


if __name__ == "__main__":
    main()
