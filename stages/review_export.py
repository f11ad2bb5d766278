"""Stage review_export: the training images a person should check first, ranked, as ``geodistill review
export`` writes them; it reads no reference mask and feeds no other stage."""

from __future__ import annotations

import click

from pipeline import catalog
from pipeline.artifacts.lineage import require_same_run
from pipeline.artifacts.store import open_artifact
from pipeline.catalog import ARTIFACTS_DIR, dvc_path
from pipeline.params import section
from pipeline.teacher_table import is_simulator
from pipeline.review.export import export_run
from stages._common import stage_command


@stage_command("review_export")
@click.option("--artifacts", "art", default=ARTIFACTS_DIR, show_default=True, type=click.Path(file_okay=False))
@click.option("--out", default=dvc_path("review"), show_default=True, type=click.Path(file_okay=False),
              help="the review folder")
def main(params, device, art, out):
    """Rank the run's training pseudo-masks for a person and export them to Label Studio / CVAT."""
    manifest, consensus, gates = (open_artifact(catalog.path(name, art), name)  # each schema is its catalogue name
                                  for name in ("manifest", "consensus", "gates"))
    require_same_run(manifest, consensus, gates)
    cfg = section(params, "review")
    res = export_run(manifest, consensus, gates, out, top=cfg["top"], ranking=cfg["ranking"],
                     letterbox=bool(section(params, "data")["letterbox"]),
                     simulator=is_simulator(section(params, "teacher")["backend"]))
    click.echo(f"review_export: {len(res.table)} training images ranked by {res.ranking} -> {res.out} "
               f"(export {res.export_id})", err=True)


if __name__ == "__main__":
    main()
