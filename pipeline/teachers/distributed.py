"""The teacher as a Ray Data pipeline (the ``cluster`` extra; docs/scaling.md).

Jobs -> CPU decode -> teacher actors (:func:`pipeline.teachers.jobs.answer_job`, as the serial loop) -> cache.
"""

from __future__ import annotations

import contextlib
import logging
import os
from typing import Callable, Sequence

import numpy as np

from pipeline.runtime.errors import InputError
from pipeline.teachers.cache import TeacherCache
from pipeline.teachers.jobs import InputLoader, TeacherBuildArgs, TeacherJob, answer_job

__all__ = ["NO_RAY", "decode_jobs", "TeacherWorker", "JOBS_PER_BLOCK", "job_blocks", "ray_session", "fill_with_ray"]

log = logging.getLogger(__name__)

#: the one line when Ray is not installed
NO_RAY = "the teacher's Ray workers need Ray: pip install -e '.[cluster]' (or run with 0 workers: the serial loop)"


def decode_jobs(batch: dict, jobs: Sequence[TeacherJob], load: InputLoader) -> dict:
    """Decode the images of a batch of jobs: the Ray Data CPU step.

    Parameters
    ----------
    batch : dict
        Ray Data's batch: ``job``, the job indices.
    jobs : sequence of TeacherJob
        Every job.
    load : InputLoader
        ``(row, view) -> TeacherInput``.

    Returns
    -------
    dict
        ``job`` and ``inputs``: per job index, the list of its
        :class:`~pipeline.teachers.base.TeacherInput` (images in the job's view).
    """
    inputs = np.empty(len(batch["job"]), dtype=object)
    for i, j in enumerate(batch["job"]):
        inputs[i] = jobs[int(j)].inputs(load)
    return {"job": batch["job"], "inputs": inputs}


class TeacherWorker:
    """Ray Data actor: one teacher (built once per actor) answering jobs into the cache.

    Parameters
    ----------
    spec : TeacherBuildArgs
        What builds the teacher.
    cache_root : str
        The teacher cache's location (:attr:`TeacherCache.location`).
    fingerprint : str
        The teacher's fingerprint.
    jobs : sequence of TeacherJob
        Every job.
    """

    def __init__(self, spec: TeacherBuildArgs, cache_root: str, fingerprint: str, jobs: Sequence[TeacherJob]):
        self.teacher = spec.build()
        self.cache = TeacherCache(cache_root, fingerprint)
        self.jobs = jobs

    def __call__(self, batch: dict) -> dict:
        """Answer a batch of decoded jobs into the cache (:func:`pipeline.teachers.jobs.answer_job`).

        Parameters
        ----------
        batch : dict
            ``job`` (indices) and ``inputs`` (:func:`decode_jobs`).

        Returns
        -------
        dict
            ``job`` and ``written``: the entries each job wrote.
        """
        written = [answer_job(self.teacher, self.cache, self.jobs[int(j)], list(inputs))
                   for j, inputs in zip(batch["job"], batch["inputs"])]
        return {"job": batch["job"], "written": np.asarray(written, np.int64)}


#: jobs per Ray Data block (one actor task): amortises Ray's per-task cost without leaving one teacher
#: alone on a large last block (measured in docs/scaling.md)
JOBS_PER_BLOCK = 4


def job_blocks(n_jobs: int, workers: int, jobs_per_block: int = JOBS_PER_BLOCK) -> int:
    """Count the Ray Data blocks for ``n_jobs`` jobs on ``workers`` teachers.

    Parameters
    ----------
    n_jobs : int
        The jobs.
    workers : int
        The teachers in the pool.
    jobs_per_block : int, optional
        About this many jobs per block (default :data:`JOBS_PER_BLOCK`).

    Returns
    -------
    int
        A multiple of ``workers`` (none idles while another finishes an extra one), between one and
        ``n_jobs``.
    """
    if n_jobs < 1:
        return 1
    workers = max(int(workers), 1)
    per_round = workers * max(int(jobs_per_block), 1)
    return max(1, min(n_jobs, workers * -(-n_jobs // per_round)))


@contextlib.contextmanager
def ray_session(address: str | None = None):
    """Start or join Ray for the ``with`` block; reused when already up (and then left up).

    Parameters
    ----------
    address : str, optional
        The cluster to join; None: ``RAY_ADDRESS``, else an embedded local one.

    Yields
    ------
    module
        The ``ray`` module, initialised.

    Raises
    ------
    InputError
        Ray is not installed (:data:`NO_RAY`).
    """
    try:
        import ray
    except ImportError:
        raise InputError(NO_RAY) from None
    started_here = not ray.is_initialized()
    if started_here:
        ray.init(address=address or os.environ.get("RAY_ADDRESS") or "local", include_dashboard=False,
                 log_to_driver=False, logging_level="WARNING", configure_logging=True)
    try:
        yield ray
    finally:
        if started_here:
            ray.shutdown()


def fill_with_ray(jobs: Sequence[TeacherJob], load: InputLoader, spec: TeacherBuildArgs, cache_root: str,
                  fingerprint: str, workers: int, address: str | None = None,
                  on_job: Callable[[int], None] | None = None) -> int:
    """Run ``jobs`` on a Ray Data actor pool of ``workers`` teachers, one GPU (or CPU) each.

    Parameters
    ----------
    jobs : sequence of TeacherJob
        The jobs.
    load : InputLoader
        ``(row, view) -> TeacherInput``, picklable.
    spec : TeacherBuildArgs
        What builds the teacher in each actor.
    cache_root : str
        The teacher cache's location (:attr:`TeacherCache.location`).
    fingerprint : str
        The teacher's fingerprint.
    workers : int
        The teachers in the pool.
    address : str, optional
        The Ray cluster to join (:func:`ray_session`).
    on_job : callable, optional
        ``on_job(job index)`` as each job's answers come back (in the order they finish).

    Returns
    -------
    int
        The cache entries written.

    Raises
    ------
    InputError
        The cluster has fewer GPUs (or CPUs) than ``workers``.
    """
    jobs = list(jobs)
    with ray_session(address) as ray:
        ctx = ray.data.DataContext.get_current()
        ctx.enable_progress_bars = False
        resources = ray.cluster_resources()
        gpus = float(resources.get("GPU", 0.0)) if spec.device != "cpu" else 0.0
        slots, unit = (gpus, "GPUs") if gpus else (float(resources.get("CPU", 0.0)), "CPUs")
        if workers > slots:  # the pool would wait forever for the missing actors
            raise InputError(f"--workers {workers}: the Ray cluster has {slots:g} {unit} (one teacher each)")
        log.info("teacher: Ray Data pool of %d teachers (%s), %d jobs", workers,
                 "one GPU each" if gpus else "one CPU each", len(jobs))
        ds = ray.data.from_items([{"job": i} for i in range(len(jobs))],
                                 override_num_blocks=job_blocks(len(jobs), workers))
        # Ray Data fuses decode into the teacher actors when both ask for the same resources (CPU-only)
        ds = ds.map_batches(decode_jobs, fn_kwargs={"jobs": jobs, "load": load}, batch_size=1, num_cpus=1.0)
        ds = ds.map_batches(TeacherWorker, fn_constructor_kwargs={"spec": spec, "cache_root": cache_root,
                                                                  "fingerprint": fingerprint, "jobs": jobs},
                            batch_size=1, compute=ray.data.ActorPoolStrategy(size=workers),
                            num_cpus=1.0, num_gpus=1.0 if gpus else 0.0)
        written = 0
        for row in ds.iter_rows():
            written += int(row["written"])
            if on_job is not None:
                on_job(int(row["job"]))
        return written
