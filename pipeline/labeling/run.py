"""``geodistill label``: a folder of images -> voted, gated pseudo-masks in standard formats, by the functions
of the DAG's teacher, consensus and geometry stages; the vote at the working resolution, resized (nearest)
to each image's own size."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Iterator, Mapping, Sequence

import numpy as np
import pandas as pd

from pipeline.geometry import NoForeground, area_ratios, foreground_agreement
from pipeline.labeling.formats import LABEL_FORMATS
from pipeline.labeling.reading import OUTPUTS, SIMULATOR_NOTE, LabelJob, check_label_folder, find_images, open_folder
from pipeline.labeling.writing import write_outputs, write_votes
from pipeline.params import section
from pipeline.pseudo_labels import Gates, reliability_gates, vote_block
from pipeline.runtime.errors import FORMAT, InputError, caller
from pipeline.runtime.progress import progress
from pipeline.teacher_table import is_simulator

log = logging.getLogger(__name__)

#: what callers import from here (the command, the API, review export, distill's project)
__all__ = ["LABEL_FORMATS", "OUTPUTS", "LabelResult", "check_label_folder", "find_images", "label_folder",
           "mask_file", "parse_formats"]


@dataclasses.dataclass(repr=False)
class LabelResult:
    """What :func:`label_folder` wrote: the folder ``out``, the per-image ``table``, the ``skipped`` files
    (path, reason), the ``formats`` and the teacher ``backend``.  Its repr is one line."""

    out: Path
    table: pd.DataFrame
    skipped: list[tuple[str, str]]
    formats: tuple[str, ...]
    backend: str
    skipped_line: str | None = None  # the bad-file summary line (BadInputPolicy.summary; None: no bad file)

    @property
    def simulator(self) -> bool:
        return is_simulator(self.backend)

    @property
    def masks(self) -> dict[str, Path]:
        """image id -> its voted mask as an image file (the first format with one, e.g. ``png``); empty when
        no format written has one."""
        where = mask_file(self.formats)
        return {} if where is None else {str(i): Path(self.out) / where(str(i)) for i in self.table["image_id"]}

    def __repr__(self) -> str:
        return (f"LabelResult(out={str(self.out)!r}, images={len(self.table)}, formats={list(self.formats)}, "
                f"skipped={len(self.skipped)}, backend={self.backend!r})")


def mask_file(formats: Sequence[str]):
    """``image id -> path`` (relative to the output folder) of the voted mask as an image file, of the first of
    ``formats`` that writes one (``png``); None when none does."""
    return next((LABEL_FORMATS[f].mask_file for f in formats if f in LABEL_FORMATS and LABEL_FORMATS[f].mask_file),
                None)


def parse_formats(formats: str | Sequence[str] | None = None) -> tuple[str, ...]:
    """``"png,coco"`` or ``["png", "coco"]`` -> ("png", "coco") in the canonical order of
    :data:`~pipeline.labeling.formats.LABEL_FORMATS`; None: its default formats; InputError on an unknown or
    empty list."""
    if formats is None:
        return tuple(name for name, f in LABEL_FORMATS.items() if f.default)
    items = [f.strip().lower() for f in (formats.split(",") if isinstance(formats, str) else formats)]
    items = [f for f in items if f]
    bad = [f for f in items if f not in LABEL_FORMATS]
    if bad or not items:
        raise InputError(f"{{}}: expected a comma-separated subset of {','.join(LABEL_FORMATS)}",
                         FORMAT(','.join(items) or repr(formats)))
    return tuple(f for f in LABEL_FORMATS if f in items)


def folder_votes(job: LabelJob, threshold: float) -> Iterator[tuple]:
    """Each image's vote (the consensus stage's :func:`pipeline.pseudo_labels.vote_block`, eq:majority-vote)
    as (voted, c, a, n_valid, h): c eq:foreground-agreement, a eq:pseudo-area; one image at a time."""
    for row in progress(range(len(job.files)), desc="label: vote + export", unit="img"):
        masks, scores, _, _ = job.runner.answers(row)
        cons, h = vote_block(masks[None], scores[None], threshold)  # a block of one image
        c, a = foreground_agreement(cons.agreement, cons.voted)[0], area_ratios(cons.voted)[0]
        yield cons.voted[0], c, a, cons.n_valid[0], h[0]


def folder_gates(c: np.ndarray, n_valid: np.ndarray, a: np.ndarray, geo: Mapping) -> Gates:
    """The geometry stage's :func:`pipeline.pseudo_labels.reliability_gates` (eq:reliability-gate), every
    image a training image; a missing a0 is a warning here (the labels are still a result)."""
    gates = reliability_gates(c, n_valid, a, np.ones(len(a), bool), geo)
    if gates.missing:
        log.warning("label: %s (every gate g is 0)", NoForeground().render(caller()))
    return gates


def label_folder(input_dir: str | Path, out: str | Path, params: Mapping, *, device: str = "auto",
                 formats: str | Sequence[str] | None = None, reference_masks: str | Path | None = None,
                 overwrite: bool = False, workers: int = 0, address: str | None = None,
                 copy_images: bool = False) -> LabelResult:
    """Label every image under ``input_dir`` into ``out`` with validated ``params``.

    ``reference_masks``: the masks the simulated teacher reads (refused for real teachers); ``workers`` /
    ``address``: the teacher's Ray Data executor (0: serial; same answers); ``copy_images``: yolo/images
    holds copies instead of relative links; ``formats``: None writes the default ones (:func:`parse_formats`).  A user's file where an output goes is refused, ``overwrite``
    or not; a user's folder only without ``overwrite``."""
    fmts = parse_formats(formats)
    job = open_folder(input_dir, out, params, reference_masks, overwrite, fmts, device, workers, address)
    job.copy_images = copy_images
    vote_threshold = float(section(params, "consensus")["vote_threshold"])
    v = write_votes(job, fmts, folder_votes(job, vote_threshold))
    gates = folder_gates(v.c, v.n_valid, v.a, job.geo)
    tcfg, n, stats = job.tcfg, len(job.files), job.stats
    table = write_outputs(job, fmts, v, gates, {
        "input": str(job.root.resolve()), "images": n, "skipped": job.policy.bad_count(), "formats": list(fmts),
        "teacher_backend": tcfg["backend"], "simulator": job.simulated,
        "note": SIMULATOR_NOTE if job.simulated else None, "teacher_fingerprint": job.fingerprint,
        "prompts": list(tcfg["prompts"]), "resolution": job.size, "vote_threshold": vote_threshold, "a0": gates.a0,
        "geometry": job.geo, "teacher_answers_computed": stats.answers_computed,
        "teacher_cache_hits": stats.cache_hits, "complete": True, "teacher": tcfg})
    # the summary is the caller's one line (pipeline/cli/label.py), not also a log line
    log.debug("label: %d images -> %s (%s)", n, job.out, ", ".join(fmts))
    return LabelResult(job.out, table, [(r["path"], r["reason"]) for r in job.policy.skipped], fmts, tcfg["backend"],
                       job.policy.summary("label", job.out / OUTPUTS["skipped"]))
