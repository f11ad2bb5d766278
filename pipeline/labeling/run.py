"""``geodistill label``: a folder of images -> voted, gated pseudo-masks in standard formats.

The work of the DAG's teacher, consensus and geometry stages on one folder: the vote (eq:majority-vote) at the
working resolution, resized (nearest) to each image's own size, and the gate (eq:reliability-gate) with every
image counted as a training image.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path
from typing import Callable, Iterator, Mapping, Sequence

import numpy as np
import pandas as pd

from pipeline.geometry import NoForeground, area_ratios, foreground_agreement
from pipeline.labeling.formats import LABEL_FORMATS, find_format
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
    """What :func:`label_folder` wrote.  Its repr is one line.

    Attributes
    ----------
    out : Path
        The output folder.
    table : pandas.DataFrame
        One row per labelled image: ``image_id``, ``file``, size, ``n_valid``, the gate columns
        (c, v, a, a0, g_conf, g_valid, g_area, g), ``h``, ``mask_pixels``, ``teacher_backend``, ``simulator``.
    skipped : list of tuple of str
        (path, reason) of each file left out.
    formats : tuple of str
        The formats written.
    backend : str
        The teacher backend.
    skipped_line : str or None
        The bad-file summary line; None when no file was bad.
    """

    out: Path
    table: pd.DataFrame
    skipped: list[tuple[str, str]]
    formats: tuple[str, ...]
    backend: str
    skipped_line: str | None = None  # the bad-file summary line (BadInputPolicy.summary; None: no bad file)

    @property
    def simulator(self) -> bool:
        """Whether the labels come from the SIMULATOR, not a real teacher (the teacher table's ``simulator``)."""
        return is_simulator(self.backend)

    @property
    def masks(self) -> dict[str, Path]:
        """Image id -> its voted mask as an image file (:func:`mask_file`); empty when no format written has one."""
        where = mask_file(self.formats)
        return {} if where is None else {str(i): Path(self.out) / where(str(i)) for i in self.table["image_id"]}

    def __repr__(self) -> str:
        """Return one line: folder, image count, formats, skipped count, backend."""
        return (f"LabelResult(out={str(self.out)!r}, images={len(self.table)}, formats={list(self.formats)}, "
                f"skipped={len(self.skipped)}, backend={self.backend!r})")


def mask_file(formats: Sequence[str]):
    """Return where the voted mask is written as an image file, by the first of ``formats`` that writes one.

    Parameters
    ----------
    formats : sequence of str
        Format names; names not in :data:`~pipeline.labeling.formats.LABEL_FORMATS` are passed over.

    Returns
    -------
    callable or None
        ``image id -> path`` relative to the output folder (``LabelFormat.mask_file``, e.g. ``png``'s
        ``masks/<id>.png``); None when no format of ``formats`` writes one.
    """
    return next((LABEL_FORMATS[f].mask_file for f in formats if f in LABEL_FORMATS and LABEL_FORMATS[f].mask_file),
                None)


def duration(seconds: float) -> str:
    """Return ``seconds`` as people read a wait: 42 s, 7.5 min, 3.2 h, 2.1 days.

    Parameters
    ----------
    seconds : float
        A wait in seconds, >= 0.

    Returns
    -------
    str
        The largest unit of which the wait is at least two (days, h, min), one decimal; below 2 min, whole
        seconds, and two significant digits below 10 s.
    """
    for unit, size in (("days", 86400.0), ("h", 3600.0), ("min", 60.0)):
        if seconds >= 2 * size:
            return f"{seconds / size:.1f} {unit}"
    return f"{seconds:.0f} s" if seconds >= 10 else f"{seconds:.2g} s"


class TeacherClock:
    """Measure what the teacher's fill costs: the runner's ``on_batch`` callback.

    After the first batch it hands ``report`` one line projecting the whole fill (serial: seconds per image so
    far x images to do; under ``workers`` Ray teachers, divided by the workers that finished batches side by
    side -- a projection, which start-up and shared cores make optimistic); :attr:`seconds_per_image` at the
    end.  Times include decoding and, under Ray, the pool's start-up: what the user waits for.

    Parameters
    ----------
    report : callable or None
        Receives the projection line; None: it is logged (INFO).
    workers : int, optional
        Ray teachers in the pool; 0 (default): serial.
    clock : callable, optional
        Wall seconds, :func:`time.perf_counter` by default (a test passes its own).

    Attributes
    ----------
    path : str or None
        The teacher's path (:func:`teacher_path`), named in the projection; None: not named.
    start : float
        ``clock()`` when the clock was made.
    first : tuple of (int, float) or None
        (images, seconds) at the first finished batch; None before it.
    images : float
        Images answered so far.
    seconds : float
        Wall seconds from ``start`` to the latest batch.
    """

    def __init__(self, report: Callable[[str], None] | None, workers: int = 0, clock=time.perf_counter):
        self.report, self.workers, self.clock = report, int(workers), clock
        self.start = clock()
        self.path: str | None = None
        self.first: tuple[int, float] | None = None   # (images, seconds) at the first finished batch
        self.images = 0.0
        self.seconds = 0.0

    def __call__(self, done: float, todo: int) -> None:
        """Record a finished batch; after the first, report the projected fill.

        Parameters
        ----------
        done : float
            Images answered so far.
        todo : int
            Images the fill answers in all.
        """
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
        on = f" on {self.path}" if self.path else ""
        line = (f"label: teacher's first batch: {done:.3g} image(s) in {self.seconds:.1f} s ({per_image:.2f} s per "
                f"image{on}); projected for the {todo} image(s) to label: {how}")
        if self.report is not None:
            self.report(line)
        else:
            log.info("%s", line)

    @property
    def seconds_per_image(self) -> float | None:
        """Measured wall seconds per image the teacher answered (None: every answer was cached)."""
        return self.seconds / self.images if self.images else None


def teacher_path(teacher) -> str | None:
    """Return the path the teacher's answers take (engine, dtype, device), from its optional ``path()``.

    Parameters
    ----------
    teacher : Teacher
        The run's teacher.

    Returns
    -------
    str or None
        E.g. ``sam3 torch eager bf16 on cpu``; None for a teacher without one to name (the SIMULATOR).
    """
    describe = getattr(teacher, "path", None)
    return describe() if callable(describe) else None


def teacher_note(teacher, computed: int) -> str | None:
    """Return the teacher's word on why its answers were computed rather than reused.

    Parameters
    ----------
    teacher : Teacher
        The run's teacher; its optional ``cache_note()`` says why (a CPU whose ``auto`` dtype is bf16: answers
        cached under fp32 miss).
    computed : int
        Teacher answers computed in this run.

    Returns
    -------
    str or None
        The note when the teacher has one and some answers were computed; else None.
    """
    note = getattr(teacher, "cache_note", None)
    return note() if callable(note) and computed else None


def parse_formats(formats: str | Sequence[str] | None = None) -> tuple[str, ...]:
    """Parse the requested label formats.

    Parameters
    ----------
    formats : str or sequence of str or None, optional
        ``"png,coco"`` or ``["png", "coco"]``, names in :data:`~pipeline.labeling.formats.LABEL_FORMATS` or of
        installed plug-ins (:func:`~pipeline.labeling.formats.find_format`); case and blanks ignored.  None
        (default): the registry's default formats (``LabelFormat.default``).

    Returns
    -------
    tuple of str
        The formats in the canonical order of :data:`~pipeline.labeling.formats.LABEL_FORMATS`.

    Raises
    ------
    InputError
        A format is unknown or none is given, naming ``--format``; a plug-in fails to load.
    """
    if formats is None:
        return tuple(name for name, f in LABEL_FORMATS.items() if f.default)
    items = [f.strip().lower() for f in (formats.split(",") if isinstance(formats, str) else formats)]
    items = [f for f in items if f]
    bad = [f for f in items if find_format(f) is None]  # a plug-in's format is loaded here
    if bad or not items:
        raise InputError(f"{{}}: expected a comma-separated subset of {','.join(LABEL_FORMATS)}",
                         FORMAT(','.join(items) or repr(formats)))
    return tuple(f for f in LABEL_FORMATS if f in items)


def folder_votes(job: LabelJob, threshold: float) -> Iterator[tuple]:
    """Vote each image of the job, one at a time (the consensus stage's :func:`pipeline.pseudo_labels.vote_block`).

    Parameters
    ----------
    job : pipeline.labeling.reading.LabelJob
        An opened job whose teacher answers are all cached.
    threshold : float
        The vote threshold (eq:majority-vote).

    Yields
    ------
    tuple
        (voted bool [R,R], c (eq:foreground-agreement), a (eq:pseudo-area), n_valid, h) per image.
    """
    for row in progress(range(len(job.files)), desc="label: vote + export", unit="img"):
        masks, scores, _, _ = job.runner.answers(row)
        cons, h = vote_block(masks[None], scores[None], threshold)  # a block of one image
        c, a = foreground_agreement(cons.agreement, cons.voted)[0], area_ratios(cons.voted)[0]
        yield cons.voted[0], c, a, cons.n_valid[0], h[0]


def folder_gates(c: np.ndarray, n_valid: np.ndarray, a: np.ndarray, geo: Mapping) -> Gates:
    """Gate every image (eq:reliability-gate), each counted as a training image.

    The geometry stage's :func:`pipeline.pseudo_labels.reliability_gates`; a missing a0 (no image with
    foreground) is a warning here, every g being 0: the labels are still a result.

    Parameters
    ----------
    c : numpy.ndarray
        Foreground agreement per image.
    n_valid : numpy.ndarray
        |V| per image.
    a : numpy.ndarray
        Area ratio per image.
    geo : mapping
        The params ``geometry`` section.

    Returns
    -------
    pipeline.pseudo_labels.Gates
        The gates.
    """
    gates = reliability_gates(c, n_valid, a, np.ones(len(a), bool), geo)
    if gates.missing:
        log.warning("label: %s (every gate g is 0)", NoForeground().render(caller()))
    return gates


def label_folder(input_dir: str | Path, out: str | Path, params: Mapping, *, device: str = "auto",
                 formats: str | Sequence[str] | None = None, reference_masks: str | Path | None = None,
                 overwrite: bool = False, workers: int = 0, address: str | None = None,
                 copy_images: bool = False, report: Callable[[str], None] | None = None) -> LabelResult:
    """Label every image under ``input_dir`` into ``out`` with validated ``params``.

    Plans and reads everything first (:func:`pipeline.labeling.reading.open_folder`), then writes each image's
    files as its vote comes, the tables and last label.json.  A user's file where an output goes is refused,
    ``overwrite`` or not; a user's folder only without ``overwrite``.

    Parameters
    ----------
    input_dir : str or Path
        A folder of images, searched recursively.
    out : str or Path
        The output folder.
    params : mapping
        Validated params with the teacher chosen.
    device : str, optional
        ``auto`` (default), ``cpu`` or ``cuda``.
    formats : str or sequence of str or None, optional
        A subset of :data:`~pipeline.labeling.formats.LABEL_FORMATS`; None (default): its default formats
        (:func:`parse_formats`).
    reference_masks : str or Path, optional
        The masks the simulated teacher reads (refused for real teachers).
    overwrite : bool, optional
        Write into an existing folder this command did not make.
    workers : int, optional
        Teachers in a Ray Data pool; 0 (default): serial, the same answers.
    address : str, optional
        The Ray cluster to join with ``workers``.
    copy_images : bool, optional
        yolo/images holds copies instead of relative links.
    report : callable, optional
        Receives the teacher's projected cost after its first batch (:class:`TeacherClock`); None (default):
        logged.

    Returns
    -------
    LabelResult
        What was written.

    Raises
    ------
    InputError
        An invalid format, folder, option or image, or an output that belongs to the user (one line naming it).
    """
    fmts = parse_formats(formats)
    clock = TeacherClock(report, workers)
    job = open_folder(input_dir, out, params, reference_masks, overwrite, fmts, device, workers, address,
                      on_batch=clock, on_teacher=lambda teacher: setattr(clock, "path", teacher_path(teacher)))
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
        "teacher_cache_hits": stats.cache_hits, "teacher_seconds_per_image": clock.seconds_per_image,
        "teacher_images_timed": clock.images, "teacher_path": clock.path, "teacher_dtype": getattr(job.runner.teacher, "dtype_name", None),
        "teacher_note": teacher_note(job.runner.teacher, stats.answers_computed),
        "complete": True, "teacher": tcfg})
    # the summary is the caller's one line (pipeline/cli/label.py), not also a log line
    log.debug("label: %d images -> %s (%s)", n, job.out, ", ".join(fmts))
    return LabelResult(job.out, table, [(r["path"], r["reason"]) for r in job.policy.skipped], fmts, tcfg["backend"],
                       job.policy.summary("label", job.out / OUTPUTS["skipped"]))
