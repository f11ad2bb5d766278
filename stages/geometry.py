"""Stage `geometry`: consensus.zarr + manifest -> geometry.zarr (sdf, skeleton) and gates.parquet
(eq:sdf-target .. eq:reliability-gate), streamed in blocks of images so memory is flat in N."""

from __future__ import annotations

import click
import numpy as np
import pandas as pd

from pipeline.catalog import dvc_path
from pipeline.artifacts import ZarrWriter, open_artifact, write_parquet
from pipeline.errors import InputError
from pipeline.geometry import foreground_agreement, image_gates, median_area, pseudo_targets
from pipeline.params import section
from pipeline.progress import progress
from stages._common import stage_command, stage_context



def read_config(params) -> dict:
    """The geometry section (every constant of eq:sdf-target .. eq:area-gate; validated by the schema)."""
    cfg = section(params, "geometry")
    return cfg


def check_inputs(cons, manifest, n_prompts: int) -> tuple[int, int, int]:
    """Consistency of consensus.zarr with the manifest and params; returns (N, H, W)."""
    agreement, voted, n_valid = cons["agreement"], cons["voted"], cons["n_valid"]
    if agreement.shape != voted.shape or n_valid.shape != voted.shape[:1]:
        raise InputError(f"{cons.path}: agreement {agreement.shape}, voted {voted.shape} and "
                         f"n_valid {n_valid.shape} shapes do not match")
    n, h, w = voted.shape
    prompts = cons.attrs.get("prompts")
    if prompts is None:
        raise InputError(f"{cons.path}: attrs['prompts'] missing (written by the consensus stage)")
    if len(prompts) != n_prompts:
        raise InputError(f"{cons.path}: the teacher used {len(prompts)} prompts but geometry.n_prompts="
                         f"{n_prompts} (eq:valid-prompt-ratio denominator)")
    ids = list(cons.attrs.get("image_ids") or [])
    df = manifest.df
    if len(df) != n or ids != df["image_id"].astype(str).tolist():
        raise InputError(f"{manifest.path}: its {len(df)} image_ids do not match the {n} images of "
                         f"{cons.path} (same rows, same order required; rerun the stages after prepare)")
    return n, h, w


@stage_command("geometry")
@click.option("--consensus", default=dvc_path("consensus"), show_default=True, help="consensus.zarr input")
@click.option("--manifest", default=dvc_path("manifest"), show_default=True, help="manifest (splits)")
@click.option("--out", default=dvc_path("geometry"), show_default=True, help="geometry.zarr output")
@click.option("--gates", default=dvc_path("gates"), show_default=True, help="gates.parquet output")
@click.option("--chunk-images", default=64, show_default=True, type=click.IntRange(1),
              help="images per block (memory only; results do not depend on it)")
def main(params, device, consensus, manifest, out, gates, chunk_images):
    """SDF, skeleton and area targets of the voted pseudo-masks, and the per-image reliability gate."""
    cfg = read_config(params)
    cons = open_artifact(consensus, "consensus")
    man = open_artifact(manifest, "manifest")
    n, h, w = check_inputs(cons, man, cfg["n_prompts"])
    ctx = stage_context("geometry", __file__, params)
    c = np.zeros(n)
    a = np.zeros(n)
    n_valid = np.asarray(cons["n_valid"][...]).astype(np.int64)
    if ((n_valid < 0) | (n_valid > cfg["n_prompts"])).any():
        raise InputError(f"{cons.path}: n_valid outside [0, geometry.n_prompts={cfg['n_prompts']}]")
    with ZarrWriter(out, ctx.meta("geometry", [cons, man])) as wr:
        wr.create("sdf", (n, h, w), np.float32)
        wr.create("skeleton", (n, h, w), bool)
        for s in progress(range(0, n, chunk_images), desc="geometry", total=-(-n // chunk_images)):
            e = min(s + chunk_images, n)
            voted = np.asarray(cons["voted"][s:e])
            agreement = np.asarray(cons["agreement"][s:e])
            empty_votes = (n_valid[s:e] == 0) & voted.reshape(e - s, -1).any(axis=1)
            if empty_votes.any():
                raise InputError(f"{cons.path}: image {s + int(np.argmax(empty_votes))} has no valid prompt "
                                 "but a non-empty voted mask")
            sdf, skel, a[s:e] = pseudo_targets(voted, quantile=cfg["sdf_quantile"], min_scale=cfg["sdf_min_scale"],
                                               min_distance=cfg["skeleton_min_distance"])
            c[s:e] = foreground_agreement(agreement, voted)
            for j in range(e - s):
                wr.write("sdf", s + j, sdf[j])
                wr.write("skeleton", s + j, skel[j])
        wr.attrs.update({"image_ids": list(cons.attrs["image_ids"])})
        split = man.df["split"].astype(str).to_numpy()
        try:
            a0 = median_area(a, split == "train")
        except InputError as err:
            raise InputError(f"{man.path}: {err}") from None
        v, gf = image_gates(c, n_valid, a, a0, cfg)
        table = pd.DataFrame({
            "image_id": man.df["image_id"].astype(str).to_numpy(), "split": split,
            "c": c, "v": v, "a": a, "a0": np.full(n, a0),
            "g_conf": gf.conf, "g_valid": gf.valid, "g_area": gf.area, "g": gf.g,
            "n_valid": n_valid.astype(np.int16)})
        write_parquet(gates, table, ctx.meta("gates", [cons, man]))


if __name__ == "__main__":
    main()
