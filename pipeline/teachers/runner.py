"""Plan, shard, compute and collect teacher answers through the cache (the teacher stage and ``geodistill label``).

Only the answers the cache lacks are computed, here or on Ray (docs/decisions.md, "Teacher runs").
"""

from __future__ import annotations

import dataclasses
import logging
import re
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from pipeline.runtime.errors import InputError
from pipeline.runtime.progress import progress
from pipeline.teachers import teacher_fingerprint
from pipeline.teachers.base import VIEWS, Teacher
from pipeline.teachers.cache import TeacherCache
from pipeline.teachers.distributed import fill_with_ray
from pipeline.teachers.jobs import InputLoader, TeacherBuildArgs, TeacherJob, answer_job, predict_view

__all__ = ["parse_shard", "shard_rows", "RunStats", "TeacherRunner", "open_runner"]

log = logging.getLogger(__name__)


def parse_shard(text: str | None) -> tuple[int, int] | None:
    """Parse ``--shard``: ``"i/n"`` -> (i, n) with 0 <= i < n.

    Parameters
    ----------
    text : str or None
        ``"i/n"``, or None (no sharding).

    Returns
    -------
    tuple of int or None
        (i, n); None for None.

    Raises
    ------
    InputError
        Not ``i/n`` with n >= 1 and 0 <= i < n, naming ``--shard``.
    """
    if text is None:
        return None
    m = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", str(text))
    if not m:
        raise InputError(f"--shard {text!r}: expected i/n, e.g. 0/8 (0 <= i < n)")
    i, n = int(m.group(1)), int(m.group(2))
    if n < 1 or not 0 <= i < n:
        raise InputError(f"--shard {text!r}: need n >= 1 and 0 <= i < n")
    return i, n


def shard_rows(rows: Sequence[int], shard: tuple[int, int] | None) -> list[int]:
    """Select the rows shard (i, n) owns.

    Parameters
    ----------
    rows : sequence of int
        The rows to share out.
    shard : tuple of int or None
        (i, n) of :func:`parse_shard`; None: every row.

    Returns
    -------
    list of int
        Positions i, i+n, ... of ``rows``.
    """
    return list(rows) if shard is None else list(rows)[shard[0]::shard[1]]


@dataclasses.dataclass
class RunStats:
    """What a :class:`TeacherRunner` did.

    Attributes
    ----------
    images_computed : int
        Images the teacher was asked about.
    answers_computed : int
        (image, prompt, view) answers computed.
    cache_hits : int
        Answers found by listing the cache at planning time.
    cache_corrupt : int
        Entries found corrupt at assembly (and recomputed).
    """

    images_computed: int = 0
    answers_computed: int = 0
    cache_hits: int = 0      # answers found by listing at planning time
    cache_corrupt: int = 0   # entries found corrupt at assembly (and recomputed)


class TeacherRunner:
    """Fill the cache for some rows, then read every row's answers back.

    A teacher without ``use_cache`` is asked directly.

    Parameters
    ----------
    teacher : Teacher
        The teacher.
    cache : TeacherCache
        Its cache.
    prompts : sequence of str
        The prompts of eq:prompt-set, answered in the identity view.
    image_sha : callable
        Row -> the image's pixel sha256.
    load : InputLoader
        (row, view) -> :class:`~pipeline.teachers.base.TeacherInput`.
    vflip_prompt : str, optional
        The prompt also answered on the flipped image (:func:`pipeline.teachers.assemble.vflip_prompt`).
    batch_size : int, optional
        Images per job (at least 1).
    spec : TeacherBuildArgs, optional
        How the Ray executor builds the teacher again; needed with ``workers``.

    Attributes
    ----------
    stats : RunStats
        What the runner did.
    """

    def __init__(self, teacher: Teacher, cache: TeacherCache, prompts: Sequence[str],
                 image_sha: Callable[[int], str], load: InputLoader, vflip_prompt: str | None = None,
                 batch_size: int = 1, spec: TeacherBuildArgs | None = None):
        self.teacher = teacher
        self.cache = cache
        self.prompts = list(prompts)
        self.image_sha = image_sha
        self.load = load
        self.vflip_prompt = vflip_prompt
        self.batch_size = max(int(batch_size), 1)
        self.spec = spec
        self.stats = RunStats()

    def requests(self) -> list[tuple[str, str]]:
        """List the (prompt, view) pairs answered per image.

        Returns
        -------
        list of tuple of str
            Each prompt in the identity view, then the vflip prompt's, if any.
        """
        req = [(p, "identity") for p in self.prompts]
        if self.vflip_prompt is not None:
            req.append((self.vflip_prompt, "vflip"))
        return req

    def missing(self, rows: Sequence[int]) -> dict[str, dict[int, list[str]]]:
        """Find the answers the cache lacks, from one listing of it (nothing read); count the hits.

        Parameters
        ----------
        rows : sequence of int
            The rows.

        Returns
        -------
        dict
            View -> row -> its prompts without a cache entry (empty for a teacher without ``use_cache``).
        """
        out: dict[str, dict[int, list[str]]] = {v: {} for v in VIEWS}
        if not self.teacher.use_cache:
            return out
        present = self.cache.listed()
        for row in rows:
            sha = self.image_sha(row)
            for prompt, view in self.requests():
                if self.cache.key(sha, prompt, view) in present:
                    self.stats.cache_hits += 1
                else:
                    out[view].setdefault(row, []).append(prompt)
        return out

    def jobs(self, todo: dict[str, dict[int, list[str]]]) -> list[TeacherJob]:
        """Plan the batches of ``batch_size`` rows per view that compute ``todo`` (identity first).

        Parameters
        ----------
        todo : dict
            :meth:`missing`'s view -> row -> prompts.

        Returns
        -------
        list of TeacherJob
            One forward per job, over the union of its rows' missing prompts.
        """
        jobs = []
        for view in VIEWS:
            pending = sorted(todo[view])
            asked = self.prompts if view == "identity" else [self.vflip_prompt]
            for i in range(0, len(pending), self.batch_size):
                rows = pending[i:i + self.batch_size]
                prompts = tuple(p for p in asked if any(p in todo[view][r] for r in rows))
                jobs.append(TeacherJob(view, tuple(rows), prompts, tuple(tuple(todo[view][r]) for r in rows)))
        return jobs

    def fill(self, rows: Sequence[int], workers: int = 0, address: str | None = None,
             on_batch: Callable[[int, int], None] | None = None) -> RunStats:
        """Compute and cache every missing answer of ``rows``, here (``workers=0``) or on a Ray pool.

        Parameters
        ----------
        rows : sequence of int
            The rows.
        workers : int, optional
            Teachers in a Ray Data pool; 0 (default): serial, the same answers.
        address : str, optional
            The Ray cluster to join with ``workers``.
        on_batch : callable, optional
            ``on_batch(images done, images to do)`` after each finished batch (a job: one view of its rows; an
            image asked in two views counts half when one is done).

        Returns
        -------
        RunStats
            :attr:`stats`, updated.

        Raises
        ------
        ValueError
            ``workers > 0`` for a runner built without ``spec``.
        """
        if not self.teacher.use_cache:
            return self.stats
        todo = self.missing(rows)
        n_images = len(set().union(*(set(t) for t in todo.values())))
        done, views = 0, sum(len(rows) for rows in todo.values())  # a row counts once per view it is asked in

        def finished(job_rows: int) -> None:
            nonlocal done
            done += job_rows
            if on_batch is not None:
                on_batch(done * n_images / views, n_images)

        log.info("teacher[%s]: %d of %d images need answers (%d cached answers reused)",
                 self.teacher.backend, n_images, len(rows), self.stats.cache_hits)
        jobs = self.jobs(todo)
        if workers > 0 and jobs:
            if self.spec is None:
                raise ValueError("TeacherRunner.fill(workers > 0) needs the runner's TeacherBuildArgs")
            self.stats.answers_computed += fill_with_ray(jobs, self.load, self.spec, self.cache.location,
                                                         self.cache.teacher_fingerprint, workers, address,
                                                         on_job=lambda j: finished(len(jobs[j].rows)))
        elif jobs:
            # the bar counts images (a job is a batch of them, per view), not jobs
            with progress(total=sum(len(j.rows) for j in jobs), desc=f"teacher[{self.teacher.backend}]",
                          unit="img") as bar:
                for job in jobs:
                    self.stats.answers_computed += answer_job(self.teacher, self.cache, job, job.inputs(self.load))
                    bar.update(len(job.rows))
                    finished(len(job.rows))
        self.stats.images_computed += n_images
        return self.stats

    def answers(self, row: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, float | None]:
        """Read one row's answers; an entry missing or corrupt here is computed on the spot.

        Parameters
        ----------
        row : int
            The row.

        Returns
        -------
        tuple
            (masks bool [K,H,W], scores float32 [K], vflip mask or None, vflip score or None).
        """
        results: dict[tuple[str, str], tuple[np.ndarray, float]] = {}
        if self.teacher.use_cache:
            sha = self.image_sha(row)
            corrupt = self.cache.stats.corrupt
            for prompt, view in self.requests():
                hit = self.cache.get(self.cache.key(sha, prompt, view))
                if hit is not None:
                    results[(prompt, view)] = hit
            self.stats.cache_corrupt += self.cache.stats.corrupt - corrupt
        for view in VIEWS:
            need = tuple(p for p, v in self.requests() if v == view and (p, v) not in results)
            if not need:
                continue
            job = TeacherJob(view, (row,), need, (need,))
            inputs = job.inputs(self.load)
            if self.teacher.use_cache:
                self.stats.answers_computed += answer_job(self.teacher, self.cache, job, inputs)
                for prompt in need:
                    results[(prompt, view)] = self.cache.get(self.cache.key(self.image_sha(row), prompt, view))
            else:
                masks, scores = predict_view(self.teacher, inputs, need, view)
                for k, prompt in enumerate(need):
                    results[(prompt, view)] = (masks[0, k], float(scores[0, k]))
        masks = np.stack([results[(p, "identity")][0] for p in self.prompts])
        scores = np.array([results[(p, "identity")][1] for p in self.prompts], np.float32)
        vm, vs = results.get((self.vflip_prompt, "vflip"), (None, None))
        return masks, scores, vm, None if vs is None else float(vs)


def open_runner(cfg: Mapping[str, Any], resolution: tuple[int, int], device: str, load: InputLoader,
                shas: Sequence[str], vflip_prompt: str | None = None) -> tuple[TeacherRunner, str]:
    """Build the teacher of a validated ``teacher:`` section behind its cache.

    Parameters
    ----------
    cfg : Mapping
        The validated ``teacher:`` section; images per job: ``teacher.batch_size``, or with 0 the backend's
        own ``runner_batch_size`` (else 2).
    resolution : tuple of int
        (H, W) of the working resolution.
    device : str
        ``auto``, ``cpu`` or ``cuda``.
    load : InputLoader
        (row, view) -> :class:`~pipeline.teachers.base.TeacherInput`.
    shas : sequence of str
        Each row's pixel sha256.
    vflip_prompt : str, optional
        The prompt also answered on the flipped image.

    Returns
    -------
    tuple of (TeacherRunner, str)
        The runner and the teacher's fingerprint.
    """
    spec = TeacherBuildArgs(dict(cfg), tuple(resolution), device)
    teacher = spec.build()
    t_fp = teacher_fingerprint(teacher)
    shas = list(shas)
    runner = TeacherRunner(teacher, TeacherCache(cfg["cache_dir"], t_fp), list(cfg["prompts"]),
                           image_sha=shas.__getitem__, load=load, vflip_prompt=vflip_prompt,
                           batch_size=cfg["batch_size"] or getattr(teacher, "runner_batch_size", 2), spec=spec)
    return runner, t_fp
