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
"""

from __future__ import annotations

import logging
import os

import click
import numpy as np
import pandas as pd

from pipeline.artifacts import ZarrWriter, open_artifact, require_same_run, write_parquet
from pipeline.catalog import dvc_path
from pipeline.errors import InputError
from pipeline.params import section
from pipeline.progress import progress
from pipeline.teachers import check_teacher_params
from pipeline.teachers.inputs import ArtifactInputs
from pipeline.teachers.runner import open_runner, parse_shard, shard_rows
from stages._common import stage_command, stage_context

log = logging.getLogger("stages.teacher")

MANIFEST_EXTRAS = ("background", "hard_case", "area_fraction")


def _check_alignment(manifest: pd.DataFrame, images, reference) -> None:
    n = len(manifest)
    ids = [str(i) for i in manifest["image_id"]]
    for art, name in ((images, "image"), (reference, "mask")):
        if art is None:
            continue
        if art[name].shape[0] != n:
            raise InputError(f"{art.path}: {art[name].shape[0]} rows but the manifest has {n}")
        att = art.attrs.get("image_ids")
        if att is not None and [str(i) for i in att] != ids:
            raise InputError(f"{art.path}: attrs image_ids differ from the manifest's image_id order")


def teacher_workers_options(fn):
    """``--workers`` / ``--address``: the teacher's Ray Data executor (teacher stage and label)."""
    fn = click.option("--address", default=None, metavar="ADDRESS",
                      help="Ray cluster to join with --workers (default: RAY_ADDRESS, else an embedded local Ray)")(fn)
    return click.option("--workers", default=0, show_default=True, type=click.IntRange(0),
                        help="teachers in a Ray Data actor pool (one per GPU or CPU worker); 0 = the serial "
                             "loop in this process (same results)")(fn)


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
    man = open_artifact(manifest, "manifest")
    img = open_artifact(images, "images")
    df = man.df.reset_index(drop=True)
    n, h, w = img["image"].shape[:3]
    prompts = list(cfg["prompts"])
    base_prompt = prompts[cfg["base_prompt_index"]]
    vflip_prompt = base_prompt if cfg["vflip_base_prompt"] else None
    run_rows = [i for i, s in enumerate(df["split"].astype(str)) if s in cfg["splits"]]
    extras = [c for c in MANIFEST_EXTRAS if c in df.columns]
    shas = df["sha256"].astype(str).tolist()
    ids = df["image_id"].astype(str).tolist()
    load = ArtifactInputs(images, None, ids, shas, [{c: df.at[row, c] for c in extras} for row in range(n)])
    runner, t_fp = open_runner(cfg, (h, w), device, load, shas, vflip_prompt)
    teacher = runner.teacher
    ref = open_artifact(reference, "reference") if teacher.needs_reference else None
    require_same_run(man, img, ref)
    _check_alignment(df, img, ref)
    if ref is not None:
        load.reference = os.path.abspath(reference)
    if teacher.backend == "simulated":
        log.info("teacher: backend 'simulated' is a SIMULATOR of foundation-model errors that reads the "
                 "synthetic ground truth; it is not a real teacher")
    stats = runner.fill(shard_rows(run_rows, shard_spec), workers=workers, address=address)
    log.info("teacher: computed %d answers on %d images; %d cached answers reused",
             stats.answers_computed, stats.images_computed, stats.cache_hits)
    if shard_spec is not None:
        click.echo(f"teacher shard {shard_spec[0]}/{shard_spec[1]}: cache filled "
                   f"({stats.answers_computed} answers computed); run without --shard to assemble", err=True)
        return

    fp_params = {k: v for k, v in cfg.items() if k != "cache_dir"}  # where the cache lives changes nothing
    inputs = [man, img] + ([ref] if ref is not None else [])
    ctx = stage_context("teacher", __file__, params)
    k = len(prompts)
    run_set = set(run_rows)
    rows = []
    with ZarrWriter(out, ctx.meta("teacher", inputs, params={"teacher": fp_params},
                                  teacher_fingerprint=t_fp)) as zw:
        zw.create("masks", (n, k, h, w), bool)
        zw.create("scores", (n, k), np.float32)
        if vflip_prompt is not None:
            zw.create("vflip_masks", (n, h, w), bool)
            zw.create("vflip_scores", (n,), np.float32)
        for row in progress(range(n), desc="teacher: assembling"):
            if row in run_set:
                masks, sc, vmask, vscore = runner.answers(row)
            else:
                masks, sc = np.zeros((k, h, w), bool), np.zeros(k, np.float32)
                vmask, vscore = np.zeros((h, w), bool), 0.0
            zw.write("masks", row, masks)
            zw.write("scores", row, sc)
            if vflip_prompt is not None:
                zw.write("vflip_masks", row, vmask)
                zw.write("vflip_scores", row, np.float32(vscore))
            areas = masks.reshape(k, -1).mean(axis=1)
            for j in range(k):
                rows.append((ids[row], j, prompts[j], float(sc[j]), bool(sc[j] > 0), float(areas[j]),
                             str(df.at[row, "split"]), row in run_set))
        zw.attrs.update({
            "prompts": prompts, "image_ids": ids, "backend": teacher.backend,
            "simulator": teacher.backend == "simulated", "teacher_fingerprint": t_fp,
            "teacher": teacher.fingerprint(), "splits_run": list(cfg["splits"]),
            "base_prompt_index": cfg["base_prompt_index"], "vflip_prompt": vflip_prompt,
        })
    table = pd.DataFrame(rows, columns=["image_id", "prompt_index", "prompt", "score", "valid", "mask_area",
                                        "split", "ran"])
    table["score"] = table["score"].astype(np.float32)
    table["prompt_index"] = table["prompt_index"].astype(np.int16)
    write_parquet(scores, table, ctx.meta("teacher_scores", inputs, params={"teacher": fp_params},
                                          teacher_fingerprint=t_fp))
    if runner.stats.cache_corrupt:
        log.warning("teacher: %d corrupt cache entries were recomputed while assembling", runner.stats.cache_corrupt)
    log.info("teacher: wrote %s and %s (%d images x %d prompts, backend %s)", out, scores, n, k, teacher.backend)


if __name__ == "__main__":
    main()
