"""Stage teacher: six-prompt teacher masks and scores for every image (eq:prompt-set, eq:teacher-prediction),
through a content-addressed cache; ``--workers`` runs it on Ray, ``--shard i/n`` only fills the cache
(docs/real-data.md)."""

from __future__ import annotations

import click

from pipeline.artifacts.store import open_artifact
from pipeline.catalog import dvc_path
from pipeline.params import section
from pipeline.teachers import check_teacher_params
from pipeline.teachers.assemble import fingerprint_params, open_teacher_run
from pipeline.teachers.runner import parse_shard, shard_rows
from stages._common import stage_command, stage_context, teacher_workers_options


@stage_command("teacher")
@click.option("--manifest", default=dvc_path("manifest"), show_default=True)
@click.option("--images", default=dvc_path("images"), show_default=True)
@click.option("--reference", default=dvc_path("reference"), show_default=True,
              help="read only by the simulated teacher (synthetic ground truth)")
@click.option("--out", default=dvc_path("teacher"), show_default=True)
@click.option("--scores", default=dvc_path("teacher_scores"), show_default=True)
@click.option("--shard", default=None, metavar="I/N",
              help="fill the cache for shard I of N (0-based) only; writes no artifact")
@teacher_workers_options
def main(params, device, manifest, images, reference, out, scores, shard, workers, address):
    """Six-prompt teacher masks and scores (cached per image and prompt); --shard i/n fills the cache only."""
    cfg = check_teacher_params(section(params, "teacher"))
    shard_spec = parse_shard(shard)
    run = open_teacher_run(cfg, open_artifact(manifest, "manifest"), open_artifact(images, "images"), reference,
                           device)
    stats = run.fill(shard_rows(run.rows, shard_spec), workers=workers, address=address)
    if shard_spec is not None:
        click.echo(f"teacher shard {shard_spec[0]}/{shard_spec[1]}: cache filled "
                   f"({stats.answers_computed} answers computed); run without --shard to assemble", err=True)
        return
    ctx = stage_context("teacher", __file__, params)
    run.write(out, scores, lambda schema: ctx.meta(schema, run.inputs, params={"teacher": fingerprint_params(cfg)},
                                                   teacher_fingerprint=run.fingerprint))


if __name__ == "__main__":
    main()
