"""``geodistill review export|import``: the human loop on a ``label`` output folder (pipeline/review/)."""

from __future__ import annotations

import click

from pipeline import catalog
from pipeline.deploy.segmenter import Segmenter
from pipeline.review.corrections import FORMATS, import_corrections
from pipeline.review.export import COCO_SHAPES, DEFAULT_IMAGE_URL, LS_SHAPES, export_review
from pipeline.review.ranking import DEFAULT_RANKING, RANKINGS
from stages._common import one_line_errors, overwrite_option, setup_logging, stage_code_version


@click.group(name="review")
def review():
    """Rank the pseudo-masks a person should check, export them to Label Studio / CVAT, and read the
    corrected masks back (docs/own-data.md, "Review and correct")."""


@review.command(name="export")
@click.argument("label_dir", metavar="LABEL_DIR", type=click.Path())
@click.option("--out", required=True, type=click.Path(file_okay=False), help="output folder")
@click.option("--top", type=int, default=None, metavar="N", help="export the N best candidates (default: all)")
@click.option("--ranking", type=click.Choice(list(RANKINGS)), default=DEFAULT_RANKING, show_default=True,
              help="combined: mean percentile rank of low gate g and high prompt disagreement h (and the "
                   "student disagreement with --student); gate; disagreement; student")
@click.option("--student", default=None, type=click.Path(), metavar="BUNDLE",
              help="a deploy bundle (RUN/artifacts/deploy): adds the student-teacher disagreement")
@click.option("--ls-shape", type=click.Choice(LS_SHAPES), default="brush", show_default=True,
              help="Label Studio pre-annotation: brush (exact) or polygon")
@click.option("--coco-shape", type=click.Choice(COCO_SHAPES), default="rle", show_default=True,
              help="CVAT COCO 1.0 segmentation: rle (exact) or polygon")
@click.option("--image-url", default=DEFAULT_IMAGE_URL, show_default=True,
              help="prefix of the tasks' image URLs (+ the image's path relative to the labelled folder)")
@overwrite_option
def export_main(label_dir, out, top, ranking, student, ls_shape, coco_shape, image_url, overwrite):
    """Write the images of a label output folder that most need a person, best first: a Label Studio
    import (labelstudio/tasks.json + label_config.xml), a CVAT import (cvat/instances_default.json, COCO
    1.0) and ranked.csv, under --out only."""
    setup_logging()
    with one_line_errors("review export"):
        predict = None
        if student is not None:
            predict = Segmenter.from_bundle(student).predict
        res = export_review(label_dir, out, top=top, ranking=ranking, ls_shape=ls_shape, coco_shape=coco_shape,
                            image_url=image_url, predict=predict, overwrite=overwrite)
        click.echo(f"review export: {len(res.table)} images ranked by {res.ranking} -> {res.out} "
                   f"(export {res.export_id})", err=True)


@review.command(name="import")
@click.argument("source", metavar="SOURCE", type=click.Path())
@click.option("--review", "review_dir", required=True, type=click.Path(file_okay=False),
              help="the review export folder the corrections belong to")
@click.option("--out", default=str(catalog.path("corrections")), show_default=True, type=click.Path(dir_okay=False),
              help="the corrections artifact (Parquet)")
@click.option("--from", "fmt", type=click.Choice(FORMATS), default="auto", show_default=True,
              help="labelstudio (JSON export), cvat (COCO 1.0 export), png (a folder of <image id>.png)")
@overwrite_option
def import_main(source, review_dir, out, fmt, overwrite):
    """Read corrected masks (a Label Studio JSON export, a CVAT COCO 1.0 export or a folder of PNGs) into
    the versioned corrections artifact."""
    setup_logging()
    with one_line_errors("review import"):
        art = import_corrections(source, review_dir, out, fmt=fmt, code_version=stage_code_version(__file__),
                                 overwrite=overwrite)
        t = art.table
        click.echo(f"review import: {len(t)} corrected masks -> {out} (median IoU to the vote "
                   f"{t['iou_to_voted'].median():.3f})", err=True)


main = review

if __name__ == "__main__":
    main()
