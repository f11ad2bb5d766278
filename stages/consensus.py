"""Stage consensus: teacher.zarr -> consensus.zarr (eq:agreement-map, eq:majority-vote), in blocks of images
so memory is flat in N."""

from __future__ import annotations

import click

from pipeline.artifacts.store import open_artifact
from pipeline.catalog import dvc_path
from pipeline.params import section
from pipeline.pseudo_labels import write_consensus
from stages._common import stage_command, stage_context


@stage_command("consensus")
@click.option("--teacher", default=dvc_path("teacher"), show_default=True, help="teacher.zarr input")
@click.option("--out", default=dvc_path("consensus"), show_default=True, help="consensus.zarr output")
@click.option("--chunk-images", default=32, show_default=True, type=click.IntRange(1),
              help="images per block (memory only; results do not depend on it)")
def main(params, device, teacher, out, chunk_images):
    """Multi-prompt consensus vote: agreement map, voted pseudo-mask and valid-prompt count per image."""
    art = open_artifact(teacher, "teacher")
    ctx = stage_context("consensus", __file__, params)
    write_consensus(art, section(params, "consensus")["vote_threshold"], out,
                    lambda schema: ctx.meta(schema, [art]), chunk_images)


if __name__ == "__main__":
    main()
