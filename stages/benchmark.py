"""Stage benchmark: latency, throughput, memory and IoU change of the deployed mask path's variants on this
machine (pipeline.deploy.benchmark; reference masks only measure accuracy)."""

from __future__ import annotations

import tempfile
from pathlib import Path

import click

from pipeline.artifacts.atomic import write_json
from pipeline.artifacts.store import write_parquet
from pipeline.catalog import ARTIFACTS_DIR, dvc_path
from pipeline.runtime.device import resolve_device
from pipeline.report.dvc_results import deploy_metrics
from pipeline.runtime.errors import InputError
from pipeline.params import section
from pipeline.thresholds import resolve_resolution
from stages._common import stage_command, stage_context


@stage_command("benchmark")
@click.option("--deploy", "deploy_dir", default=None, type=click.Path(file_okay=False),
              help="deploy bundle (geodistill export); or use --checkpoint")
@click.option("--checkpoint", default=None, type=click.Path(file_okay=False), help="checkpoint dir instead of a bundle")
@click.option("--artifacts", "art", default=ARTIFACTS_DIR, show_default=True, type=click.Path(file_okay=False),
              help="manifest/images/reference for the IoU check and int8 calibration (optional standalone)")
@click.option("--thresholds", default=dvc_path("thresholds"), show_default=True,
              help="with --checkpoint: where to find its calibrated tau")
@click.option("--tau", type=float, default=None, help="override the deployed tau")
@click.option("--resolution", type=int, default=None, help="time at this size (default: deploy.benchmark_resolution "
              "or the bundle's working resolution); IoU is always measured on images.zarr")
@click.option("--out", default=None, type=click.Path(dir_okay=False), help="efficiency.parquet to write")
@click.option("--json", "json_out", default=None, type=click.Path(dir_okay=False),
              help="JSON results to write (every variant, the run's settings and notes)")
@click.option("--metrics-json", default=None, type=click.Path(dir_okay=False),
              help="DVC metrics file to write: latency_ms of the deployed fast path (dvc.yaml: reports/metrics/deploy.json)")
def main(params, device, deploy_dir, checkpoint, art, thresholds, tau, resolution, out, json_out, metrics_json):
    """Latency, throughput, memory and IoU change of the deployed mask path's variants."""
    from pipeline.deploy import benchmark as B
    cfg = section(params, "deploy")
    st = B.benchmark_settings(cfg)
    target = B.open_target(deploy_dir, checkpoint, thresholds, tau, params)
    resolution, _ = resolve_resolution(option=resolution, benchmark=st["resolution"], recorded=target.resolution,
                                       params=section(params, "data").get("resolution"))
    val_images, val_masks, calib, data_inputs = B.read_benchmark_data(
        Path(art), st["int8_settings"].int8_calibration_images)
    notes = {} if val_images is not None else {
        "iou": f"no validation images with reference masks under {art}: IoU columns not computed"}
    with tempfile.TemporaryDirectory() as td:
        onnx_path, int8_path, onnx_notes = B.prepare_onnx_models(
            target, st["variants"], td, resolution=resolution, opset=st["opset"], calibration_images=calib,
            int8_settings=st["int8_settings"])
        notes.update(onnx_notes)
        for key in ("iou", "onnx"):
            if key in notes:
                click.echo(f"benchmark: {notes[key]}", err=True)
        rows, run_info = B.measure_variants(
            target.model, resolution=resolution, device=resolve_device(device), variants=st["variants"],
            warmup=st["warmup"], iters=st["iters"], batches=st["batches"], tau=target.tau, val_images=val_images,
            val_masks=val_masks, onnx_path=onnx_path, int8_path=int8_path,
            on_variant=lambda n: click.echo(f"benchmark: {n} ...", err=True))
    for name, why in {**run_info["skipped"], **run_info["slow"]}.items():
        click.echo(f"benchmark: {name}: {why}", err=True)
    if all(r["status"].startswith(B.SKIPPED) for r in rows):
        raise InputError("deploy.benchmark_variants: nothing could be measured on this host")
    click.echo(B.format_table(rows))
    if sweep := B.format_sweep(run_info):  # the CUDA batch sweep
        click.echo(sweep)
    summary = B.fast_path_summary(rows, resolution, target_ms=st["target_ms"], target_res=st["target_res"],
                                  max_drop=st["max_drop"])
    if summary is not None:
        click.echo(B.fast_path_line(summary, rows, resolution, st["target_ms"], st["target_res"]))
    if json_out:
        write_json(json_out, B.benchmark_result(rows, run_info, st, tau=target.tau, summary=summary, notes=notes))
    if metrics_json:
        write_json(metrics_json, deploy_metrics(summary, rows, B.BASELINE_VARIANT))
    if out:
        import pandas as pd

        meta = stage_context("benchmark", __file__, params).meta(
            "efficiency", target.inputs + data_inputs, params={"deploy": cfg, "resolution": resolution, "tau": target.tau},
            device=run_info["device"], threads=run_info["threads"], notes=notes)
        write_parquet(out, pd.DataFrame(rows), meta)
    click.echo(f"benchmark: {len(rows)} variants" + (f" -> {out}" if out else "") + (f", {json_out}" if json_out else ""),
               err=True)


if __name__ == "__main__":
    main()
