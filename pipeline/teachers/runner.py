"""Plan, shard, compute and collect teacher answers through the cache (the teacher stage and ``geodistill
label``): only the answers the cache lacks are computed, here or on Ray (docs/decisions.md, "Teacher runs")."""

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

log = logging.getLogger(__name__)


def parse_shard(text: str | None) -> tuple[int, int] | None:
    """``"i/n"`` -> (i, n) with 0 <= i < n; None passes through; InputError names ``--shard`` otherwise."""
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
    """The rows shard (i, n) owns: positions i, i+n, ... of ``rows`` (all rows when shard is None)."""
    return list(rows) if shard is None else list(rows)[shard[0]::shard[1]]


@dataclasses.dataclass
class RunStats:
    images_computed: int = 0
    answers_computed: int = 0
    cache_hits: int = 0      # answers found by listing at planning time
    cache_corrupt: int = 0   # entries found corrupt at assembly (and recomputed)


class TeacherRunner:
    """Fill the cache for some rows, then read every row's answers back.

    ``image_sha``: row -> sha256; ``load``: (row, view) -> :class:`TeacherInput`; ``spec``: how the Ray
    executor builds the teacher again.  A teacher without ``use_cache`` is asked directly."""

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
        """(prompt, view) pairs answered per image."""
        req = [(p, "identity") for p in self.prompts]
        if self.vflip_prompt is not None:
            req.append((self.vflip_prompt, "vflip"))
        return req

    def missing(self, rows: Sequence[int]) -> dict[str, dict[int, list[str]]]:
        """view -> row -> prompts without a cache entry, from one listing of the cache (nothing read)."""
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
        """The batches of ``batch_size`` rows per view that compute ``todo`` (identity first)."""
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
        """Compute and cache every missing answer of ``rows``, here (``workers=0``) or on a Ray pool;
        ``on_batch(images done, images to do)`` after each finished batch (a job: one view of its rows; an image
        asked in two views counts half when one is done)."""
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
        """(masks bool [K,H,W], scores float32 [K], vflip mask or None, vflip score or None) of one row;
        an entry missing or corrupt here is computed on the spot."""
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
    """(runner, fingerprint) of the teacher of the validated ``teacher:`` section ``cfg``; images per job:
    ``teacher.batch_size``, or with 0 the backend's own unit or 2."""
    spec = TeacherBuildArgs(dict(cfg), tuple(resolution), device)
    teacher = spec.build()
    t_fp = teacher_fingerprint(teacher)
    shas = list(shas)
    runner = TeacherRunner(teacher, TeacherCache(cfg["cache_dir"], t_fp), list(cfg["prompts"]),
                           image_sha=shas.__getitem__, load=load, vflip_prompt=vflip_prompt,
                           batch_size=cfg["batch_size"] or getattr(teacher, "runner_batch_size", 2), spec=spec)
    return runner, t_fp
