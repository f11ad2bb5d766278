"""``geodistill review export|import``: the human loop on a ``label`` output folder (pipeline/review/)."""

from __future__ import annotations

import click

from pipeline import catalog
from pipeline.deploy.segmenter import Segmenter
from pipeline.review.corrections import FORMATS, import_corrections, read_review
from pipeline.review.export import COCO_SHAPES, LS_RECORD_KEY, LS_SHAPES, export_review, server_env
from pipeline.review.labelstudio import Client, upload_review
from pipeline.review.ranking import DEFAULT_RANKING, RANKINGS
from pipeline.cli.conventions import one_line_errors, overwrite_option, setup_logging, stage_code_version

__all__ = ["main"]


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
@click.option("--image-url", default=None,
              help="prefix of the tasks' image URLs (+ the image's path relative to the labelled folder); "
                   "default: Label Studio local files of the labelled folder (see review upload)")
@overwrite_option
def export_main(label_dir, out, top, ranking, student, ls_shape, coco_shape, image_url, overwrite):
    """Write the images of a label output folder that most need a person, best first.

    A Label Studio import (labelstudio/tasks.json + label_config.xml), a CVAT import
    (cvat/instances_default.json, COCO 1.0) and ranked.csv, under --out only.
    """
    setup_logging()
    with one_line_errors("review export"):
        predict = None
        if student is not None:
            predict = Segmenter.from_bundle(student).predict
        res = export_review(label_dir, out, top=top, ranking=ranking, ls_shape=ls_shape, coco_shape=coco_shape,
                            image_url=image_url, predict=predict, overwrite=overwrite)
        click.echo(f"review export: {len(res.table)} images ranked by {res.ranking} -> {res.out} "
                   f"(export {res.export_id})", err=True)
        layout = read_review(res.out).get(LS_RECORD_KEY)
        if layout:
            env = " ".join(f"{k}={v}" for k, v in server_env(layout).items())
            click.echo(f"review export: serve the images with `{env} label-studio`, then `geodistill review "
                       f"upload {res.out}` (or a Local files storage of path {layout['storage_path']})", err=True)


@review.command(name="upload")
@click.argument("review_dir", metavar="REVIEW_DIR", type=click.Path(file_okay=False))
@click.option("--url", default="http://localhost:8080", show_default=True, envvar="LABEL_STUDIO_URL",
              help="the Label Studio server (env LABEL_STUDIO_URL)")
@click.option("--token", required=True, envvar="LABEL_STUDIO_API_KEY",
              help="your API token: a legacy token or a personal access token (env LABEL_STUDIO_API_KEY)")
@click.option("--title", default=None, help="the project's title (default: geodistill review <export id>)")
def upload_main(review_dir, url, token, title):
    """Create a Label Studio project for a review export through the API.

    Its labelling interface, the Local files storage connection that serves the images, and the tasks; then
    check the first image is served.  Label Studio must run with the two variables review export printed.
    """
    setup_logging()
    with one_line_errors("review upload"):
        res = upload_review(Client(url, token), review_dir, title)
        click.echo(f"review upload: {res['tasks']} tasks -> {url.rstrip('/')}/projects/{res['project']}/data"
                   + (" (images served)" if res["served"] else ""), err=True)


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
    """Read corrected masks into the versioned corrections artifact.

    From a Label Studio JSON export, a CVAT COCO 1.0 export or a folder of PNGs.
    """
    setup_logging()
    with one_line_errors("review import"):
        art = import_corrections(source, review_dir, out, fmt=fmt, code_version=stage_code_version(__file__),
                                 overwrite=overwrite)
        t, n = art.table, len(read_review(review_dir)["images"])
        click.echo(f"review import: {len(t)} corrected masks of the export's {n} images -> {out} (median IoU "
                   f"to the vote {t['iou_to_voted'].median():.3f}; the other {n - len(t)} not corrected)", err=True)


main = review

if __name__ == "__main__":
    main()
