"""``geodistill segment``: binary spacecraft masks for image files with a trained or exported student.

--checkpoint  a checkpoint directory (artifacts/checkpoints/<method>/<seed>) or a deploy bundle
              (artifacts/deploy, from ``geodistill export``)
--input       one image file or a folder (searched recursively for png/jpg/jpeg/tif/tiff/bmp)
--output      folder for ``<input name>.mask.png`` (0/255, at the image's original size), optional
              ``<input name>.prob.png`` (--save-prob) and ``<input name>.overlay.png`` (--overlay), and
              skipped.csv.  The whole input name is kept and sub-folders are mirrored:
              ``photos/sub/a.png`` -> ``masks/sub/a.png.mask.png``, so a.png, a.jpg and a_png.png get
              distinct outputs.  Two inputs whose outputs differ only in letter case (b.png, b.PNG) are
              refused before anything is written.
--overwrite   replace files in the way that an earlier segment run did not write; without it such a
              file stops the run before anything is written.  ``segment.json`` in --output lists what
              segment wrote there, and a rerun replaces those without asking (pipeline.ownership)
--skip-bad    leave unreadable images out (listed in skipped.csv); without it the first one stops
              the run with one line naming it (the bad-file policy of label, distill and prepare)

--engine      auto | torch | cuda | torchscript | onnx | int8 | openvino_int8: what computes the logits.
              ``auto`` = on a CUDA device ``cuda`` (bf16 + CUDA graphs, pipeline.deploy.cuda_engine),
              else onnx when the bundle holds model.onnx and onnxruntime imports, else torch: on the
              CPU only engines whose masks equal PyTorch's; int8 / openvino_int8 (faster,
              approximate) must be asked for.  A checkpoint directory supports torch and cuda only.  Every engine gets the same
              preprocessed input and the same tau; the engine and its timings are printed on stderr
              (model ms/image includes the first, warm-up batch).

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
outputs: one line on stderr naming the path, exit code 2, nothing written.
"""

from __future__ import annotations

from pathlib import Path

import click

from pipeline.catalog import dvc_path
from pipeline.datasets.manifest import BadInputPolicy
from pipeline.device import resolve_device
from pipeline.errors import InputError
from pipeline.ownership import claim_outputs
from pipeline.params import load_params
from pipeline.thresholds import MIN_RESOLUTION, RESOLUTION_LABELS, resolve_resolution
from stages._common import one_line_errors, overwrite_option, setup_logging, skip_bad_option


def _fallback(params_file: str, overrides: tuple[str, ...], section_name: str, key: str):
    """``section.key`` from the params file (profile applied), or None when the file does not exist."""
    if not Path(params_file).exists():
        return None
    return (load_params(params_file, overrides).get(section_name) or {}).get(key)


def run(checkpoint, input_path, output, tau, resolution, thresholds, engine, batch_size, save_prob, overlay,
        device, params_file, overrides, overwrite=False, skip_bad=False) -> int:
    from pipeline import deploy  # torch: this module stays torch-free at import (--help)
    from pipeline.deploy import files as F

    setup_logging()
    if not checkpoint:
        raise InputError("--checkpoint missing: a checkpoint directory or a deploy bundle (geodistill export)")
    if not input_path:
        raise InputError("--input missing: an image file or a folder of images")
    if not output:
        raise InputError("--output missing: a folder for the masks")
    if batch_size < 1:
        raise InputError(f"--batch-size {batch_size}: must be >= 1")
    if resolution is not None and resolution < MIN_RESOLUTION:
        raise InputError(f"--resolution {resolution}: must be >= {MIN_RESOLUTION}")
    found = F.scan_inputs(input_path)
    if not found.files:
        extra = f"; skipped {found.skipped[0][0]}: {found.skipped[0][1]}" if found.skipped else ""
        raise InputError(f"--input {input_path}: no image files (png, jpg, jpeg, tif, tiff, bmp){extra}")
    files = found.files
    suffixes = F.output_suffixes(save_prob, overlay)
    stems = F.plan_outputs(found.root, files, output, found.is_dir, suffixes=suffixes, overwrite=overwrite)
    policy = BadInputPolicy(skip_bad, hint="pass --skip-bad to leave it out")
    root = found.root if found.is_dir else None

    def image_id(path) -> str:
        """The id label gives the file: its path relative to the input folder, without the suffix."""
        p = Path(path)
        try:
            return (p.relative_to(root) if root is not None else Path(p.name)).with_suffix("").as_posix()
        except ValueError:
            return p.stem

    for path, reason in found.skipped:  # links and special files: before anything is written
        policy.report(image_id(path), path, reason)
    for path, reason in found.unused:  # not images (hidden files, other types): listed, not an error
        policy.record(image_id(path), path, reason)

    seg = deploy.load_segmenter(checkpoint, engine, resolve_device(device), thresholds)
    tau, source = seg.resolve_tau(option=tau, fixed=(_fallback(params_file, overrides, "calibrate", "fixed_tau"),
                                                     "calibrate.fixed_tau (uncalibrated)"))
    trained = seg.resolution
    recorded_in = f"{Path(checkpoint) / deploy.DEPLOY_JSON}" if deploy.is_deploy_bundle(checkpoint) \
        else f"checkpoint {checkpoint}"
    if trained is not None:  # a recorded resolution is checked even when --resolution overrides it
        resolve_resolution(recorded=(trained, recorded_in))
    resolution, res_source = resolve_resolution(
        option=resolution, recorded=(trained, recorded_in),
        missing=f"--checkpoint {checkpoint}: records no training resolution; pass --resolution N "
                "(the image size the model was trained at)")
    if res_source == RESOLUTION_LABELS["option"] and trained is not None and resolution != trained:
        click.echo(f"segment: warning: --resolution {resolution} differs from the {trained}px the model was "
                   f"trained at ({recorded_in})", err=True)

    def report(path, reason):
        policy.report(image_id(path), path, reason)  # raises without --skip-bad

    click.echo(f"segment: engine {seg.engine}" + (" (auto)" if engine == "auto" else "")
               + f", {len(files)} image(s), {resolution}px ({res_source}), tau={tau:.4g} ({source})", err=True)
    claim_outputs(output, F.relative_outputs(output, stems, suffixes), F.RECORD, "segment",
                  {"input": str(Path(input_path).absolute()), "checkpoint": str(Path(checkpoint).absolute())})
    result = deploy.segment_files(seg, files, stems, tau=tau, resolution=resolution, batch_size=batch_size,
                                  save_prob=save_prob, overlay=overlay, on_skip=report)
    listing = Path(output) / F.SKIPPED_CSV
    deploy.write_skipped_csv(listing, policy.rows())
    click.echo(f"segment: wrote {len(result.written)} mask(s) to {output}", err=True)
    if (line := policy.summary("segment", listing)) is not None:
        click.echo(line, err=True)
    if result.written:
        n = len(result.written)
        click.echo(f"segment: timing: engine {seg.engine}, {1e3 * result.model_seconds / n:.2f} ms/image in the model, "
                   f"{1e3 * result.total_seconds / n:.2f} ms/image end to end ({n} images, batch {batch_size}, "
                   f"{resolution}px)", err=True)
    if not result.written:
        raise InputError(f"--input {input_path}: none of the {len(files)} file(s) could be read")
    return 0


@click.command(name="segment", help="Binary spacecraft masks for image files with a trained or exported student (at each image's original size).")
@click.option("--checkpoint", default=None, help="checkpoint directory or deploy bundle")
@click.option("--input", "input_path", default=None, help="image file or folder")
@click.option("--output", default=None, help="output folder")
@click.option("--tau", type=float, default=None, help="threshold override (default: the calibrated one)")
@click.option("--resolution", type=int, default=None,
              help="working resolution N (default: the one recorded with the model; required when none is)")
@click.option("--thresholds", default=dvc_path("thresholds"), show_default=True,
              help="thresholds table used to find a checkpoint's calibrated tau (when it exists)")
@click.option("--engine", default="auto", show_default=True,
              help="auto | torch | cuda | torchscript | onnx | int8 | openvino_int8 (all but torch and cuda "
                   "need a deploy bundle); auto = cuda on a GPU, else onnx if available, else torch (exact "
                   "engines only on the CPU; the int8 engines are faster but approximate)")
@click.option("--batch-size", type=int, default=8, show_default=True)
@click.option("--save-prob", is_flag=True, help="also write <input name>.prob.png (P x 255)")
@click.option("--overlay", is_flag=True, help="also write <input name>.overlay.png")
@overwrite_option
@skip_bad_option
@click.option("--device", default="auto", show_default=True, help="auto | cpu | cuda")
@click.option("--params", "params_file", default="params.yaml", show_default=True,
              help="params file, read only for the tau / resolution fallbacks")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE", help="override a param (repeatable)")
def main(checkpoint, input_path, output, tau, resolution, thresholds, engine, batch_size, save_prob, overlay,
         overwrite, skip_bad, device, params_file, overrides):
    with one_line_errors("segment"):
        run(checkpoint, input_path, output, tau, resolution, thresholds, engine, batch_size, save_prob, overlay,
            device, params_file, overrides, overwrite, skip_bad)


if __name__ == "__main__":
    main()
