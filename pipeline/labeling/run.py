"""``geodistill label``: a folder of images -> voted, gated pseudo-masks in standard formats.

The DAG's teacher, consensus and geometry steps, composed of the functions those stages call, on a
plain folder and without a DVC project:

1. every image (recursively, any size, grey / RGB / RGBA, 8/16-bit: :func:`pipeline.datasets.loading.
   load_rgb`) is resized to the working resolution ``data.resolution`` and sent to the teacher
   (``teacher.*``: SAM 3, imported masks, or the SIMULATOR) through the teacher stage's runner and
   content-addressed cache (:func:`pipeline.teachers.runner.open_runner`; serial, or with ``workers`` a
   Ray Data pool) -- a rerun, or a run killed half-way, recomputes nothing that is cached;
2. the K prompt masks are voted by the consensus stage's :func:`pipeline.pseudo_labels.vote_block`
   (eq:agreement-map, eq:majority-vote);
3. the reliability gates are the geometry stage's :func:`pipeline.pseudo_labels.reliability_gates`
   (eq:foreground-agreement .. eq:reliability-gate), every image of the folder a training image (the a0
   rule: docs/decisions.md, "The area reference a0").

Outputs under ``out`` (formats ``png``, ``coco``, ``yolo``; the table, contact sheet and run record
always)::

    masks/<relative path without suffix>.png  voted pseudo-mask, 0/255, at the ORIGINAL image size
    coco.json                                 COCO instances, one RLE annotation per non-empty mask
    yolo/labels/<relative stem>.txt           YOLO segmentation lines per image
    yolo/images/<relative path>               a RELATIVE symbolic link to the input (a copy with --copy-images)
    yolo/data.yaml, yolo/train.txt, yolo/val.txt, yolo/README.txt
                                              the Ultralytics dataset: image lists relative to the folder, a
                                              seeded validation share (formats.yolo_split; no val.txt below
                                              2 images, the reason in README.txt)
    labels.parquet, labels.csv                one row per image: c, v, a, a0, g_conf, g_valid, g_area, g, and h
                                              (prompt disagreement: pipeline.consensus.agreement_entropy)
    contact_sheet.png                         sampled images with their pseudo-mask contours and g
    label.json                                backend (and whether it is a SIMULATOR), counts, params
    skipped.csv                               files left out by --skip-bad (columns image_id, path, reason)

Decisions: the vote happens at the working resolution (the pseudo-mask is exactly the DAG's training
target for the same image and params) and the voted mask is brought to the original size by
nearest-neighbour resizing; ``--set data.resolution=...`` gives finer masks for large images.
Relative cache folders (``teacher.cache_dir``, ``data.cache_dir``) are taken inside ``out``, so a
rerun into the same folder resumes; label.json records the teacher cache as an absolute path, and
``distill --labels OUT`` reads it after checking OUT against label.json's checksums
(:func:`check_label_folder`), so distill computes no answer again (the cache key is the image bytes'
sha256, the teacher's fingerprint, the prompt and the view -- the same keys the DAG's teacher stage uses).  Two inputs whose relative paths differ only in the suffix or
letter case would share a label file name (YOLO needs ``<image stem>.txt``): refused before anything
is computed.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

from pipeline.runtime.errors import FORMAT, InputError, caller
from pipeline.geometry import NoForeground
from pipeline.labeling.reading import check_label_folder, find_images, open_folder, teacher_answers
from pipeline.labeling.writing import FORMATS, OUTPUTS, SIMULATOR_NOTE, YOLO_LISTS, vote_and_export, write_outputs
from pipeline.params import section
from pipeline.pseudo_labels import Gates, reliability_gates

log = logging.getLogger(__name__)

#: what callers import from here (the command, the API, review export, distill's project)
__all__ = ["FORMATS", "OUTPUTS", "YOLO_LISTS", "LabelResult", "check_label_folder", "find_images", "label_folder",
           "parse_formats"]


@dataclasses.dataclass(repr=False)
class LabelResult:
    """What :func:`label_folder` (``pipeline.label``) wrote: the output folder ``out``, the per-image
    ``table`` (image_id, c, v, a, g, ...), the ``skipped`` files (path, reason), the ``formats`` written,
    the teacher ``backend``; :attr:`masks` maps each image id to its mask PNG.  Its repr is one line."""

    out: Path
    table: pd.DataFrame
    skipped: list[tuple[str, str]]
    formats: tuple[str, ...]
    backend: str
    skipped_line: str | None = None  # the bad-file summary line (BadInputPolicy.summary; None: no bad file)

    @property
    def simulator(self) -> bool:
        return self.backend == "simulated"

    @property
    def masks(self) -> dict[str, Path]:
        """image id -> its voted mask ``out/masks/<image id>.png`` (at the image's own size); empty when
        ``png`` was not among the formats."""
        if "png" not in self.formats:
            return {}
        return {str(i): Path(self.out) / OUTPUTS["masks"] / f"{i}.png" for i in self.table["image_id"]}

    def __repr__(self) -> str:
        return (f"LabelResult(out={str(self.out)!r}, images={len(self.table)}, formats={list(self.formats)}, "
                f"skipped={len(self.skipped)}, backend={self.backend!r})")


def parse_formats(formats: str | Sequence[str]) -> tuple[str, ...]:
    """``"png,coco"`` or ``["png", "coco"]`` -> ("png", "coco") in the canonical order; InputError on an
    unknown or empty list (naming ``--format`` / ``formats=``)."""
    items = [f.strip().lower() for f in (formats.split(",") if isinstance(formats, str) else formats)]
    items = [f for f in items if f]
    bad = [f for f in items if f not in FORMATS]
    if bad or not items:
        raise InputError(f"{{}}: expected a comma-separated subset of {','.join(FORMATS)}",
                         FORMAT(','.join(items) or repr(formats)))
    return tuple(f for f in FORMATS if f in items)


def folder_gates(c: np.ndarray, n_valid: np.ndarray, a: np.ndarray, geo: Mapping) -> Gates:
    """The geometry stage's :func:`pipeline.pseudo_labels.reliability_gates` (eq:reliability-gate) of a
    folder, every image a training image; a missing a0 is a warning in the words distill stops with
    (:class:`pipeline.geometry.NoForeground`, spelled for the caller): the labels are still a result.
    ``c``, ``n_valid``, ``a``: [N] gate inputs; ``geo``: params ``geometry``."""
    gates = reliability_gates(c, n_valid, a, np.ones(len(a), bool), geo)
    if gates.missing:
        log.warning("label: %s (every gate g is 0)", NoForeground().render(caller()))
    return gates


def label_folder(input_dir: str | Path, out: str | Path, params: Mapping, *, device: str = "auto",
                 formats: str | Sequence[str] = FORMATS, reference_masks: str | Path | None = None,
                 overwrite: bool = False, workers: int = 0, address: str | None = None,
                 copy_images: bool = False) -> LabelResult:
    """Label every image under ``input_dir`` into ``out`` (module docstring); ``params`` are validated
    params (schema defaults or a params file): data.resolution / cache_dir / contact_sheet_images /
    seed, teacher.*, consensus.vote_threshold, geometry.*.  ``reference_masks``: the folder of masks the
    simulated teacher (a SIMULATOR) reads; refused for real teachers (they never see masks).
    ``workers`` / ``address``: the teacher's Ray Data executor, as the teacher stage's ``--workers``
    (0: the serial loop; same answers either way).  ``copy_images``: ``yolo/images`` holds copies of the
    inputs instead of relative links (``--copy-images``).

    Ownership (:mod:`pipeline.artifacts.ownership`): ``label.json`` lists the files written; a user's file where
    one goes (``coco.json``, ``masks/a.png``) is refused before anything is written, ``overwrite`` or
    not; a user's folder (``masks/``) is refused unless ``overwrite``, and the files in it stay; label's
    own files of an earlier run that this run does not write are removed."""
    fmts = parse_formats(formats)
    job = open_folder(input_dir, out, params, reference_masks, overwrite, fmts)
    runner, t_fp, stats = teacher_answers(job, device, workers, address)
    vote_threshold = float(section(params, "consensus")["vote_threshold"])
    v = vote_and_export(job, runner, fmts, vote_threshold, copy_images)
    gates = folder_gates(v.c, v.n_valid, v.a, job.geo)
    tcfg, n = job.tcfg, len(job.files)
    table = write_outputs(job, fmts, v, gates, {
        "input": str(job.root.resolve()), "images": n, "skipped": job.policy.bad_count(), "formats": list(fmts),
        "teacher_backend": tcfg["backend"], "simulator": job.simulated,
        "note": SIMULATOR_NOTE if job.simulated else None, "teacher_fingerprint": t_fp,
        "prompts": list(tcfg["prompts"]), "resolution": job.size, "vote_threshold": vote_threshold, "a0": gates.a0,
        "geometry": job.geo, "teacher_answers_computed": stats.answers_computed,
        "teacher_cache_hits": stats.cache_hits, "complete": True, "teacher": tcfg})
    # the summary is the caller's one line (pipeline/cli/label.py), not also a log line
    log.debug("label: %d images -> %s (%s)", n, job.out, ", ".join(fmts))
    return LabelResult(job.out, table, [(r["path"], r["reason"]) for r in job.policy.skipped], fmts, tcfg["backend"],
                       job.policy.summary("label", job.out / OUTPUTS["skipped"]))
