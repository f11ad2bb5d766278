"""Stage export: the deployed mask path of one checkpoint -> artifacts/deploy/ (TorchScript, ONNX, tau).

tau is the validation-calibrated threshold of the checkpoint's (method, seed) in thresholds.parquet
(eq:inference-mask).  Fallback, recorded as ``tau_source`` in deploy.json with a warning: without
``--thresholds`` or without a row for that run, ``calibrate.fixed_tau`` (the paper's fixed-threshold
setting, 0.5); ``--tau`` overrides both.  The working resolution comes from the checkpoint when it
records one, else ``data.resolution``.  The parity check (pipeline.deploy.check_parity) runs here and a
failure stops the stage before anything is written.  ONNX needs the ``onnx`` extra; without it the
bundle holds TorchScript only and deploy.json says why.
"""

from __future__ import annotations

import logging

import click

from pipeline.params import require, section
from stages._common import meta_for, stage_code_version, stage_command

CODE_MODULES = ("deploy.py", "model.py", "inference.py", "artifacts.py")
log = logging.getLogger("geodistill.export")


@stage_command("export")
@click.option("--checkpoint", required=True, type=click.Path(), help="checkpoint dir artifacts/checkpoints/<method>/<seed>")
@click.option("--thresholds", default=None, type=click.Path(dir_okay=False),
              help="thresholds.parquet with the calibrated tau (default: fall back to calibrate.fixed_tau)")
@click.option("--tau", type=float, default=None, help="override tau (recorded as the tau source)")
@click.option("--out", default="artifacts/deploy", show_default=True, type=click.Path(file_okay=False))
@click.option("--no-onnx", is_flag=True, help="write TorchScript only")
def main(params, device, checkpoint, thresholds, tau, out, no_onnx):
    """Export the mask path (TorchScript + ONNX) with its calibrated tau and a parity check."""
    from pipeline import deploy
    from pipeline.artifacts import artifact_dir, open_artifact
    from pipeline.errors import InputError
    from pipeline.inference import is_active_run, load_student

    cfg = section(params, "deploy")
    opset = require(cfg, "opset", "deploy", kind=int, lo=9, hi=30)
    atol = float(require(cfg, "parity_atol", "deploy", kind=(int, float), lo=0.0))
    if not is_active_run(checkpoint):
        raise InputError(f"--checkpoint {checkpoint}: inactive in this profile (no trained model); "
                         f"choose an active run with deploy.export_method / deploy.export_seed")
    ckpt = open_artifact(checkpoint, "checkpoint")
    model, payload = load_student(checkpoint, "cpu")
    method, seed = payload.get("method"), payload.get("seed")
    inputs = [ckpt]
    if tau is not None:
        tau, tau_source = deploy.check_tau(tau, "--tau"), "--tau"
    else:
        found = None
        if thresholds is not None:
            table = open_artifact(thresholds, "thresholds")
            inputs.append(table)
            found = deploy.lookup_tau(table.df, method, seed)
        if found is not None:
            tau, tau_source = found, f"calibrated on the validation split ({thresholds}: {method}, seed {seed})"
        else:
            tau = deploy.check_tau(require(section(params, "calibrate"), "fixed_tau", "calibrate"), "calibrate.fixed_tau")
            tau_source = (f"calibrate.fixed_tau (no calibrated row for {method} seed {seed} in {thresholds})"
                          if thresholds else "calibrate.fixed_tau (no --thresholds given)")
            log.warning("export: tau = %s from %s", tau, tau_source)
    resolution = deploy.checkpoint_resolution(checkpoint, payload)
    res_source = "checkpoint"
    if resolution is None:
        resolution = require(section(params, "data"), "resolution", "data", kind=int, lo=8)
        res_source = "data.resolution"

    code = stage_code_version(__file__, *CODE_MODULES)
    meta = meta_for("deploy", "export", code,
                    {"deploy": {"opset": opset, "parity_atol": atol, "onnx": not no_onnx},
                     "tau": tau, "tau_source": tau_source, "resolution": int(resolution)}, inputs)
    source = {"checkpoint": str(checkpoint), "checkpoint_fingerprint": ckpt.fingerprint,
              "selected_epoch": payload.get("selected_epoch"), "stage": payload.get("stage"),
              "thresholds": str(thresholds) if thresholds else None, "resolution_source": res_source,
              "bundle_fingerprint": meta.fingerprint}
    with artifact_dir(out, meta) as tmp:
        info = deploy.write_bundle(tmp, model, payload, tau=tau, tau_source=tau_source, resolution=int(resolution),
                                   opset=opset, atol=atol, onnx=not no_onnx, source=source)
    par = info["parity"]
    summary = ", ".join(f"{fmt}: max|dZ|={par[fmt]['max_abs_diff']:.2e}, masks identical={par[fmt]['masks_identical']}"
                        for fmt in ("torchscript", "onnx") if fmt in par)
    click.echo(f"export: {method} seed {seed}, tau={tau:.4g}, {resolution}px -> {out} ({summary})", err=True)
    if info.get("onnx_note") and not no_onnx:
        click.echo(f"export: {info['onnx_note']}", err=True)


if __name__ == "__main__":
    main()
