"""Stage calibrate: choose every student's binarisation threshold tau on the VALIDATION split.

Paper (Training Details): "The binarization threshold is selected by Image IoU on the corresponding
validation set and then applied unchanged to the test set."  For each active run (method, seed):
P = sigmoid(Z) on the validation images, tau = argmax over the grid of the mean Image IoU of
[P >= tau] (eq:inference-mask; ties -> closest to 0.5): pipeline.thresholds.calibrate_threshold.  The whole curve is kept (list columns
``grid`` and ``curve``) for the report's threshold-curve figure, with the fixed tau = 0.5 alongside.

Manual (reference) masks enter here ONLY to calibrate tau -- they are never a training target.
"""

from __future__ import annotations

import click
import pandas as pd

from pipeline.params import section
from stages._common import declared_params, meta_for, stage_code_version, stage_command



@stage_command("calibrate")
@click.option("--artifacts", "art", default="artifacts", show_default=True, type=click.Path(file_okay=False),
              help="directory holding manifest.parquet, images.zarr, reference.zarr")
@click.option("--checkpoints", default="artifacts/checkpoints", show_default=True, type=click.Path(file_okay=False))
@click.option("--out", default="artifacts/thresholds.parquet", show_default=True, type=click.Path(dir_okay=False))
def main(params, device, art, checkpoints, out):
    """Calibrate tau per (method, seed) by mean validation Image IoU; write thresholds.parquet."""
    from pipeline.artifacts import open_artifact, read_chunk_rows, write_parquet
    from pipeline.device import resolve_device
    from pipeline.inference import active_runs, load_student, open_labelled_split, predict_probs
    from pipeline.metrics import iou_curve
    from pipeline.progress import progress
    from pipeline.thresholds import calibrate_threshold, threshold_grid

    cfg = section(params, "calibrate")
    grid = threshold_grid(cfg)
    fixed_tau = cfg["fixed_tau"]
    manifest, images, reference, val = open_labelled_split(art, "val", "calibration needs some")
    runs = active_runs(checkpoints, "calibrate")

    dev = resolve_device(device)
    val_images = read_chunk_rows(images["image"], val)
    # reference masks: threshold calibration only (never a training loss)
    val_masks = read_chunk_rows(reference["mask"], val).astype(bool)
    rows, inputs = [], [manifest, images, reference]
    for method, seed, path in progress(runs, desc="calibrate"):
        model, _ = load_student(path, dev)
        probs = predict_probs(model, val_images, device=dev)
        tau, curve = calibrate_threshold(probs, val_masks, grid)
        fixed_iou = float(iou_curve(probs, val_masks, [fixed_tau]).mean())
        rows.append({"method": method, "seed": int(seed), "tau": tau, "val_iou": float(curve.max()),
                     "fixed_tau": fixed_tau, "fixed_val_iou": fixed_iou, "n_val": int(val.size),
                     "grid": grid.tolist(), "curve": curve.tolist()})
        inputs.append(open_artifact(path))
    code = stage_code_version(__file__)
    meta = meta_for("thresholds", "calibrate", code, declared_params(params, "calibrate"), inputs,
                    note="reference masks of the validation split used only for threshold calibration")
    write_parquet(out, pd.DataFrame(rows), meta)
    click.echo(f"calibrate: {len(rows)} runs on {val.size} validation images -> {out}", err=True)


if __name__ == "__main__":
    main()
