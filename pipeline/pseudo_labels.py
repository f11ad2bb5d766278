"""The consensus and geometry stages' work, callable without the CLI: the pseudo-label artifacts.

* :func:`write_consensus`: teacher.zarr -> consensus.zarr (agreement, voted, n_valid, and the prompt
  disagreement h of :func:`pipeline.consensus.agreement_entropy`; eq:agreement-map,
  eq:majority-vote, :mod:`pipeline.consensus`);
* :func:`write_geometry`: consensus.zarr + manifest -> geometry.zarr (sdf, skeleton; eq:sdf-target) and
  the gates table (eq:foreground-agreement .. eq:reliability-gate, :mod:`pipeline.geometry`).

Both stream blocks of images, so memory is flat in N; the block size changes nothing in the results.
Each takes opened artifacts and ``meta(schema)``, the stamp of each output (the stage's provenance).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import pandas as pd

from pipeline.artifacts import Meta, ZarrWriter, write_parquet
from pipeline.consensus import vote_batch
from pipeline.errors import InputError
from pipeline.geometry import (GateFactors, NoForeground, foreground_agreement, image_gates, median_area,
                               pseudo_targets)
from pipeline.progress import progress
from pipeline.consensus import agreement_entropy


# --------------------------------------------------------------------------------------------------
# consensus
# --------------------------------------------------------------------------------------------------
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


def write_consensus(teacher, threshold: float, out: str | Path, meta: Callable[[str], Meta],
                    chunk_images: int = 32) -> None:
    """consensus.zarr from the opened teacher artifact: the vote at ``threshold`` (``consensus.vote_threshold``)."""
    n, k, h, w = check_teacher(teacher)
    with ZarrWriter(out, meta("consensus")) as wr:
        wr.create("agreement", (n, h, w), np.float32)
        wr.create("voted", (n, h, w), bool)
        wr.create("n_valid", (n,), np.int16)
        wr.create("h", (n,), np.float64)   # the prompt disagreement label records (pipeline.consensus.agreement_entropy)
        for s in progress(range(0, n, chunk_images), desc="consensus", total=-(-n // chunk_images)):
            e = min(s + chunk_images, n)
            try:
                c = vote_batch(teacher["masks"][s:e], teacher["scores"][s:e], threshold)
            except InputError as err:
                raise InputError(f"{teacher.path} (images {s}..{e - 1}): {err}") from None
            n_valid = c.n_valid
            h = agreement_entropy(c.agreement)   # of the stored float32 map, as label computes it
            for j in range(e - s):
                wr.write("agreement", s + j, c.agreement[j])
                wr.write("voted", s + j, c.voted[j])
                wr.write("n_valid", s + j, n_valid[j])
                wr.write("h", s + j, h[j])
        wr.attrs.update({"image_ids": list(teacher.attrs["image_ids"]), "prompts": list(teacher.attrs["prompts"])})


# --------------------------------------------------------------------------------------------------
# geometry
# --------------------------------------------------------------------------------------------------
def check_consensus(cons, manifest, n_prompts: int) -> tuple[int, int, int]:
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


def gate_table(image_ids: np.ndarray, split: np.ndarray, c: np.ndarray, v: np.ndarray, a: np.ndarray, a0: float,
               gates: GateFactors, n_valid: np.ndarray) -> pd.DataFrame:
    """The gates table, one row per image: c, v, a, a0 and the factors of g (eq:reliability-gate)."""
    return pd.DataFrame({
        "image_id": image_ids, "split": split,
        "c": c, "v": v, "a": a, "a0": np.full(len(c), a0),
        "g_conf": gates.conf, "g_valid": gates.valid, "g_area": gates.area, "g": gates.g,
        "n_valid": n_valid.astype(np.int16)})


def write_geometry(cons, manifest, cfg: Mapping[str, Any], out: str | Path, gates: str | Path,
                   meta: Callable[[str], Meta], chunk_images: int = 64) -> pd.DataFrame:
    """geometry.zarr (sdf, skeleton of each voted mask) and the gates table from the opened consensus
    and manifest artifacts; ``cfg`` is the ``geometry:`` section.  Returns the gates table.

    a0 (eq:area-gate) is the median pseudo-area of the training split's images."""
    n_prompts = cfg["n_prompts"]
    n, h, w = check_consensus(cons, manifest, n_prompts)
    c = np.zeros(n)
    a = np.zeros(n)
    n_valid = np.asarray(cons["n_valid"][...]).astype(np.int64)
    if ((n_valid < 0) | (n_valid > n_prompts)).any():
        raise InputError(f"{cons.path}: n_valid outside [0, geometry.n_prompts={n_prompts}]")
    with ZarrWriter(out, meta("geometry")) as wr:
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
        split = manifest.df["split"].astype(str).to_numpy()
        try:
            a0 = median_area(a, split == "train")
        except NoForeground:
            raise  # said in the user's terms, no file to name
        except InputError as err:
            raise InputError(f"{manifest.path}: {err}") from None
        v, gf = image_gates(c, n_valid, a, a0, cfg)
        table = gate_table(manifest.df["image_id"].astype(str).to_numpy(), split, c, v, a, a0, gf, n_valid)
        write_parquet(gates, table, meta("gates"))
    return table
