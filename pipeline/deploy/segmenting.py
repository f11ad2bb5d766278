"""``geodistill segment``'s logic: binary masks M = [P >= tau] (eq:inference-mask) for image files, each at
its own size, with a checkpoint or a deploy bundle (``pipeline/cli/segment.py`` is its wiring)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Callable, Mapping

from pipeline.datasets.loading import BadFileError, check_bit_depth, pixel_limit, reset_frame_warnings
from pipeline.datasets.manifest import BadInputPolicy, write_skipped_csv
from pipeline.datasets.scan import scan_inputs
from pipeline.runtime.device import resolve_device
from pipeline.engine_table import AUTO
from pipeline.runtime.errors import CHECKPOINT, InputError
from pipeline.artifacts.ownership import claim_outputs
from pipeline.thresholds import MIN_RESOLUTION, RESOLUTION_LABELS, resolve_resolution


def _stderr(line: str) -> None:
    print(line, file=sys.stderr)


def check_options(checkpoint, input_path, output, batch_size: int, resolution: int | None) -> None:
    """InputError naming the first missing or invalid option."""
    if not checkpoint:
        raise InputError("{} missing: a checkpoint directory or a deploy bundle (geodistill export)", CHECKPOINT)
    if not input_path:
        raise InputError("--input missing: an image file or a folder of images")
    if not output:
        raise InputError("--output missing: a folder for the masks")
    if batch_size < 1:
        raise InputError(f"--batch-size {batch_size}: must be >= 1")
    if resolution is not None and resolution < MIN_RESOLUTION:
        raise InputError(f"--resolution {resolution}: must be >= {MIN_RESOLUTION}")


def segment_images(checkpoint, input_path, output, *, tau: float | None = None, resolution: int | None = None,
                   thresholds=None, engine: str = AUTO, batch_size: int = 8, save_prob: bool = False,
                   overlay: bool = False, device="auto", params: Mapping | None = None, overwrite: bool = False,
                   skip_bad: bool = False, max_pixels: int | None = None, echo: Callable[[str], None] = _stderr,
                   workers: int | None = None, bit_depth: str | int | None = None, quiet: bool = False):
    """Segment one image file or a folder; :func:`pipeline.deploy.files.segment_files`' result.  The inputs are
    found and every output planned before anything is written; tau as :func:`pipeline.thresholds.resolve_tau`
    (``params``: the fixed tau); the resolution given or recorded, never guessed; ``workers``: reader threads
    (0: the serial loop, the same bytes); ``bit_depth``: None = what the bundle records; ``quiet``: only
    warnings, errors and the summary line on ``echo``."""
    from pipeline.deploy import files as F  # torch
    from pipeline.deploy.segmenter import load_segmenter

    check_options(checkpoint, input_path, output, batch_size, resolution)
    if workers is not None and workers < 0:
        raise InputError(f"workers={workers}: must be >= 0 (0 = the serial loop)")
    found = scan_inputs(input_path)
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

    max_pixels = pixel_limit(max_pixels)
    for path, reason in found.skipped:  # links and special files: before anything is written
        policy.report(image_id(path), path, reason)
    for path, reason in found.unused:  # not images (hidden files, other types): listed, not an error
        policy.record(image_id(path), path, reason)

    seg = load_segmenter(checkpoint, engine, resolve_device(device), thresholds, params=params)
    if bit_depth is not None:
        seg.bit_depth = check_bit_depth(bit_depth)
    reset_frame_warnings()  # once per run
    tau, source = seg.resolve_tau(option=tau)
    resolution, res_source = model_resolution(seg.resolution, resolution, checkpoint, echo)

    def report(path, reason, error):  # raises without --skip-bad, naming the option in the caller's terms
        if isinstance(error, BadFileError):
            policy.report_error(image_id(path), error)
        else:
            policy.report(image_id(path), path, reason)

    info = (lambda line: None) if quiet else echo
    info(f"segment: engine {seg.engine}" + (" (auto)" if engine == AUTO else "")
         + f", {len(files)} image(s), {resolution}px ({res_source}), tau={tau:.4g} ({source})")
    claim_outputs(output, F.relative_outputs(output, stems, suffixes), F.RECORD, "segment",
                  {"input": str(Path(input_path).absolute()), "checkpoint": str(Path(checkpoint).absolute())})
    result = F.segment_files(seg, files, stems, tau=tau, resolution=resolution, batch_size=batch_size,
                             save_prob=save_prob, overlay=overlay, on_skip=report, max_pixels=max_pixels,
                             **({} if workers is None else {"workers": workers}))
    listing = Path(output) / F.SKIPPED_CSV
    write_skipped_csv(listing, policy.rows())
    F.write_confidence_csv(Path(output) / F.CONFIDENCE_CSV, Path(output).absolute().resolve(), result.written,
                           result.scores)
    lowest = (f" (lowest {min(result.scores):.3f}: {result.written[result.scores.index(min(result.scores))].name})"
              if result.scores else "")
    echo(f"segment: wrote {len(result.written)} mask(s) to {output}; per-frame confidence in "
         f"{F.CONFIDENCE_CSV}{lowest}")
    if (line := policy.summary("segment", listing)) is not None:
        echo(line)
    if not result.written:
        raise InputError(f"--input {input_path}: none of the {len(files)} file(s) could be read")
    n = len(result.written)
    info(f"segment: timing: engine {seg.engine}, {1e3 * result.model_seconds / n:.2f} ms/image in the model, "
         f"{1e3 * result.total_seconds / n:.2f} ms/image end to end ({n} images, batch {batch_size}, "
         f"{resolution}px)")
    return result


def model_resolution(trained: int | None, option: int | None, checkpoint,
                     echo: Callable[[str], None] = _stderr) -> tuple[int, str]:
    """(resolution, source): ``option`` (--resolution, with a warning when it differs) > the recorded one."""
    from pipeline.deploy.bundle import DEPLOY_JSON, is_deploy_bundle

    recorded_in = f"{Path(checkpoint) / DEPLOY_JSON}" if is_deploy_bundle(checkpoint) else f"checkpoint {checkpoint}"
    if trained is not None:  # a recorded resolution is checked even when --resolution overrides it
        resolve_resolution(recorded=(trained, recorded_in))
    resolution, res_source = resolve_resolution(
        option=option, recorded=(trained, recorded_in),
        missing=f"--checkpoint {checkpoint}: records no training resolution; pass --resolution N "
                "(the image size the model was trained at)")
    if res_source == RESOLUTION_LABELS["option"] and trained is not None and resolution != trained:
        echo(f"segment: warning: --resolution {resolution} differs from the {trained}px the model was "
             f"trained at ({recorded_in})")
    return resolution, res_source
