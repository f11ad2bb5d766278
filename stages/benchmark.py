"""Stage benchmark: efficiency of the deployed mask path on this machine (pipeline.deploy.benchmark).

For every variant in ``deploy.benchmark_variants`` (fp32 eager NCHW = the plain baseline, channels_last,
bf16 autocast, TorchScript frozen, ONNX Runtime fp32 and int8, ...): parameters and GFLOPs counted on the
graph, batch-1 latency (median after warm-up), best-batch throughput, peak memory, and the change of the
mean validation Image IoU against the fp32 baseline at the deployed tau.  The table goes to stdout with
each variant's speed-up over the baseline measured in the same run; ``--json`` writes the same numbers.

Validation data: rows of images.zarr / reference.zarr with split == 'val' and a reference mask
(reference masks here only measure accuracy, never train).  int8: the bundle's ``model.int8.onnx``
(calibrated at export) when it has one -- the very file segment runs; otherwise (``--checkpoint``, or a
bundle exported without it) the ONNX model is quantised here with the same code
(pipeline.deploy.quantize_onnx_int8) on training-split images only (no masks).  Standalone: ``--checkpoint C`` instead of ``--deploy``, ``--resolution 384``
to time another size; without artifacts the IoU columns are NaN.  Timings are measurements of this
machine and its load: nothing here asserts a target, the JSON records whether it was met.
"""

from __future__ import annotations

import json
import math
import tempfile
from pathlib import Path

import click
import numpy as np

from pipeline.params import require, section
from stages._common import meta_for, stage_code_version, stage_command

CODE_MODULES = ("deploy.py", "model.py", "inference.py", "metrics.py", "artifacts.py")


def _split_rows(manifest_df, split: str, has_mask=None) -> np.ndarray:
    keep = manifest_df["split"].to_numpy() == split
    if has_mask is not None:
        keep &= np.asarray(has_mask, bool)
    return np.flatnonzero(keep)


def load_data(art: Path, n_calib: int):
    """(val images, val masks, calibration images, input artifacts); Nones when artifacts are absent."""
    from pipeline.artifacts import open_artifact, read_chunk_rows
    from pipeline.deploy import calibration_rows

    paths = [art / "manifest.parquet", art / "images.zarr", art / "reference.zarr"]
    if not all(p.exists() for p in paths):
        return None, None, None, []
    manifest = open_artifact(paths[0], "manifest")
    images = open_artifact(paths[1], "images")
    reference = open_artifact(paths[2], "reference")
    val = _split_rows(manifest.df, "val", reference.numpy("has_mask"))
    train = calibration_rows(manifest.df["split"].to_numpy(), n_calib)  # the export's selection
    val_images = read_chunk_rows(images["image"], val) if val.size else None
    # reference masks: accuracy measurement only (never a training target)
    val_masks = read_chunk_rows(reference["mask"], val).astype(bool) if val.size else None
    calib = read_chunk_rows(images["image"], train) if train.size else None
    return val_images, val_masks, calib, [manifest, images, reference]


def format_table(rows, baseline: str) -> str:
    head = (f"{'variant':22s} {'latency ms':>10s} {'x base':>7s} {'img/s':>8s} {'batch':>5s} {'peak MB':>8s} "
            f"{'IoU':>7s} {'dIoU':>8s} {'mIoU fp32':>9s}")
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(f"{r['variant']:22s} {r['latency_ms']:10.2f} {r['speedup']:7.2f} {r['throughput']:8.2f} "
                     f"{r['batch']:5d} {r['peak_mb']:8.1f} {r['iou']:7.4f} {r['iou_delta']:+8.4f} {r['iou_vs_fp32']:9.4f}")
    lines.append(f"(x base = {baseline} latency / variant latency, timed round-robin in the same run; "
                 f"mIoU fp32 = mean per-image IoU of the variant's masks with {baseline}'s)")
    return "\n".join(lines)


def _clean(v):
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


@stage_command("benchmark")
@click.option("--deploy", "deploy_dir", default=None, type=click.Path(file_okay=False),
              help="deploy bundle (geodistill export); or use --checkpoint")
@click.option("--checkpoint", default=None, type=click.Path(file_okay=False), help="checkpoint dir instead of a bundle")
@click.option("--artifacts", "art", default="artifacts", show_default=True, type=click.Path(file_okay=False),
              help="manifest/images/reference for the IoU check and int8 calibration (optional standalone)")
@click.option("--thresholds", default="artifacts/thresholds.parquet", show_default=True,
              help="with --checkpoint: where to find its calibrated tau")
@click.option("--tau", type=float, default=None, help="override the deployed tau")
@click.option("--resolution", type=int, default=None, help="time at this size (default: deploy.benchmark_resolution "
              "or the bundle's working resolution); IoU is always measured on images.zarr")
@click.option("--out", default=None, type=click.Path(dir_okay=False), help="efficiency.parquet to write")
@click.option("--json", "json_out", default=None, type=click.Path(dir_okay=False), help="JSON results to write")
def main(params, device, deploy_dir, checkpoint, art, thresholds, tau, resolution, out, json_out):
    """Latency, throughput, memory and IoU change of the deployed mask path's variants."""
    from pipeline import deploy
    from pipeline.artifacts import atomic_path, open_artifact, write_parquet
    from pipeline.device import resolve_device
    from pipeline.errors import InputError
    from pipeline.inference import load_student

    cfg = section(params, "deploy")
    warmup = require(cfg, "benchmark_warmup", "deploy", kind=int, lo=0)
    iters = require(cfg, "benchmark_iters", "deploy", kind=int, lo=1)
    batches = require(cfg, "benchmark_batches", "deploy", kind=list)
    variants = require(cfg, "benchmark_variants", "deploy", kind=list)
    n_calib = require(cfg, "int8_calibration_images", "deploy", kind=int, lo=1)
    q8 = deploy.int8_params(cfg)
    target_ms = float(require(cfg, "target_latency_ms", "deploy", kind=(int, float), lo=0))
    max_drop = float(require(cfg, "target_iou_drop", "deploy", kind=(int, float), lo=0))
    target_res = require(cfg, "target_resolution", "deploy", kind=int, lo=1)
    if not batches or not all(isinstance(b, int) and b >= 1 for b in batches):
        raise InputError(f"params: deploy.benchmark_batches={batches!r}: positive integers expected")
    unknown = [v for v in variants if v not in deploy.VARIANTS]
    if unknown:
        raise InputError(f"params: deploy.benchmark_variants: unknown {unknown} (known: {', '.join(deploy.VARIANTS)})")
    if (deploy_dir is None) == (checkpoint is None):
        raise InputError("give exactly one of --deploy (a bundle) or --checkpoint")

    dev = resolve_device(device)
    inputs = []
    onnx_path = bundle_int8 = None
    if deploy_dir is not None:
        bundle = open_artifact(deploy_dir, "deploy")
        inputs.append(bundle)
        info = deploy.read_deploy_info(deploy_dir)
        model, payload = load_student(deploy_dir, "cpu")
        tau_dep, res_dep = info["tau"], info["resolution"]
        if (Path(deploy_dir) / "model.onnx").exists():
            onnx_path = Path(deploy_dir) / "model.onnx"
        if (Path(deploy_dir) / deploy.INT8_FILE).exists():
            bundle_int8 = Path(deploy_dir) / deploy.INT8_FILE
            bundle_int8_info = info.get("int8") or {}
    else:
        seg = deploy.load_segmenter(checkpoint, "torch", "cpu", thresholds)
        model, payload = load_student(checkpoint, "cpu")
        inputs.append(open_artifact(checkpoint, "checkpoint"))
        tau_dep, res_dep = seg.tau, seg.resolution
        if tau_dep is None and tau is None:
            tau_dep = require(section(params, "calibrate"), "fixed_tau", "calibrate")
            click.echo(f"benchmark: no calibrated tau for {checkpoint}; IoU at calibrate.fixed_tau={tau_dep}", err=True)
    tau = deploy.check_tau(tau if tau is not None else tau_dep, "tau")
    resolution = resolution or cfg.get("benchmark_resolution") or res_dep or section(params, "data").get("resolution")
    if not isinstance(resolution, int) or resolution < 8:
        raise InputError(f"--resolution: invalid or unknown ({resolution!r})")

    val_images, val_masks, calib, data_inputs = load_data(Path(art), n_calib)
    inputs += data_inputs
    notes = {}
    if val_images is None:
        notes["iou"] = f"no validation images with reference masks under {art}: IoU columns are NaN"
        click.echo(f"benchmark: {notes['iou']}", err=True)

    with tempfile.TemporaryDirectory() as td:
        int8_path = None
        reason = deploy.onnx_unavailable_reason()
        if reason is None:
            if onnx_path is None:
                onnx_path = deploy.export_onnx(model, Path(td) / "model.onnx", resolution, require(cfg, "opset", "deploy"))
            if "onnxruntime_int8" in variants and bundle_int8 is not None:
                int8_path = bundle_int8
                notes["int8_calibration"] = (f"deploy bundle's {deploy.INT8_FILE} (calibrated at export on "
                                             f"{bundle_int8_info.get('calibration_images', '?')} training-split images)")
            elif "onnxruntime_int8" in variants:
                if calib is None:
                    calib = (deploy.parity_inputs(min(resolution, 128), n=4).permute(0, 2, 3, 1).numpy() * 255
                             ).round().astype(np.uint8)
                    notes["int8_calibration"] = "no training images found: calibrated on synthetic smooth noise"
                else:
                    notes["int8_calibration"] = f"{len(calib)} training-split images (no masks)"
                int8_path = deploy.quantize_onnx_int8(onnx_path, Path(td) / "model_int8.onnx", calib,
                                                      q8["calibration"], q8["percentile"])
        else:
            click.echo(f"benchmark: {reason}", err=True)
        rows, run_info = deploy.benchmark(
            model, resolution=resolution, device=dev, variants=variants, warmup=warmup, iters=iters,
            batches=batches, tau=tau, val_images=val_images, val_masks=val_masks, onnx_path=onnx_path,
            int8_path=int8_path, on_variant=lambda n: click.echo(f"benchmark: {n} ...", err=True))
    for name, why in run_info["skipped"].items():
        click.echo(f"benchmark: skipped {name}: {why}", err=True)
    if not rows:
        raise InputError("deploy.benchmark_variants: nothing could be measured")

    fast = deploy.fastest_within(rows, max_drop)
    base = next((r for r in rows if r["variant"] == deploy.BASELINE_VARIANT), None)
    click.echo(format_table(rows, deploy.BASELINE_VARIANT))
    summary = None
    if fast is not None:
        # the latency target is defined at deploy.target_resolution: at another size it is not judged (None)
        meets = fast["latency_ms"] <= target_ms if resolution == target_res else None
        summary = {"variant": fast["variant"], "latency_ms": fast["latency_ms"], "speedup": fast["speedup"],
                   "iou_delta": _clean(fast["iou_delta"]), "meets_latency_target": meets,
                   "within_iou_drop": (None if math.isnan(fast["iou_delta"]) else abs(fast["iou_delta"]) <= max_drop)}
        verdict = ("not judged at this size" if meets is None else "met" if meets else "NOT met")
        click.echo(f"fast path: {fast['variant']} {fast['latency_ms']:.1f} ms/image at {resolution}px batch 1 "
                   f"({fast['speedup']:.1f}x the {deploy.BASELINE_VARIANT} baseline"
                   + (f" of {base['latency_ms']:.1f} ms" if base else "") + f"); target {target_ms:g} ms at "
                   f"{target_res}px: {verdict}")

    result = {
        "resolution": resolution, "device": run_info["device"], "threads": run_info["threads"], "tau": tau,
        "n_val": run_info["n_val"], "warmup": warmup, "iters": iters, "batches": run_info["batches"],
        "baseline": deploy.BASELINE_VARIANT, "fast_path": summary,
        "target": {"latency_ms": target_ms, "max_iou_drop": max_drop, "batch": 1, "resolution": target_res},
        "peak_memory_method": rows[0]["peak_method"], "skipped": run_info["skipped"], "notes": notes,
        "variants": {r["variant"]: {k: _clean(v) for k, v in r.items() if k != "variant"} for r in rows},
    }
    if json_out:
        with atomic_path(json_out) as tmp:
            tmp.write_text(json.dumps(result, indent=1, sort_keys=True))
    if out:
        import pandas as pd

        code = stage_code_version(__file__, *CODE_MODULES)
        meta = meta_for("efficiency", "benchmark", code, {"deploy": cfg, "resolution": resolution, "tau": tau},
                        inputs, device=run_info["device"], threads=run_info["threads"], notes=notes)
        df = pd.DataFrame(rows)
        write_parquet(out, df, meta)
    click.echo(f"benchmark: {len(rows)} variants" + (f" -> {out}" if out else "") + (f", {json_out}" if json_out else ""),
               err=True)


if __name__ == "__main__":
    main()
