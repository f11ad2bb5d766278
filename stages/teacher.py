"""Stage teacher: six-prompt teacher masks and scores for every image (eq:prompt-set, eq:teacher-prediction).

Normal run (what ``dvc repro`` calls): fill the content-addressed cache with whatever is missing, then
assemble ``teacher.zarr`` + ``teacher_scores.parquet`` from it::

    python -m stages.teacher --manifest artifacts/manifest.parquet --images artifacts/images.zarr \\
        --reference artifacts/reference.zarr --out artifacts/teacher.zarr --scores artifacts/teacher_scores.parquet

``--workers N`` runs the teacher as a Ray Data pipeline (:mod:`pipeline.teachers.distributed`, the
``cluster`` extra): CPU workers read the images, an actor pool of N teachers (one per GPU, or per CPU
worker without GPUs) fills the cache with the same per-batch function as the serial loop, then this
process assembles the artifacts; ``--address`` joins a running Ray cluster (e.g. on SLURM, see
docs/real-data.md), otherwise Ray runs embedded and local.  Without ``--workers`` (or with 0) the
serial loop runs in this process, no Ray needed; both give the same cache and the same artifacts.

``--shard i/n`` (0 <= i < n) only fills the cache for shard i's images and writes no artifact (the
former way to split the work over a SLURM array; Ray with ``--workers`` replaces it)::

    srun python -m stages.teacher --shard ${SLURM_ARRAY_TASK_ID}/${SLURM_ARRAY_TASK_COUNT} --device cuda
    # afterwards, once (computes nothing that the shards cached, writes the artifacts):
    dvc repro teacher

Artifacts (manifest row order, N = all manifest rows):
  teacher.zarr  ``masks`` bool [N,K,H,W], ``scores`` float32 [N,K]; with ``teacher.vflip_base_prompt``
  also ``vflip_masks`` bool [N,H,W] / ``vflip_scores`` float32 [N] (base prompt on the vertically
  flipped image, mask flipped back; annotation-free-style control).  attrs: prompts, image_ids,
  backend, teacher_fingerprint, simulator (true for the simulated backend), splits_run, base_prompt_index.
  teacher_scores.parquet  one row per (image, prompt): image_id, prompt_index, prompt, score, valid,
  mask_area (foreground fraction of the frame, eq:pseudo-area applied to M_ik), plus split and ran.

Rows whose split is not in ``teacher.splits`` are not sent to the teacher: their masks are empty,
their scores 0 (all prompts invalid, so eq:valid-set is empty and the gate is 0) and ``ran`` is false
in teacher_scores.parquet.  By default all three splits run: train images for distillation,
validation and test images for the teacher-quality analysis.

Wiring only: the work is :mod:`pipeline.teachers.assemble` (open the run, fill the cache, write).
"""

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
