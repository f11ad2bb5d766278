"""Stage calibrate: each run's tau on the VALIDATION split by mean Image IoU over the grid (eq:inference-mask,
``calibrate.tau_rule``), the whole curve and calibration diagnostics; reference masks only calibrate here."""

from __future__ import annotations

import click
import numpy as np
import pandas as pd

from pipeline.artifacts.store import open_artifact, read_chunk_rows, write_parquet
from pipeline.catalog import ARTIFACTS_DIR, dvc_path
from pipeline.runtime.device import resolve_device
from pipeline.evaluation.diagnostics import (area_ratio_curve, expected_calibration_error, median_area_ratio,
    reliability_bins)
from pipeline.evaluation.inference import (CORRECTED_VALIDATION, active_runs, load_student, open_labelled_split, predict_probs,
    validation_corrections, with_validation_corrections)
from pipeline.metrics import iou_curve
from pipeline.params import section
from pipeline.runtime.progress import progress
from pipeline.thresholds import NO_VALIDATION_MASKS, calibrate_threshold, rule_options, threshold_grid
from stages._common import stage_command, stage_context



def fixed_thresholds(params, runs, inputs, out) -> None:
    """No validation image has a mask: every run gets the fixed tau (``calibrate.fixed_tau``, 0.5),
    ``val_iou`` NaN, ``n_val`` 0 and ``tau_source`` saying why -- export and segment then use 0.5 and
    the report says that no masks were available."""
    fixed_tau = section(params, "calibrate")["fixed_tau"]
    rows = [{"method": method, "seed": int(seed), "tau": fixed_tau, "val_iou": float("nan"), "fixed_tau": fixed_tau,
             "fixed_val_iou": float("nan"), "n_val": 0, "tau_source": NO_VALIDATION_MASKS} for method, seed, _ in runs]
    inputs = list(inputs) + [open_artifact(path) for _, _, path in runs]
    meta = stage_context("calibrate", __file__, params).meta(
                    "thresholds", inputs, note=f"no validation image has a reference mask: tau = calibrate.fixed_tau = {fixed_tau}")
    write_parquet(out, pd.DataFrame(rows), meta)
    click.echo(f"calibrate: no validation masks; {len(rows)} runs get the fixed tau {fixed_tau} -> {out}", err=True)


@stage_command("calibrate")
@click.option("--artifacts", "art", default=ARTIFACTS_DIR, show_default=True, type=click.Path(file_okay=False),
              help="directory holding manifest.parquet, images.zarr, reference.zarr")
@click.option("--checkpoints", default=dvc_path("checkpoints"), show_default=True, type=click.Path(file_okay=False))
@click.option("--out", default=dvc_path("thresholds"), show_default=True, type=click.Path(dir_okay=False))
def main(params, device, art, checkpoints, out):
    """Calibrate tau per (method, seed) by mean validation Image IoU; write thresholds.parquet."""
    cfg = section(params, "calibrate")
    grid = threshold_grid(cfg)
    fixed_tau = cfg["fixed_tau"]
    manifest, images, reference, val = open_labelled_split(art, "val", "calibration needs some", allow_empty=True)
    # review.mode validate: the corrected training images are validation images too (pipeline/review/apply.py)
    corrected = validation_corrections(art, section(params, "review"))
    runs = active_runs(checkpoints, "calibrate")
    if val.size == 0 and corrected is None:  # e.g. `geodistill distill` without --val-masks: see fixed_thresholds
        return fixed_thresholds(params, runs, [manifest, images, reference], out)

    dev = resolve_device(device)
    # reference (and corrected) masks: threshold calibration only (never a training loss)
    val_images, val_masks = with_validation_corrections(
        read_chunk_rows(images["image"], val), read_chunk_rows(reference["mask"], val).astype(bool), corrected, images)
    n_val = len(val_masks)
    rows, inputs = [], [manifest, images, reference] + ([corrected] if corrected is not None else [])
    for method, seed, path in progress(runs, desc="calibrate"):
        model, _ = load_student(path, dev)
        probs = predict_probs(model, val_images, device=dev)
        tau, curve = calibrate_threshold(probs, val_masks, grid, **rule_options(cfg))
        fixed_iou = float(iou_curve(probs, val_masks, [fixed_tau]).mean())
        rel = reliability_bins(probs, val_masks, cfg["reliability_bins"])
        area = median_area_ratio(area_ratio_curve(probs, val_masks, grid))
        rows.append({"method": method, "seed": int(seed), "tau": tau, "val_iou": float(curve.max()),
                     "fixed_tau": fixed_tau, "fixed_val_iou": fixed_iou, "n_val": n_val,
                     "grid": grid.tolist(), "curve": curve.tolist(),
                     "ece": expected_calibration_error(rel.confidence, rel.frequency, rel.count),
                     "rel_confidence": rel.confidence.tolist(), "rel_frequency": rel.frequency.tolist(),
                     "rel_count": rel.count.tolist(), "area_curve": area.tolist(),
                     # tau is a grid point (select_tau): its area ratio is on the curve already
                     "area_ratio": float(area[int(np.flatnonzero(grid == tau)[0])]),
                     "fixed_area_ratio": float(median_area_ratio(area_ratio_curve(probs, val_masks, [fixed_tau]))[0])})
        inputs.append(open_artifact(path))
    note = "reference masks of the validation split used only for threshold calibration"
    extra = {}
    if corrected is not None:
        note += f", with the masks of {n_val - val.size} corrected training images (review.mode validate)"
        extra[CORRECTED_VALIDATION] = n_val - int(val.size)
    meta = stage_context("calibrate", __file__, params).meta("thresholds", inputs, note=note, **extra)
    write_parquet(out, pd.DataFrame(rows), meta)
    click.echo(f"calibrate: {len(rows)} runs on {n_val} validation images -> {out}", err=True)


if __name__ == "__main__":
    main()
