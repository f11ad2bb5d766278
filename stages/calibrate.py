"""Stage calibrate: choose every student's binarisation threshold tau on the VALIDATION split.

Paper (Training Details): "The binarization threshold is selected by Image IoU on the corresponding
validation set and then applied unchanged to the test set."  For each active run (method, seed):
P = sigmoid(Z) on the validation images, tau = argmax over the grid of the mean Image IoU of
[P >= tau] (eq:inference-mask; ties -> closest to 0.5).  The whole curve is kept (list columns
``grid`` and ``curve``) for the report's threshold-curve figure, with the fixed tau = 0.5 alongside.

Manual (reference) masks enter here ONLY to calibrate tau -- they are never a training target.
"""

from __future__ import annotations


import click
import numpy as np
import pandas as pd

from pipeline.params import require, section
from stages._common import meta_for, stage_code_version, stage_command

CODE_MODULES = ("metrics.py", "inference.py", "artifacts.py")


def threshold_grid(cfg: dict) -> np.ndarray:
    """tau grid from calibrate.grid_start .. grid_stop (inclusive) in steps of grid_step, rounded to
    1e-9 so that 0.5 is exactly on the default grid."""
    from pipeline.errors import InputError

    start = require(cfg, "grid_start", "calibrate", kind=(int, float), lo=0.0, hi=1.0)
    stop = require(cfg, "grid_stop", "calibrate", kind=(int, float), lo=0.0, hi=1.0)
    step = require(cfg, "grid_step", "calibrate", kind=(int, float), lo=1e-6, hi=1.0)
    if stop < start:
        raise InputError(f"params: calibrate.grid_stop={stop} < calibrate.grid_start={start}")
    n = int(np.floor((stop - start) / step + 1e-9)) + 1
    return np.round(start + step * np.arange(n), 9)


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
    from pipeline.metrics import calibrate_threshold, iou_curve
    from pipeline.progress import progress

    cfg = section(params, "calibrate")
    grid = threshold_grid(cfg)
    fixed_tau = float(require(cfg, "fixed_tau", "calibrate", kind=(int, float), lo=0.0, hi=1.0))
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
    code = stage_code_version(__file__, *CODE_MODULES)
    meta = meta_for("thresholds", "calibrate", code, {"calibrate": cfg}, inputs,
                    note="reference masks of the validation split used only for threshold calibration")
    write_parquet(out, pd.DataFrame(rows), meta)
    click.echo(f"calibrate: {len(rows)} runs on {val.size} validation images -> {out}", err=True)


if __name__ == "__main__":
    main()
