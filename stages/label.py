"""``geodistill label INPUT --out DIR``: pseudo-labels of a folder of images (pipeline/labeling/run.py)."""

from __future__ import annotations

import click

from pipeline.api import choose_teacher, with_data_options
from pipeline.labeling import label_folder
from pipeline.labeling.run import parse_formats
from pipeline.params import BACKENDS
from pipeline.profiles import load_params_or_profile
from stages._common import (max_pixels_option, overwrite_option, skip_bad_option, stage_command,
                            teacher_workers_options)


@stage_command("label", default_profile="paper", profile_loader=load_params_or_profile)
@click.argument("input_dir", metavar="INPUT", type=click.Path())
@click.option("--out", required=True, type=click.Path(file_okay=False), help="output folder")
@click.option("--checkpoint", default=None, type=click.Path(),
              help="SAM 3 folder (save_pretrained layout); implies --backend sam3")
@click.option("--backend", type=click.Choice(BACKENDS), default=None,
              help="teacher: sam3 | imported (masks made elsewhere) | simulated (a SIMULATOR; needs --reference-masks)")
@click.option("--imported-dir", default=None, type=click.Path(), help="imported teacher masks (see the README layout)")
@click.option("--reference-masks", default=None, type=click.Path(),
              help="simulated backend only: masks named like the images, read by the SIMULATOR")
@click.option("--format", "formats", default="png,coco,yolo", show_default=True,
              help="comma-separated: png, coco, yolo")
@skip_bad_option
@max_pixels_option
@overwrite_option
@teacher_workers_options
def main(params, device, input_dir, out, checkpoint, backend, imported_dir, reference_masks, formats, skip_bad,
         max_pixels, overwrite, workers, address):
    """Label a folder of images with the multi-prompt teacher: voted pseudo-masks as PNG, COCO (RLE)
    and YOLO segmentation files, a table of agreement c, valid ratio v, area a and gate g per image,
    and a contact sheet.  Without --params the paper's values are used (working resolution 384).
    --workers N runs the teacher on a Ray Data pool of N (same labels).
    Reruns resume from the teacher cache inside OUT; label.json there lists what label wrote, and
    anything else in the way is refused unless --overwrite (docs/own-data.md)."""
    fmts = parse_formats(formats)  # checked before any work
    params = with_data_options(choose_teacher(params, backend, checkpoint, imported_dir), skip_bad, max_pixels)
    result = label_folder(input_dir, out, params, device=device, formats=fmts, reference_masks=reference_masks,
                          overwrite=overwrite, workers=workers, address=address)
    g = result.table["g"]
    click.echo(f"label: {len(result.table)} images -> {result.out} ({', '.join(result.formats)}); "
               f"gate g median {g.median():.3f}, {int((g > 0).sum())} with g > 0"
               + ("; backend simulated is a SIMULATOR" if result.simulator else ""), err=True)
    if result.skipped_line:
        click.echo(result.skipped_line, err=True)


if __name__ == "__main__":
    main()
