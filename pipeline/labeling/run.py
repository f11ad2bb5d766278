"""``geodistill label``: a folder of images -> voted, gated pseudo-masks in standard formats, by the functions
of the DAG's teacher, consensus and geometry stages; the vote at the working resolution, resized (nearest)
to each image's own size."""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path
from typing import Callable, Iterator, Mapping, Sequence

import numpy as np
import pandas as pd

from pipeline.geometry import NoForeground, area_ratios, foreground_agreement
from pipeline.labeling.reading import (FORMATS, OUTPUTS, SIMULATOR_NOTE, YOLO_LISTS, LabelJob, check_label_folder,
                                       find_images, open_folder)
from pipeline.labeling.writing import write_outputs, write_votes
from pipeline.params import section
from pipeline.pseudo_labels import Gates, reliability_gates, vote_block
from pipeline.runtime.errors import FORMAT, InputError, caller
from pipeline.runtime.progress import progress

log = logging.getLogger(__name__)

#: what callers import from here (the command, the API, review export, distill's project)
__all__ = ["FORMATS", "OUTPUTS", "YOLO_LISTS", "LabelResult", "check_label_folder", "find_images", "label_folder",
           "parse_formats"]


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
        return self.backend == "simulated"

    @property
    def masks(self) -> dict[str, Path]:
        """image id -> its voted mask PNG; empty when ``png`` was not among the formats."""
        if "png" not in self.formats:
            return {}
        return {str(i): Path(self.out) / OUTPUTS["masks"] / f"{i}.png" for i in self.table["image_id"]}

    def __repr__(self) -> str:
        return (f"LabelResult(out={str(self.out)!r}, images={len(self.table)}, formats={list(self.formats)}, "
                f"skipped={len(self.skipped)}, backend={self.backend!r})")


def duration(seconds: float) -> str:
    """``seconds`` as people read a wait: 42 s, 7.5 min, 3.2 h, 2.1 days."""
    for unit, size in (("days", 86400.0), ("h", 3600.0), ("min", 60.0)):
        if seconds >= 2 * size:
            return f"{seconds / size:.1f} {unit}"
    return f"{seconds:.0f} s" if seconds >= 10 else f"{seconds:.2g} s"


class TeacherClock:
    """What the teacher's fill costs, measured: the runner's ``on_batch`` callback.  After the first batch it
    hands ``report`` one line projecting the whole fill (serial: seconds per image so far x images to do;
    under ``workers`` Ray teachers, divided by the workers that finished batches side by side -- a
    projection, which start-up and shared cores make optimistic); :attr:`seconds_per_image` at the end.

    Times include decoding and, under Ray, the pool's start-up: what the user waits for."""

    def __init__(self, report: Callable[[str], None] | None, workers: int = 0, clock=time.perf_counter):
        self.report, self.workers, self.clock = report, int(workers), clock
        self.start = clock()
        self.first: tuple[int, float] | None = None   # (images, seconds) at the first finished batch
        self.images = 0.0
        self.seconds = 0.0

    def __call__(self, done: float, todo: int) -> None:
        self.images, self.seconds = done, self.clock() - self.start
        if self.first is not None:
            return
        self.first = (done, self.seconds)
        per_image = self.seconds / max(done, 1)
        if self.workers > 0:
            how = (f"about {duration(per_image * todo / self.workers)} under {self.workers} Ray workers "
                   f"(the first batch's rate x {self.workers} workers keeping pace)")
        else:
            how = f"about {duration(per_image * todo)} serially"
        line = (f"label: teacher's first batch: {done:.3g} image(s) in {self.seconds:.1f} s ({per_image:.2f} s per "
                f"image); projected for the {todo} image(s) to label: {how}")
        if self.report is not None:
            self.report(line)
        else:
            log.info("%s", line)

    @property
    def seconds_per_image(self) -> float | None:
        """Measured wall seconds per image the teacher answered (None: every answer was cached)."""
        return self.seconds / self.images if self.images else None


def teacher_note(teacher, computed: int) -> str | None:
    """The teacher's word on why its answers were computed rather than reused (a CPU whose ``auto`` dtype is
    bf16: answers cached under fp32 miss), when it has one and some were computed; else None."""
    note = getattr(teacher, "cache_note", None)
    return note() if callable(note) and computed else None


def parse_formats(formats: str | Sequence[str]) -> tuple[str, ...]:
    """``"png,coco"`` or ``["png", "coco"]`` -> ("png", "coco") in the canonical order; InputError on an
    unknown or empty list."""
    items = [f.strip().lower() for f in (formats.split(",") if isinstance(formats, str) else formats)]
    items = [f for f in items if f]
    bad = [f for f in items if f not in FORMATS]
    if bad or not items:
        raise InputError(f"{{}}: expected a comma-separated subset of {','.join(FORMATS)}",
                         FORMAT(','.join(items) or repr(formats)))
    return tuple(f for f in FORMATS if f in items)


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
                 formats: str | Sequence[str] = FORMATS, reference_masks: str | Path | None = None,
                 overwrite: bool = False, workers: int = 0, address: str | None = None,
                 copy_images: bool = False, report: Callable[[str], None] | None = None) -> LabelResult:
    """Label every image under ``input_dir`` into ``out`` with validated ``params``.

    ``reference_masks``: the masks the simulated teacher reads (refused for real teachers); ``workers`` /
    ``address``: the teacher's Ray Data executor (0: serial; same answers); ``copy_images``: yolo/images
    holds copies instead of relative links; ``report``: receives the teacher's projected cost after its
    first batch (:class:`TeacherClock`; None: logged).  A user's file where an output goes is refused,
    ``overwrite`` or not; a user's folder only without ``overwrite``."""
    fmts = parse_formats(formats)
    clock = TeacherClock(report, workers)
    job = open_folder(input_dir, out, params, reference_masks, overwrite, fmts, device, workers, address,
                      on_batch=clock)
    vote_threshold = float(section(params, "consensus")["vote_threshold"])
    v = write_votes(job, fmts, folder_votes(job, vote_threshold), copy_images)
    gates = folder_gates(v.c, v.n_valid, v.a, job.geo)
    tcfg, n, stats = job.tcfg, len(job.files), job.stats
    table = write_outputs(job, fmts, v, gates, {
        "input": str(job.root.resolve()), "images": n, "skipped": job.policy.bad_count(), "formats": list(fmts),
        "teacher_backend": tcfg["backend"], "simulator": job.simulated,
        "note": SIMULATOR_NOTE if job.simulated else None, "teacher_fingerprint": job.fingerprint,
        "prompts": list(tcfg["prompts"]), "resolution": job.size, "vote_threshold": vote_threshold, "a0": gates.a0,
        "geometry": job.geo, "teacher_answers_computed": stats.answers_computed,
        "teacher_cache_hits": stats.cache_hits, "teacher_seconds_per_image": clock.seconds_per_image,
        "teacher_images_timed": clock.images, "teacher_dtype": getattr(job.runner.teacher, "dtype_name", None),
        "teacher_note": teacher_note(job.runner.teacher, stats.answers_computed),
        "complete": True, "teacher": tcfg})
    # the summary is the caller's one line (pipeline/cli/label.py), not also a log line
    log.debug("label: %d images -> %s (%s)", n, job.out, ", ".join(fmts))
    return LabelResult(job.out, table, [(r["path"], r["reason"]) for r in job.policy.skipped], fmts, tcfg["backend"],
                       job.policy.summary("label", job.out / OUTPUTS["skipped"]))
