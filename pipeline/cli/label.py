"""``geodistill label INPUT --out DIR``: pseudo-labels of a folder of images (pipeline/labeling/run.py)."""

from __future__ import annotations

import contextlib
import json
import logging
import os

import click

from pipeline.api import choose_teacher, with_data_options
from pipeline.runtime.errors import CLI
from pipeline.geometry import NoForeground
from pipeline.labeling import label_folder
from pipeline.labeling.run import LABEL_FORMATS, OUTPUTS, parse_formats
from pipeline.teacher_table import FORMAT_GROUP
from pipeline.profiles import load_params_or_profile
from pipeline.runtime.progress import quiet_bars
from pipeline.cli.conventions import (bit_depth_option, max_pixels_option, overwrite_option, quiet_option,
                                      skip_bad_option, stage_command, teacher_choice_options, teacher_workers_options)

__all__ = ["main", "summary_line"]


@stage_command("label", default_profile="paper", profile_loader=load_params_or_profile)
@click.argument("input_dir", metavar="INPUT", type=click.Path())
@click.option("--out", required=True, type=click.Path(file_okay=False), help="output folder")
@teacher_choice_options()
@click.option("--reference-masks", default=None, type=click.Path(),
              help="simulated backend only: masks named like the images, read by the SIMULATOR")
@click.option("--format", "formats", default=None,
              help=f"comma-separated, of {', '.join(LABEL_FORMATS)} or a plug-in's (entry points {FORMAT_GROUP}) "
                   f"(default: {','.join(parse_formats())})")
@click.option("--copy-images", is_flag=True,
              help="yolo/images holds copies of the inputs (default: relative links, which survive moving the "
                   "input and output folders together)")
@quiet_option
@skip_bad_option
@max_pixels_option
@bit_depth_option
@overwrite_option
@teacher_workers_options
def main(params, device, input_dir, out, backend, reference_masks, formats, copy_images, quiet, skip_bad, max_pixels,
         bit_depth, overwrite, workers, address, **folders):
    """Label a folder of images with the multi-prompt teacher.

    Voted pseudo-masks as PNG, COCO (RLE) and YOLO files, a table of agreement c, valid ratio v, area a and
    gate g per image, and a contact sheet.  Without --params the paper's values are used.  Reruns resume from
    the teacher cache inside OUT; a file of yours where an output goes is refused by name (docs/own-data.md).
    The step log: GEODISTILL_LOG=INFO.
    """
    fmts = parse_formats(formats)  # checked before any work
    params = with_data_options(choose_teacher(params, backend, folders), skip_bad, max_pixels, bit_depth)
    with quiet_bars(quiet), _step_log_off():  # -q keeps the cost lines: they are the summary's
        result = label_folder(input_dir, out, params, device=device, formats=fmts, reference_masks=reference_masks,
                              overwrite=overwrite, workers=workers, address=address, copy_images=copy_images,
                              report=lambda line: click.echo(line, err=True))
    click.echo(summary_line(result), err=True)
    if (line := empty_line(result)) is not None:
        click.echo(line, err=True)
    if result.skipped_line:
        click.echo(result.skipped_line, err=True)


@contextlib.contextmanager
def _step_log_off():
    """Turn the INFO step log off (warnings stay) unless GEODISTILL_LOG names a level: the summary line says it."""
    logger = logging.getLogger("pipeline")
    before = logger.level
    if "GEODISTILL_LOG" not in os.environ:
        logger.setLevel(max(logging.WARNING, logger.getEffectiveLevel()))
    try:
        yield
    finally:
        logger.setLevel(before)


def empty_line(result) -> str | None:
    """Return the summary's plain word when every mask is empty (still exit 0), with the likely causes; else None."""
    if len(result.table) and not (result.table["mask_pixels"] > 0).any():
        return f"label: all {len(result.table)} masks are empty. {NoForeground().render(CLI)}"
    return None


def summary_line(result) -> str:
    """Return the command's one summary line: images, formats, the teacher's work, the gates, the YOLO split.

    Parameters
    ----------
    result : pipeline.labeling.LabelResult
        What ``label`` wrote; its label.json is read for the teacher's work.

    Returns
    -------
    str
        The parts joined by "; ": images and formats, teacher answers computed and cached (and the measured
        seconds per image), the gate g's median and count above 0, each format's own summary, the teacher's
        note, and the SIMULATOR's name where the backend is one.
    """
    record = json.loads((result.out / OUTPUTS["record"]).read_text())
    g = result.table["g"]
    parts = [f"label: {len(result.table)} images -> {result.out} ({', '.join(result.formats)})",
             f"teacher answers {record['teacher_answers_computed']} computed, {record['teacher_cache_hits']} cached"
             + (f" ({record['teacher_seconds_per_image']:.2f} s per image"
                + (f" on {record['teacher_path']}" if record.get("teacher_path") else "")
                + f", measured on {record['teacher_images_timed']:.3g})"
                if record.get("teacher_seconds_per_image") is not None else ""),
             f"gate g median {g.median():.3f}, {int((g > 0).sum())} with g > 0"]
    parts += [LABEL_FORMATS[f].summary(result.out, len(result.table)) for f in result.formats
              if LABEL_FORMATS[f].summary]
    if record.get("teacher_note"):
        parts.append(record["teacher_note"])
    if result.simulator:
        parts.append(f"backend {result.backend} is a SIMULATOR")
    return "; ".join(parts)


if __name__ == "__main__":
    main()
