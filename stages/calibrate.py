"""Stage calibrate: each run's tau on the VALIDATION split by mean Image IoU over the grid (eq:inference-mask,
``calibrate.tau_rule``), the whole curve and calibration diagnostics; reference masks only calibrate here
(the logic: :mod:`pipeline.evaluation.evaluate`)."""

from __future__ import annotations

import click

from pipeline.artifacts.store import open_artifact, read_chunk_rows, write_parquet
from pipeline.catalog import ARTIFACTS_DIR, dvc_path
from pipeline.evaluation.evaluate import calibrate_runs, fixed_thresholds
from pipeline.evaluation.inference import (CORRECTED_VALIDATION, active_runs, open_labelled_split,
                                           validation_corrections, with_validation_corrections)
from pipeline.params import section
from pipeline.runtime.device import resolve_device
from stages._common import stage_command, stage_context


@stage_command("calibrate")
@click.option("--artifacts", "art", default=ARTIFACTS_DIR, show_default=True, type=click.Path(file_okay=False),
              help="directory holding manifest.parquet, images.zarr, reference.zarr")
@click.option("--checkpoints", default=dvc_path("checkpoints"), show_default=True, type=click.Path(file_okay=False))
@click.option("--out", default=dvc_path("thresholds"), show_default=True, type=click.Path(dir_okay=False))
def main(params, device, art, checkpoints, out):
    """Calibrate tau per (method, seed) by mean validation Image IoU; write thresholds.parquet."""
    cfg = section(params, "calibrate")
    manifest, images, reference, val = open_labelled_split(art, "val", "calibration needs some", allow_empty=True)
    # review.mode validate: the corrected training images are validation images too (pipeline/review/apply.py)
    corrected = validation_corrections(art, section(params, "review"))
    runs = active_runs(checkpoints, "calibrate")
    inputs = [manifest, images, reference] + ([corrected] if corrected is not None else [])
    inputs += [open_artifact(path) for _, _, path in runs]
    ctx = stage_context("calibrate", __file__, params)
    if val.size == 0 and corrected is None:  # e.g. `geodistill distill` without --val-masks
        fixed_tau = cfg["fixed_tau"]
        table = fixed_thresholds(runs, fixed_tau)
        write_parquet(out, table, ctx.meta("thresholds", inputs, note="no validation image has a reference mask: "
                                                                      f"tau = calibrate.fixed_tau = {fixed_tau}"))
        click.echo(f"calibrate: no validation masks; {len(table)} runs get the fixed tau {fixed_tau} -> {out}", err=True)
        return
    # reference (and corrected) masks: threshold calibration only (never a training loss)
    val_images, val_masks = with_validation_corrections(
        read_chunk_rows(images["image"], val), read_chunk_rows(reference["mask"], val).astype(bool), corrected, images)
    table = calibrate_runs(runs, val_images, val_masks, cfg, resolve_device(device))
    note, extra, n_val = "reference masks of the validation split used only for threshold calibration", {}, len(val_masks)
    if corrected is not None:
        note += f", with the masks of {n_val - val.size} corrected training images (review.mode validate)"
        extra[CORRECTED_VALIDATION] = n_val - int(val.size)
    write_parquet(out, table, ctx.meta("thresholds", inputs, note=note, **extra))
    click.echo(f"calibrate: {len(table)} runs on {n_val} validation images -> {out}", err=True)


if __name__ == "__main__":
    main()
