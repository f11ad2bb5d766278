"""Run a DAG of commands as concurrent processes: dependencies, a bounded pool, GPU slots, a thread budget.

This module knows nothing of DVC.  ``geodistill run`` (:mod:`stages.run`) turns DVC's stage graph into
:class:`Job` s and passes two hooks: ``prepare(job)`` (is it stale? DVC decides, exactly when the job's
upstream jobs are done) and ``record(job)`` (DVC records what ran, in the orchestrating process only,
one stage at a time).  Everything here is testable with fake jobs (``sh -c 'sleep 1'``).

Scheduling rules (decided here, documented in ``geodistill run --help``):

* A job starts once every job it ``needs`` has finished (run or found up to date) and ``prepare`` said
  it must run.  At most ``Resources.jobs`` processes run at once.
* Ready jobs start in priority order: the longest remaining path to the end of the DAG first (weighted
  by ``costs``, e.g. seconds measured by the previous run; 1 per job without), then more descendants,
  then declaration order -- so the Stage-I runs that eight Stage-II runs wait for start before
  independent work.
* ``gpu`` jobs take a slot on a GPU (least-loaded device first, at most ``gpu_slots[d]`` jobs on device
  ``d``) and see only that device (``CUDA_VISIBLE_DEVICES``); other jobs see no GPU.  Without GPUs
  every job is a CPU job.
* CPU threads: each starting job gets an equal share of the cores the running jobs do not hold, at
  least ``cores // jobs`` (:attr:`Resources.min_threads`), through ``OMP_NUM_THREADS`` and friends --
  N processes never ask for N x cores threads (at most about twice the cores in all), and a stage
  running alone (e.g. evaluate at the end) gets all of them.
* ``exclusive`` jobs (those that measure wall time) start only when nothing runs, and nothing starts
  beside them; once such a job is the highest-priority ready job, the pool drains for it.
* A failing job (non-zero exit, or an exception from ``prepare``/``record``) is reported with the last
  error line of its log; its dependents never start.  By default nothing new starts after a failure
  (``keep_going=True``: independent jobs go on); running jobs finish and are recorded, so a rerun
  resumes.  Ctrl-C terminates every running job (its process group) and records nothing partial.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import time
from collections import Counter
from pathlib import Path
from typing import Callable, Iterable, Mapping, Sequence

from pipeline.environment import THREAD_ENV_VARS


@dataclasses.dataclass(frozen=True)
class Job:
    """One command of the DAG.  ``argv`` runs in ``cwd`` with the parent's environment plus ``env``."""

    name: str
    argv: tuple[str, ...]
    needs: frozenset[str] = frozenset()
    gpu: bool = False          # may use a GPU: placed on a GPU slot where there are GPUs
    exclusive: bool = False    # measures wall time: runs alone
    cwd: str | None = None
    env: Mapping[str, str] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class Resources:
    """What the pool may use: ``jobs`` processes, ``cores`` CPU threads in all, ``gpu_slots`` device
    id -> concurrent jobs on it (empty: no GPU)."""

    jobs: int
    cores: int
    gpu_slots: Mapping[str, int] = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        if self.jobs < 1 or self.cores < 1 or any(n < 1 for n in self.gpu_slots.values()):
            raise ValueError(f"resources need jobs >= 1, cores >= 1 and >= 1 job per GPU: {self}")

    @property
    def min_threads(self) -> int:
        """The fewest threads a job gets: cores // jobs (>= 1).  A process keeps the thread count it
        started with, so a long job started beside short ones would otherwise keep a small share."""
        return max(1, self.cores // self.jobs)


@dataclasses.dataclass(frozen=True)
class Placement:
    """Where a started job runs: ``device`` (a GPU id, or None for CPU only) and its CPU ``threads``."""

    device: str | None
    threads: int


@dataclasses.dataclass
class JobRecord:
    """What happened to one job.  ``status``: ran | up_to_date | failed | not_run; times in seconds
    since the start of the run."""

    status: str = "pending"
    start: float | None = None
    end: float | None = None
    device: str | None = None
    threads: int | None = None
    returncode: int | None = None
    record_s: float | None = None  # seconds spent recording it (DVC: hashes, cache, dvc.lock) after it exited
    error: str | None = None
    log: str | None = None

    @property
    def seconds(self) -> float | None:
        return None if self.start is None or self.end is None else self.end - self.start


@dataclasses.dataclass
class RunReport:
    records: dict[str, JobRecord]
    wall_s: float
    resources: Resources

    @property
    def ok(self) -> bool:
        return all(r.status in ("ran", "up_to_date") for r in self.records.values())

    def failed(self) -> list[str]:
        return [n for n, r in self.records.items() if r.status == "failed"]

    def to_dict(self) -> dict:
        return {"wall_s": round(self.wall_s, 3),
                "resources": {"jobs": self.resources.jobs, "cores": self.resources.cores,
                              "gpu_slots": dict(self.resources.gpu_slots)},
                "jobs": {n: {**{k: v for k, v in dataclasses.asdict(r).items() if v is not None},
                             **({"seconds": round(r.seconds, 3)} if r.seconds is not None else {})}
                         for n, r in self.records.items()}}


# --------------------------------------------------------------------------------------------------
# Pure scheduling
# --------------------------------------------------------------------------------------------------
def topological_order(jobs: Sequence[Job]) -> list[str]:
    """Job names, every job after the jobs it needs (declaration order among independent ones).

    Raises ValueError naming an unknown need, a duplicate name or a job on a cycle."""
    names = [j.name for j in jobs]
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise ValueError(f"job {dup!r} is declared twice")
    known = set(names)
    for j in jobs:
        unknown = sorted(j.needs - known)
        if unknown:
            raise ValueError(f"job {j.name!r} needs unknown job(s) {unknown}")
    by_name = {j.name: j for j in jobs}
    done: list[str] = []
    placed: set[str] = set()
    remaining = list(names)
    while remaining:
        ready = [n for n in remaining if by_name[n].needs <= placed]
        if not ready:
            raise ValueError(f"dependency cycle among jobs {sorted(remaining)}")
        done.extend(ready)
        placed.update(ready)
        remaining = [n for n in remaining if n not in placed]
    return done


def waves(jobs: Sequence[Job]) -> list[list[str]]:
    """Topological levels: wave k holds the jobs whose longest chain of needs has k jobs (for display;
    the scheduler itself starts a job as soon as its own needs are done, not wave by wave)."""
    by_name = {j.name: j for j in jobs}
    level: dict[str, int] = {}
    for n in topological_order(jobs):
        level[n] = 1 + max((level[m] for m in by_name[n].needs), default=-1)
    out: list[list[str]] = [[] for _ in range(max(level.values(), default=-1) + 1)]
    for j in jobs:
        out[level[j.name]].append(j.name)
    return out


def priorities(jobs: Sequence[Job], costs: Mapping[str, float] | None = None) -> dict[str, tuple]:
    """Sort key per job, smaller first: (-longest cost-weighted path from the job to a sink,
    -number of descendants, declaration index).  ``costs`` default to 1 per job."""
    costs = costs or {}
    order = topological_order(jobs)
    children: dict[str, list[str]] = {j.name: [] for j in jobs}
    for j in jobs:
        for m in j.needs:
            children[m].append(j.name)
    path: dict[str, float] = {}
    desc: dict[str, set[str]] = {}
    for n in reversed(order):
        path[n] = float(costs.get(n, 1.0)) + max((path[c] for c in children[n]), default=0.0)
        desc[n] = set(children[n]).union(*(desc[c] for c in children[n])) if children[n] else set()
    index = {j.name: i for i, j in enumerate(jobs)}
    return {n: (-path[n], -len(desc[n]), index[n]) for n in index}


def pick(queue: Sequence[Job], running: Mapping[str, tuple[Job, Placement]], res: Resources) -> list[tuple[Job, Placement]]:
    """Which queued jobs start now and where.  ``queue`` is the ready jobs in priority order.

    Pure: the rules of the module docstring (pool bound, GPU slots, exclusive jobs, thread shares)."""
    if any(job.exclusive for job, _ in running.values()):
        return []
    gpu_ids = list(res.gpu_slots)
    load = Counter(p.device for _, p in running.values() if p.device is not None)
    chosen: list[tuple[Job, str | None]] = []
    for job in queue:
        if job.exclusive:
            if not running and not chosen:
                chosen.append((job, gpu_ids[0] if job.gpu and gpu_ids else None))
            break  # the pool drains for it: lower-priority jobs wait
        if len(running) + len(chosen) >= res.jobs:
            break
        device = None
        if job.gpu and gpu_ids:
            free = [d for d in gpu_ids if load[d] < res.gpu_slots[d]]
            if not free:
                continue  # waits for a GPU slot; CPU jobs behind it may start
            device = min(free, key=lambda d: (load[d], gpu_ids.index(d)))
            load[device] += 1
        chosen.append((job, device))
    if not chosen:
        return []
    if chosen[0][0].exclusive:
        return [(chosen[0][0], Placement(chosen[0][1], res.cores))]
    held = sum(p.threads for _, p in running.values())
    base, extra = divmod(max(res.cores - held, 0), len(chosen))
    return [(job, Placement(dev, max(res.min_threads, base + (1 if i < extra else 0))))
            for i, (job, dev) in enumerate(chosen)]


def child_env(base: Mapping[str, str], job: Job, place: Placement, has_gpus: bool) -> dict[str, str]:
    """The environment of a started job: ``base`` + the job's own + its thread count + its device."""
    env = {**base, **job.env}
    for var in THREAD_ENV_VARS:
        env[var] = str(place.threads)
    if has_gpus:
        env["CUDA_DEVICE_ORDER"] = "PCI_BUS_ID"  # CUDA numbers devices as nvidia-smi does
        env["CUDA_VISIBLE_DEVICES"] = place.device if place.device is not None else ""
    return env


def error_line(log_text: str, limit: int = 300) -> str:
    """The line that says why a job failed: the last ``...: error: ...`` line (the stage commands' one-line
    InputError), else the last non-empty line (a traceback's exception line); shortened to ``limit``."""
    lines = [ln.strip() for ln in log_text.replace("\r", "\n").splitlines() if ln.strip()]
    errors = [ln for ln in lines if ": error: " in ln or ln.startswith("ERROR")]
    line = (errors or lines or ["(no output)"])[-1]
    return line if len(line) <= limit else line[: limit - 3] + "..."


# --------------------------------------------------------------------------------------------------
# The process pool
# --------------------------------------------------------------------------------------------------
def run_jobs(jobs: Sequence[Job], res: Resources, log_dir: str | Path, *,
             prepare: Callable[[Job], bool] = lambda job: True,
             record: Callable[[Job], None] = lambda job: None,
             costs: Mapping[str, float] | None = None,
             keep_going: bool = False,
             echo: Callable[[str], None] = print,
             base_env: Mapping[str, str] | None = None,
             poll_s: float = 0.1) -> RunReport:
    """Run ``jobs`` as concurrent processes under ``res``; each one's stdout+stderr go to
    ``log_dir/<name>.log``.

    ``prepare(job)`` is called (in this process) once all of the job's needs are done: True -> it runs,
    False -> it is up to date.  ``record(job)`` is called after it exits 0.  Both run here, one at a
    time, never concurrently.  Returns the report; never raises for a failing job."""
    order = topological_order(jobs)
    by_name = {j.name: j for j in jobs}
    prio = priorities(jobs, costs)
    log_dir = Path(log_dir)
    log_dir.mkdir(parents=True, exist_ok=True)
    base = dict(os.environ if base_env is None else base_env)
    has_gpus = bool(res.gpu_slots)
    recs = {n: JobRecord() for n in order}
    queue: list[Job] = []
    running: dict[str, tuple[Job, Placement]] = {}
    procs: dict[str, tuple[subprocess.Popen, object]] = {}
    t0 = time.monotonic()
    stopping = False
    now = lambda: time.monotonic() - t0  # noqa: E731

    def fail(name: str, error: str) -> None:
        nonlocal stopping
        r = recs[name]
        r.status, r.error, r.end = "failed", error, r.end if r.end is not None else now()
        echo(f"[{now():7.1f}s] FAILED {name}: {error}" + (f"   (log: {r.log})" if r.log else ""))
        stopping = stopping or not keep_going

    def resolve() -> None:
        """Prepare every pending job whose needs are done; mark those behind a failure not_run."""
        changed = True
        while changed:
            changed = False
            for n in order:
                r = recs[n]
                if r.status != "pending":
                    continue
                states = [recs[m].status for m in by_name[n].needs]
                if any(s in ("failed", "not_run") for s in states):
                    r.status, changed = "not_run", True
                    continue
                if stopping or not all(s in ("ran", "up_to_date") for s in states):
                    continue
                try:
                    must_run = prepare(by_name[n])
                except Exception as e:  # a DVC error naming the stage: the job fails, the run goes on
                    fail(n, f"{type(e).__name__}: {e}".splitlines()[0])
                    changed = True
                    continue
                if must_run:
                    r.status = "queued"
                    queue.append(by_name[n])
                else:
                    r.status, changed = "up_to_date", True
        queue.sort(key=lambda j: prio[j.name])

    def launch(job: Job, place: Placement) -> None:
        log = log_dir / f"{job.name}.log"
        fh = open(log, "wb")
        try:
            p = subprocess.Popen(list(job.argv), cwd=job.cwd, env=child_env(base, job, place, has_gpus),
                                 stdin=subprocess.DEVNULL, stdout=fh, stderr=subprocess.STDOUT,
                                 start_new_session=True)  # own process group: Ctrl-C stops all of it
        except OSError as e:
            fh.close()
            recs[job.name].log = str(log)
            fail(job.name, f"cannot start {job.argv[0]!r}: {e}")
            return
        r = recs[job.name]
        r.status, r.start, r.device, r.threads, r.log = "running", now(), place.device, place.threads, str(log)
        running[job.name] = (job, place)
        procs[job.name] = (p, fh)
        where = f"GPU {place.device}" if place.device is not None else "CPU"
        echo(f"[{r.start:7.1f}s] start  {job.name} ({where}, {place.threads} thread{'s' * (place.threads > 1)})")

    def exited(name: str, rc: int) -> bool:
        """Free the job's slot; a non-zero exit fails it.  True: it exited 0 and awaits recording."""
        running.pop(name)
        p, fh = procs.pop(name)
        fh.close()
        r = recs[name]
        r.end, r.returncode = now(), rc
        if rc != 0:
            text = Path(r.log).read_text(errors="replace") if r.log else ""
            fail(name, f"exit {rc}: {error_line(text)}")
        return rc == 0

    def recorded(name: str) -> None:
        r = recs[name]
        t = time.monotonic()
        try:
            record(by_name[name])
        except Exception as e:
            fail(name, f"recording failed: {type(e).__name__}: {e}".splitlines()[0])
            return
        r.status, r.record_s = "ran", time.monotonic() - t
        echo(f"[{now():7.1f}s] done   {name} ({r.seconds:.1f} s)")

    def start_what_fits() -> None:
        if not stopping:
            for job, place in pick(queue, running, res):
                queue.remove(job)
                launch(job, place)

    try:
        while True:
            resolve()
            start_what_fits()
            if not running:
                if queue and not stopping:
                    raise RuntimeError(f"scheduler stalled with queued jobs {[j.name for j in queue]}")
                break
            time.sleep(poll_s)
            ok = [n for n in list(running) if (rc := procs[n][0].poll()) is not None and exited(n, rc)]
            if ok:
                start_what_fits()  # fill the freed slots first: recording (hashing, caching) takes a while
                for n in ok:
                    recorded(n)
    except BaseException:
        _terminate(procs)
        raise
    for n, r in recs.items():
        if r.status in ("pending", "queued"):
            r.status = "not_run"
    return RunReport(recs, now(), res)


def _terminate(procs: Mapping[str, tuple[subprocess.Popen, object]], grace_s: float = 10.0) -> None:
    """SIGTERM every running job's process group, SIGKILL what is left after ``grace_s``."""
    for p, _ in procs.values():
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
    deadline = time.monotonic() + grace_s
    for p, fh in procs.values():
        try:
            p.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            p.wait()
        fh.close()


def overlapping(report: RunReport | Mapping, names: Iterable[str]) -> bool:
    """True when the jobs ``names`` all ran at one moment (their [start, end] intervals intersect)."""
    jobs = report.to_dict()["jobs"] if isinstance(report, RunReport) else report["jobs"]
    spans = [(jobs[n]["start"], jobs[n]["end"]) for n in names]
    return max(s for s, _ in spans) < min(e for _, e in spans)


def write_timeline(report: RunReport, path: str | Path, costs: Mapping[str, float] | None = None) -> Path:
    """The run's timeline as JSON: per job status, start, end, seconds, device, threads, record_s; and
    ``costs``, the seconds each job took when it last ran (``costs`` from before, updated by this run),
    which the next run's :func:`priorities` weigh the critical path with."""
    from pipeline.artifacts import write_json

    obj = report.to_dict()
    obj["costs"] = {**(costs or {}), **{n: j["seconds"] for n, j in obj["jobs"].items()
                                          if j["status"] == "ran" and "seconds" in j}}
    return write_json(path, obj)


def read_costs(path: str | Path) -> dict[str, float]:
    """The ``costs`` of a previous run's timeline ({} when there is none or it is unreadable)."""
    try:
        return {str(n): float(v) for n, v in json.loads(Path(path).read_text())["costs"].items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}
