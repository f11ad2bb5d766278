"""Stage export: the deployed mask path of one checkpoint with its calibrated tau -> artifacts/deploy/
(TorchScript, ONNX, int8 calibrated on training images; pipeline.deploy.export)."""

from __future__ import annotations

import click

from pipeline.catalog import dvc_path
from pipeline.runtime.device import resolve_device
from pipeline.deploy.bundle import is_deploy_bundle
from pipeline.deploy.export import bundle_files, export_lines, plan_export, write_export
from pipeline.artifacts.ownership import refuse_foreign_files, refuse_unowned
from stages._common import overwrite_option, stage_command, stage_context


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
    replaced whole when it holds an earlier bundle (its meta.json) and nothing else; a folder without
    a bundle is refused unless --overwrite, and a file in it that is not a bundle's is always refused."""
    refuse_unowned([out], [out] if is_deploy_bundle(out) else [], command="export", option="--out", where=out,
                   why="no deploy bundle's meta.json in it", overwrite=overwrite)
    # the bundle is swapped in whole: a file in it that no earlier bundle lists is refused, never lost
    refuse_foreign_files(out, bundle_files(out), command="export", option="--out", where=out,
                         why="not a file of the deploy bundle there, which export replaces whole")
    plan = plan_export(checkpoint, params, thresholds=thresholds, tau=tau, artifacts=art, onnx=not no_onnx,
                       int8=not no_int8)
    meta = stage_context("export", __file__, params).meta("deploy", plan.inputs, params=plan.params)
    info = write_export(plan, out, meta, device=resolve_device(device))
    for line in export_lines(plan, info, out):
        click.echo(line, err=True)


if __name__ == "__main__":
    main()
