"""The teacher stage's work (eq:prompt-set, eq:teacher-prediction) without the CLI.

A teacher behind its cache over a manifest's rows -> ``teacher.zarr`` and the score table.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import pandas as pd

from pipeline.artifacts.lineage import Meta, require_same_run
from pipeline.artifacts.store import ZarrWriter, open_artifact, write_parquet
from pipeline.runtime.errors import InputError
from pipeline.runtime.progress import progress
from pipeline.teacher_table import is_simulator
from pipeline.teachers import teacher_record
from pipeline.teachers.base import manifest_extras
from pipeline.teachers.inputs import ArtifactInputs
from pipeline.teachers.runner import RunStats, TeacherRunner, open_runner

__all__ = ["SCORE_COLUMNS", "check_alignment", "vflip_prompt", "fingerprint_params", "score_rows", "score_table",
           "TeacherRun", "open_teacher_run"]

log = logging.getLogger(__name__)

#: teacher_scores.parquet: one row per (image, prompt)
SCORE_COLUMNS = ("image_id", "prompt_index", "prompt", "score", "valid", "mask_area", "split", "ran")


def check_alignment(manifest: pd.DataFrame, images, reference) -> None:
    """Check that images.zarr (and reference.zarr, if given) have the manifest's rows in its order.

    Parameters
    ----------
    manifest : pandas.DataFrame
        The manifest, in row order.
    images : pipeline.artifacts.store.Artifact
        The opened ``images`` artifact.
    reference : pipeline.artifacts.store.Artifact or None
        The opened ``reference`` artifact, or None.

    Raises
    ------
    InputError
        An artifact's row count, or its ``image_ids`` attribute, differs from the manifest's (naming it).
    """
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


def vflip_prompt(cfg: Mapping[str, Any]) -> str | None:
    """Return the prompt also run on the flipped image (the annotation-free-style control), if any.

    Parameters
    ----------
    cfg : Mapping
        The validated ``teacher:`` section.

    Returns
    -------
    str or None
        The base prompt (``prompts[base_prompt_index]``) when ``vflip_base_prompt``; else None.
    """
    return cfg["prompts"][cfg["base_prompt_index"]] if cfg["vflip_base_prompt"] else None


def fingerprint_params(cfg: Mapping[str, Any]) -> dict:
    """Return the ``teacher:`` section as the artifacts' fingerprint holds it.

    Parameters
    ----------
    cfg : Mapping
        The validated ``teacher:`` section.

    Returns
    -------
    dict
        ``cfg`` without ``cache_dir``: where the cache lives changes nothing.
    """
    return {k: v for k, v in cfg.items() if k != "cache_dir"}


def score_rows(image_id: str, prompts: Sequence[str], masks: np.ndarray, scores: np.ndarray, split: str,
               ran: bool) -> list[tuple]:
    """Build one image's rows of the score table (:data:`SCORE_COLUMNS`).

    Parameters
    ----------
    image_id : str
        The image's id.
    prompts : sequence of str
        The K prompts.
    masks : numpy.ndarray
        bool [K,H,W]: M_ik of eq:teacher-prediction.
    scores : numpy.ndarray
        float [K]: s_ik.
    split : str
        The image's split.
    ran : bool
        Whether the teacher ran on it (its split is in ``teacher.splits``).

    Returns
    -------
    list of tuple
        Per prompt: its score, validity (score > 0: in the valid-prompt set V_i of eq:agreement-map) and mask
        area (eq:pseudo-area applied to M_ik).
    """
    k = len(prompts)
    areas = masks.reshape(k, -1).mean(axis=1)
    return [(image_id, j, prompts[j], float(scores[j]), bool(scores[j] > 0), float(areas[j]), split, ran)
            for j in range(k)]


def score_table(rows: Sequence[tuple]) -> pd.DataFrame:
    """Build teacher_scores.parquet's frame.

    Parameters
    ----------
    rows : sequence of tuple
        Rows of :func:`score_rows`.

    Returns
    -------
    pandas.DataFrame
        Columns :data:`SCORE_COLUMNS`; score float32, prompt_index int16.
    """
    table = pd.DataFrame(rows, columns=list(SCORE_COLUMNS))
    table["score"] = table["score"].astype(np.float32)
    table["prompt_index"] = table["prompt_index"].astype(np.int16)
    return table


@dataclasses.dataclass
class TeacherRun:
    """The teacher of one ``teacher:`` section behind its cache, over the rows of one manifest.

    Attributes
    ----------
    cfg : dict
        The validated ``teacher:`` section.
    runner : TeacherRunner
        The teacher behind its cache.
    fingerprint : str
        The teacher's fingerprint (the cache's teacher component).
    manifest : pandas.DataFrame
        The manifest, indexed 0..N-1.
    shape : tuple of int
        (N, H, W) of images.zarr.
    inputs : list
        The opened artifacts the outputs descend from (manifest, images[, reference]).
    rows : list of int
        The rows in ``teacher.splits``, in manifest order.
    """

    cfg: dict
    runner: TeacherRunner
    fingerprint: str            # the teacher's (the cache's teacher component)
    manifest: pd.DataFrame      # index 0..N-1
    shape: tuple[int, int, int]  # N, H, W of images.zarr
    inputs: list                # the opened artifacts the outputs descend from (manifest, images[, reference])
    rows: list[int]             # the rows in teacher.splits, in manifest order

    @property
    def teacher(self):
        """The teacher (:class:`pipeline.teachers.base.Teacher`)."""
        return self.runner.teacher

    @property
    def prompts(self) -> list[str]:
        """The K prompts (eq:prompt-set), in order."""
        return list(self.cfg["prompts"])

    def fill(self, rows: Sequence[int], workers: int = 0, address: str | None = None) -> RunStats:
        """Compute and cache what ``rows`` (of :attr:`rows`) lack (:meth:`TeacherRunner.fill`).

        Parameters
        ----------
        rows : sequence of int
            Manifest rows.
        workers : int, optional
            Teachers in a Ray Data pool; 0 (default): serial, the same answers.
        address : str, optional
            The Ray cluster to join with ``workers``.

        Returns
        -------
        RunStats
            The answers computed and reused so far.
        """
        stats = self.runner.fill(rows, workers=workers, address=address)
        log.info("teacher: computed %d answers on %d images; %d cached answers reused",
                 stats.answers_computed, stats.images_computed, stats.cache_hits)
        return stats

    def write(self, out: str | Path, scores: str | Path, meta: Callable[[str], Meta]) -> pd.DataFrame:
        """Assemble teacher.zarr and teacher_scores.parquet from the cache, in manifest order.

        A row outside :attr:`rows` gets empty masks and zero scores (``ran`` False).

        Parameters
        ----------
        out : str or Path
            Where teacher.zarr goes.
        scores : str or Path
            Where teacher_scores.parquet goes.
        meta : callable
            Artifact name -> its :class:`pipeline.artifacts.lineage.Meta`.

        Returns
        -------
        pandas.DataFrame
            The score table written (:func:`score_table`).
        """
        n, h, w = self.shape
        prompts, vflip, k = self.prompts, vflip_prompt(self.cfg), len(self.prompts)
        ids = self.manifest["image_id"].astype(str).tolist()
        splits = self.manifest["split"].astype(str).tolist()
        run_set = set(self.rows)
        rows = []
        with ZarrWriter(out, meta("teacher")) as zw:
            zw.create("masks", (n, k, h, w), bool)
            zw.create("scores", (n, k), np.float32)
            if vflip is not None:
                zw.create("vflip_masks", (n, h, w), bool)
                zw.create("vflip_scores", (n,), np.float32)
            for row in progress(range(n), desc="teacher: assembling"):
                if row in run_set:
                    masks, sc, vmask, vscore = self.runner.answers(row)
                else:
                    masks, sc = np.zeros((k, h, w), bool), np.zeros(k, np.float32)
                    vmask, vscore = np.zeros((h, w), bool), 0.0
                zw.write("masks", row, masks)
                zw.write("scores", row, sc)
                if vflip is not None:
                    zw.write("vflip_masks", row, vmask)
                    zw.write("vflip_scores", row, np.float32(vscore))
                rows += score_rows(ids[row], prompts, masks, sc, splits[row], row in run_set)
            zw.attrs.update({
                "prompts": prompts, "image_ids": ids, "backend": self.teacher.backend,
                "simulator": is_simulator(self.teacher.backend), "teacher_fingerprint": self.fingerprint,
                "teacher": teacher_record(self.teacher), "splits_run": list(self.cfg["splits"]),
                "base_prompt_index": self.cfg["base_prompt_index"], "vflip_prompt": vflip,
            })
        table = score_table(rows)
        write_parquet(scores, table, meta("teacher_scores"))
        if self.runner.stats.cache_corrupt:
            log.warning("teacher: %d corrupt cache entries were recomputed while assembling",
                        self.runner.stats.cache_corrupt)
        log.info("teacher: wrote %s and %s (%d images x %d prompts, backend %s)", out, scores, n, k,
                 self.teacher.backend)
        return table


def open_teacher_run(cfg: Mapping[str, Any], manifest, images, reference: str | Path,
                     device: str = "auto") -> TeacherRun:
    """Open the teacher of a ``teacher:`` section over a manifest's images, checked to come from one run.

    Parameters
    ----------
    cfg : Mapping
        The validated ``teacher:`` section.
    manifest : pipeline.artifacts.store.Artifact
        The opened manifest.
    images : pipeline.artifacts.store.Artifact
        The opened ``images`` artifact.
    reference : str or Path
        The ``reference`` artifact, opened only for a backend whose row is marked ``simulator``.
    device : str, optional
        ``auto`` (default), ``cpu`` or ``cuda``.

    Returns
    -------
    TeacherRun
        The teacher behind its cache, over the rows in ``teacher.splits``.
    """
    df = manifest.df.reset_index(drop=True)
    n, h, w = images["image"].shape[:3]
    rows = [i for i, s in enumerate(df["split"].astype(str)) if s in cfg["splits"]]
    shas = df["sha256"].astype(str).tolist()
    simulator = is_simulator(cfg["backend"])  # only a row marked simulator reads the reference and its extras
    load = ArtifactInputs(images.path, None, df["image_id"].astype(str).tolist(), shas,
                          manifest_extras(df) if simulator else [{}] * len(df))
    runner, t_fp = open_runner(cfg, (h, w), device, load, shas, vflip_prompt(cfg))
    ref = open_artifact(reference, "reference") if simulator else None
    require_same_run(manifest, images, ref)
    check_alignment(df, images, ref)
    if ref is not None:
        load.reference = os.path.abspath(reference)
    if simulator:
        log.info("teacher: backend %r is a SIMULATOR of foundation-model errors that reads the synthetic ground "
                 "truth; it is not a real teacher", runner.teacher.backend)
    return TeacherRun(dict(cfg), runner, t_fp, df, (n, h, w), [manifest, images] + ([ref] if ref is not None else []),
                      rows)
