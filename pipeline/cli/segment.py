"""``geodistill segment``: binary spacecraft masks for image files with a trained or exported student.

--checkpoint  a checkpoint directory (artifacts/checkpoints/<method>/<seed>) or a deploy bundle
              (artifacts/deploy, from ``geodistill export``)
--input       one image file or a folder (searched recursively for png/jpg/jpeg/tif/tiff/bmp)
--output      folder for ``<input name>.mask.png`` (0/255, at the image's original size), optional
              ``<input name>.prob.png`` (--save-prob) and ``<input name>.overlay.png`` (--overlay), and
              skipped.csv and confidence.csv (each mask's per-frame confidence in [0, 1], low = don't trust
              this frame: pipeline.deploy.confidence).  The whole input name is kept and sub-folders are mirrored:
              ``photos/sub/a.png`` -> ``masks/sub/a.png.mask.png``, so a.png, a.jpg and a_png.png get
              distinct outputs.  Two inputs whose outputs differ only in letter case (b.png, b.PNG) are
              refused before anything is written.
--overwrite   replace files in the way that an earlier segment run did not write; without it such a
              file stops the run before anything is written.  ``segment.json`` in --output lists what
              segment wrote there, and a rerun replaces those without asking (pipeline.artifacts.ownership)
--skip-bad    leave unreadable images out (listed in skipped.csv); without it the first one stops
              the run with one line naming it (the bad-file policy of label, distill and prepare)
--max-pixels  refuse images above N pixels, read from the file header before decoding (default
              data.max_pixels); a bad file like any other under --skip-bad

--engine      auto or an engine of pipeline.deploy.engine_table (``--help`` lists them): what computes the logits.
              ``auto`` = on a CUDA device ``cuda`` (bf16 + CUDA graphs, pipeline.deploy.cuda_engine),
              else onnxruntime_fp32 when the bundle holds model.onnx and onnxruntime imports, else torch:
              on the CPU only engines whose masks equal PyTorch's; the int8 engines (faster,
              approximate) must be asked for.  A checkpoint directory supports torch and cuda only.  Every engine gets the same
              preprocessed input and the same tau; the engine and its timings are printed on stderr
              (model ms/image includes the first, warm-up batch; not with --quiet).

tau (pipeline.thresholds.resolve_tau): ``--tau`` > the bundle's deploy.json > the checkpoint's payload >
its row in ``--thresholds`` (default artifacts/thresholds.parquet when it exists) > ``calibrate.fixed_tau``
of the params file (with a warning).  Working resolution: ``--resolution`` > the one the model was
trained at (the bundle's deploy.json, the checkpoint's payload or meta.json); never guessed from the
params file: a checkpoint that records none is refused with a request for ``--resolution N``, and a
``--resolution`` other than the recorded one is used with a warning.

Unlike the pipeline stages this is a user tool: it runs anywhere, and reads the params file only
for the tau fallback, when that file exists.  Unreadable images -- and, in an input folder, symbolic
links pointing outside it, broken links and links to folders (never followed) -- stop the run with
one line, or with --skip-bad are listed in skipped.csv and counted on stderr; the rest go on.  Inputs are never modified and outputs never
overwrite inputs (an output folder inside the input folder is refused).  Bad options and refused
outputs: one line on stderr naming the path, exit code 2, nothing written.  The logic is
:func:`pipeline.deploy.segmenting.segment_images`; this script is wiring.
"""

from __future__ import annotations

from pathlib import Path

import click

from pipeline.catalog import PARAMS_FILE, dvc_path
from pipeline.deploy.engine_table import AUTO, ENGINE_ALIASES, ENGINE_CHOICES, MODEL_ENGINES
from pipeline.params import load_params
from pipeline.deploy.segmenting import segment_images
from pipeline.runtime.progress import quiet_bars
from stages._common import (bit_depth_option, max_pixels_option, one_line_errors, overwrite_option, quiet_option,
                            setup_logging, skip_bad_option)


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
