"""Stage `consensus`: teacher.zarr -> consensus.zarr (agreement, voted, n_valid), eq:agreement-map and
eq:majority-vote, streamed in blocks of images so memory is flat in N."""

from __future__ import annotations

import click
import numpy as np

from pipeline.catalog import dvc_path
from pipeline.artifacts import ZarrWriter, open_artifact
from pipeline.consensus import vote_batch
from pipeline.errors import InputError
from pipeline.params import section
from pipeline.progress import progress
from stages._common import stage_command, stage_context



def check_teacher(teacher) -> tuple[int, int, int, int]:
    """Shape and attribute checks of a teacher artifact; returns (N, K, H, W)."""
    masks, scores = teacher["masks"], teacher["scores"]
    n, k, h, w = masks.shape
    if scores.shape != (n, k):
        raise InputError(f"{teacher.path}: scores shape {scores.shape} does not match masks {masks.shape} (want {(n, k)})")
    prompts = teacher.attrs.get("prompts")
    if prompts is None:
        raise InputError(f"{teacher.path}: attrs['prompts'] missing")
    if len(prompts) != k:
        raise InputError(f"{teacher.path}: {k} prompt masks per image but attrs['prompts'] lists {len(prompts)} prompts")
    ids = teacher.attrs.get("image_ids")
    if ids is None or len(ids) != n:
        raise InputError(f"{teacher.path}: attrs['image_ids'] must list the {n} images")
    return n, k, h, w


@stage_command("consensus")
@click.option("--teacher", default=dvc_path("teacher"), show_default=True, help="teacher.zarr input")
@click.option("--out", default=dvc_path("consensus"), show_default=True, help="consensus.zarr output")
@click.option("--chunk-images", default=32, show_default=True, type=click.IntRange(1),
              help="images per block (memory only; results do not depend on it)")
def main(params, device, teacher, out, chunk_images):
    """Multi-prompt consensus vote: agreement map, voted pseudo-mask and valid-prompt count per image."""
    cfg = section(params, "consensus")
    threshold = cfg["vote_threshold"]
    art = open_artifact(teacher, "teacher")
    n, k, h, w = check_teacher(art)
    meta = stage_context("consensus", __file__, params).meta("consensus", [art])
    with ZarrWriter(out, meta) as wr:
        wr.create("agreement", (n, h, w), np.float32)
        wr.create("voted", (n, h, w), bool)
        wr.create("n_valid", (n,), np.int16)
        for s in progress(range(0, n, chunk_images), desc="consensus", total=-(-n // chunk_images)):
            e = min(s + chunk_images, n)
            try:
                c = vote_batch(art["masks"][s:e], art["scores"][s:e], threshold)
            except InputError as err:
                raise InputError(f"{art.path} (images {s}..{e - 1}): {err}") from None
            n_valid = c.n_valid
            for j in range(e - s):
                wr.write("agreement", s + j, c.agreement[j])
                wr.write("voted", s + j, c.voted[j])
                wr.write("n_valid", s + j, n_valid[j])
        wr.attrs.update({"image_ids": list(art.attrs["image_ids"]), "prompts": list(art.attrs["prompts"])})


if __name__ == "__main__":
    main()
