"""``geodistill segment``: binary spacecraft masks at each image's original size, with a trained student.

The student is a checkpoint or an exported bundle (docs/own-data.md); the logic is
:func:`pipeline.deploy.image_files.segment_images`.
"""

from __future__ import annotations

from pathlib import Path

import click

from pipeline.catalog import PARAMS_FILE, dvc_path
from pipeline.engine_table import AUTO, ENGINE_ALIASES, ENGINE_CHOICES, MODEL_ENGINES
from pipeline.params import load_params
from pipeline.deploy.image_files import segment_images
from pipeline.runtime.progress import quiet_bars
from pipeline.cli.conventions import (bit_depth_option, max_pixels_option, one_line_errors, overwrite_option,
                                      quiet_option, setup_logging, skip_bad_option)

__all__ = ["main"]


@click.command(name="segment", help="Binary spacecraft masks for image files with a trained or exported student (at each image's original size).")
@click.option("--checkpoint", required=True, help="checkpoint directory or deploy bundle")
@click.option("--input", "input_path", required=True, help="image file or folder")
@click.option("--output", required=True, help="output folder")
@click.option("--tau", type=float, default=None, help="threshold override (default: the calibrated one)")
@click.option("--resolution", type=int, default=None,
              help="working resolution N (default: the one recorded with the model; required when none is)")
@click.option("--thresholds", default=dvc_path("thresholds"), show_default=True,
              help="thresholds table used to find a checkpoint's calibrated tau (when it exists)")
@click.option("--engine", default=AUTO, show_default=True,
              help=f"{' | '.join(ENGINE_CHOICES)} (all but {' and '.join(MODEL_ENGINES)} need a deploy bundle); "
                   "auto = cuda on a GPU, else onnxruntime_fp32 if available, else torch (exact engines only on "
                   "the CPU; the int8 engines are faster but approximate); also accepted: "
                   + ", ".join(f"{old} = {new}" for old, new in ENGINE_ALIASES.items()))
@click.option("--batch-size", type=int, default=8, show_default=True)
@click.option("--save-prob", is_flag=True, help="also write <input name>.prob.png (P x 255)")
@click.option("--overlay", is_flag=True, help="also write <input name>.overlay.png")
@overwrite_option
@skip_bad_option
@max_pixels_option
@bit_depth_option
@quiet_option
@click.option("--device", default="auto", show_default=True, help="auto | cpu | cuda")
@click.option("--params", "params_file", default=PARAMS_FILE, show_default=True,
              help="params file, read only for the tau / resolution fallbacks")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE", help="override a param (repeatable)")
def main(checkpoint, input_path, output, tau, resolution, thresholds, engine, batch_size, save_prob, overlay,
         overwrite, skip_bad, max_pixels, bit_depth, quiet, device, params_file, overrides):
    with one_line_errors("segment"):
        setup_logging()
        params = load_params(params_file, overrides) if Path(params_file).exists() else None
        with quiet_bars(quiet):
            segment_images(checkpoint, input_path, output, tau=tau, resolution=resolution, thresholds=thresholds,
                           engine=engine, batch_size=batch_size, save_prob=save_prob, overlay=overlay, device=device,
                           params=params, overwrite=overwrite, skip_bad=skip_bad, max_pixels=max_pixels, bit_depth=bit_depth, quiet=quiet,
                           echo=lambda line: click.echo(line, err=True))


if __name__ == "__main__":
    main()
