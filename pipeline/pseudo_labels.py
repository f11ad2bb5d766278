"""The consensus and geometry stages' work, callable without the CLI.

teacher.zarr -> consensus.zarr (:func:`write_consensus`), and consensus.zarr + manifest -> geometry.zarr and
the gates table (:func:`write_geometry`), streamed in blocks of images.  ``geodistill label`` calls the same
:func:`vote_block` and :func:`reliability_gates`, so its masks and gates are the DAG's.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Mapping, NamedTuple

import numpy as np
import pandas as pd

from pipeline.artifacts.lineage import Meta
from pipeline.artifacts.store import ZarrWriter, write_parquet
from pipeline.consensus import Consensus, agreement_entropy, vote_batch
from pipeline.runtime.errors import InputError
from pipeline.geometry import GateFactors, NoForeground, foreground_agreement, image_gates, median_area, pseudo_targets
from pipeline.runtime.progress import progress

__all__ = ["vote_block", "write_consensus", "Gates", "reliability_gates", "gate_columns", "write_geometry"]


def check_teacher(teacher) -> tuple[int, int, int, int]:
    """Check the shapes and attributes of a teacher artifact.

    Parameters
    ----------
    teacher : pipeline.artifacts.store.ZarrArtifact
        The opened teacher.zarr (``masks`` [N,K,H,W], ``scores`` [N,K], attrs ``prompts`` and ``image_ids``).

    Returns
    -------
    tuple of int
        (N, K, H, W).

    Raises
    ------
    InputError
        ``scores`` does not match ``masks``, or ``prompts`` or ``image_ids`` is missing or of the wrong length.
    """
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


def vote_block(masks: np.ndarray, scores: np.ndarray, threshold: float) -> tuple[Consensus, np.ndarray]:
    """Vote a block of images (eq:agreement-map, eq:majority-vote) and measure their prompt disagreement.

    Parameters
    ----------
    masks : array_like
        Prompt masks, bool or 0/1 [N,K,H,W].
    scores : array_like
        Teacher scores [N,K].
    threshold : float
        The vote threshold (``consensus.vote_threshold``).

    Returns
    -------
    tuple
        (:class:`pipeline.consensus.Consensus`, h float64 [N]): h is
        :func:`pipeline.consensus.agreement_entropy` of the stored float32 map.

    Raises
    ------
    InputError
        As :func:`pipeline.consensus.vote_batch`.
    """
    c = vote_batch(masks, scores, threshold)
    return c, agreement_entropy(c.agreement)


def write_consensus(teacher, threshold: float, out: str | Path, meta: Callable[[str], Meta],
                    chunk_images: int = 32) -> None:
    """Write consensus.zarr (``agreement``, ``voted``, ``n_valid``, ``h``) from the opened teacher artifact.

    Parameters
    ----------
    teacher : pipeline.artifacts.store.ZarrArtifact
        The opened teacher.zarr.
    threshold : float
        The vote threshold.
    out : str or Path
        The consensus.zarr path, replaced atomically.
    meta : callable
        Schema name -> :class:`pipeline.artifacts.lineage.Meta` of the artifact.
    chunk_images : int, optional
        Images per block (default 32).

    Raises
    ------
    InputError
        The teacher artifact is inconsistent (:func:`check_teacher`) or a block's vote fails, naming the
        artifact and the block's images.
    """
    n, k, h, w = check_teacher(teacher)
    with ZarrWriter(out, meta("consensus")) as wr:
        wr.create("agreement", (n, h, w), np.float32)
        wr.create("voted", (n, h, w), bool)
        wr.create("n_valid", (n,), np.int16)
        wr.create("h", (n,), np.float64)
        for s in progress(range(0, n, chunk_images), desc="consensus", total=-(-n // chunk_images)):
            e = min(s + chunk_images, n)
            try:
                c, h = vote_block(teacher["masks"][s:e], teacher["scores"][s:e], threshold)
            except InputError as err:
                raise InputError(f"{teacher.path} (images {s}..{e - 1}): {err}") from None
            n_valid = c.n_valid
            for j in range(e - s):
                wr.write("agreement", s + j, c.agreement[j])
                wr.write("voted", s + j, c.voted[j])
                wr.write("n_valid", s + j, n_valid[j])
                wr.write("h", s + j, h[j])
        wr.attrs.update({"image_ids": list(teacher.attrs["image_ids"]), "prompts": list(teacher.attrs["prompts"])})


def check_consensus(cons, manifest, n_prompts: int) -> tuple[int, int, int]:
    """Check consensus.zarr against the manifest and the params.

    Parameters
    ----------
    cons : pipeline.artifacts.store.ZarrArtifact
        The opened consensus.zarr.
    manifest : pipeline.artifacts.store.TableArtifact
        The opened manifest (``image_id`` in the consensus's order).
    n_prompts : int
        ``geometry.n_prompts``, the denominator of eq:valid-prompt-ratio.

    Returns
    -------
    tuple of int
        (N, H, W).

    Raises
    ------
    InputError
        The arrays' shapes disagree, ``prompts`` is missing or not ``n_prompts`` long, or the manifest's image ids
        differ from the consensus's.
    """
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


class Gates(NamedTuple):
    """The reliability gates of a set of images.

    Attributes
    ----------
    a0 : float
        The area reference (0.0 when ``missing``).
    v : numpy.ndarray
        Valid-prompt ratio per image.
    factors : pipeline.geometry.GateFactors
        The gate factors and g per image.
    missing : bool
        Whether no training image had foreground (a0 could not be measured).
    """

    a0: float
    v: np.ndarray
    factors: GateFactors
    missing: bool


def reliability_gates(c, n_valid, a, is_train, geo: Mapping[str, Any]) -> Gates:
    """Compute the gate of every image (docs/decisions.md, "The area reference a0").

    a0 = median{a_i : i in the training split, a_i > 0} (the text before eq:confidence-gate);
    g_i = clip(g_conf * g_valid * g_area, 0, 1) at a0 (eq:confidence-gate .. eq:reliability-gate).  Without such
    an a_i, the gates at a0 = 0 with ``missing`` set, for the caller to say so.

    Parameters
    ----------
    c : array_like
        Foreground agreement per image.
    n_valid : array_like
        |V| per image.
    a : array_like
        Area ratio per image.
    is_train : array_like
        bool per image: in the training split.
    geo : mapping
        The params ``geometry`` section.

    Returns
    -------
    Gates
        The gates.

    Raises
    ------
    InputError
        ``a`` and ``is_train`` differ in shape, or an input is not finite (:func:`pipeline.geometry.gate_factors`).
    """
    a = np.asarray(a, np.float64)
    try:
        a0, missing = median_area(a, is_train), False
    except NoForeground:
        a0, missing = 0.0, True
    v, factors = image_gates(c, n_valid, a, a0, geo)
    return Gates(a0, v, factors, missing)


def gate_columns(c, a, gates: Gates) -> dict[str, np.ndarray]:
    """Return the gate columns of the gates table and of label's table.

    Parameters
    ----------
    c : array_like
        Foreground agreement per image.
    a : array_like
        Area ratio per image.
    gates : Gates
        From :func:`reliability_gates`.

    Returns
    -------
    dict of str to numpy.ndarray
        ``c, v, a, a0, g_conf, g_valid, g_area, g``.
    """
    f = gates.factors
    return {"c": c, "v": gates.v, "a": a, "a0": np.full(len(c), gates.a0),
            "g_conf": f.conf, "g_valid": f.valid, "g_area": f.area, "g": f.g}


def write_geometry(cons, manifest, cfg: Mapping[str, Any], out: str | Path, gates: str | Path,
                   meta: Callable[[str], Meta], chunk_images: int = 64) -> pd.DataFrame:
    """Write geometry.zarr (``sdf``, ``skeleton``; eq:sdf-target) and the gates table.

    Parameters
    ----------
    cons : pipeline.artifacts.store.ZarrArtifact
        The opened consensus.zarr.
    manifest : pipeline.artifacts.store.TableArtifact
        The opened manifest (its ``split`` column decides the training images of a0).
    cfg : mapping
        The params ``geometry`` section.
    out : str or Path
        The geometry.zarr path, replaced atomically.
    gates : str or Path
        The gates table's path (Parquet).
    meta : callable
        Schema name -> :class:`pipeline.artifacts.lineage.Meta`.
    chunk_images : int, optional
        Images per block (default 64).

    Returns
    -------
    pandas.DataFrame
        The gates table: ``image_id``, ``split``, the :func:`gate_columns` and ``n_valid``.

    Raises
    ------
    InputError
        consensus.zarr is inconsistent (:func:`check_consensus`), ``n_valid`` lies outside [0, n_prompts], or an
        image without a valid prompt has a non-empty voted mask.
    NoForeground
        No training image has foreground (nothing to train on).
    """
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
        gated = reliability_gates(c, n_valid, a, split == "train", cfg)
        if gated.missing:
            raise NoForeground()  # said in the user's terms, no file to name
        table = pd.DataFrame({"image_id": manifest.df["image_id"].astype(str).to_numpy(), "split": split,
                              **gate_columns(c, a, gated), "n_valid": n_valid.astype(np.int16)})
        write_parquet(gates, table, meta("gates"))
    return table
