"""Stage geometry: consensus.zarr -> geometry.zarr (sdf, skeleton) and gates.parquet (eq:sdf-target ..
eq:reliability-gate), in blocks of images so memory is flat in N."""

from __future__ import annotations

import click

from pipeline.artifacts.store import open_artifact
from pipeline.catalog import dvc_path
from pipeline.params import section
from pipeline.pseudo_labels import write_geometry
from stages._common import stage_command, stage_context


@stage_command("geometry")
@click.option("--consensus", default=dvc_path("consensus"), show_default=True, help="consensus.zarr input")
@click.option("--manifest", default=dvc_path("manifest"), show_default=True, help="manifest (splits)")
@click.option("--out", default=dvc_path("geometry"), show_default=True, help="geometry.zarr output")
@click.option("--gates", default=dvc_path("gates"), show_default=True, help="gates.parquet output")
@click.option("--chunk-images", default=64, show_default=True, type=click.IntRange(1),
              help="images per block (memory only; results do not depend on it)")
def main(params, device, consensus, manifest, out, gates, chunk_images):
    """SDF, skeleton and area targets of the voted pseudo-masks, and the per-image reliability gate."""
    cfg = section(params, "geometry")  # every constant of eq:sdf-target .. eq:area-gate (validated by the schema)
    cons = open_artifact(consensus, "consensus")
    man = open_artifact(manifest, "manifest")
    ctx = stage_context("geometry", __file__, params)
    write_geometry(cons, man, cfg, out, gates, lambda schema: ctx.meta(schema, [cons, man]), chunk_images)


if __name__ == "__main__":
    main()
