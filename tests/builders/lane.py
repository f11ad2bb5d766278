"""The suite's second lane: the long runs that are only subprocesses (a whole DAG under ``dvc repro``, a
``geodistill distill``, a benchmark script), started in the background when the session starts, one at a
time, while the other tests run on the other core; the test that checks a run waits for its result
(imported as ``tests.builders.lane``; the ``lane`` fixture and the fixtures that wait are in tests/conftest.py).

What runs on the lane is the command the test ran before, with the same arguments; only *when* it runs
changed.  So that it stays the same command:

- a job starts subprocesses only -- never torch or numpy's global generators in this process, which a
  test running at the same time seeds and draws from;
- its environment is ``os.environ`` as the session started (:attr:`Lane.env`): a test's
  ``monkeypatch.setenv`` never reaches a job;
- its paths are absolute (a test's ``monkeypatch.chdir`` does not move it);
- each subprocess runs in a process group of its own, killed with the lane when the session ends (also
  on Ctrl-C), so no run outlives pytest.

Each job is keyed by name; :meth:`Lane.submit` queues it once (a second call returns the first future)
and :meth:`Lane.wait` returns its result or raises its exception in the test that waits.
"""

from __future__ import annotations

import atexit
import os
import queue
import shutil
import signal
import subprocess
import sys
import threading
from concurrent.futures import Future
from pathlib import Path

import yaml

from pipeline.params import deep_merge

REPO = Path(__file__).resolve().parents[2]


class Lane:
    """One daemon thread running queued jobs in order; their subprocesses are tracked and killable."""

    def __init__(self):
        self.env = dict(os.environ)  # the session's environment, before any test patches it
        self.jobs: dict[str, Future] = {}
        self._queue: queue.Queue = queue.Queue()
        self._procs: set[subprocess.Popen] = set()
        self._lock = threading.Lock()
        self._closed = False
        threading.Thread(target=self._work, name="tests-lane", daemon=True).start()
        atexit.register(self.close)

    def _work(self) -> None:
        while (item := self._queue.get()) is not None:
            fut, fn, args = item
            if fut.set_running_or_notify_cancel():
                try:
                    fut.set_result(fn(self, *args))
                except BaseException as e:  # noqa: BLE001 -- handed to the test that waits
                    fut.set_exception(e)

    def submit(self, key: str, fn, *args) -> Future:
        """Queue ``fn(lane, *args)`` under ``key`` (once)."""
        with self._lock:
            if key not in self.jobs:
                self.jobs[key] = Future()
                self._queue.put((self.jobs[key], fn, args))
            return self.jobs[key]

    def wait(self, key: str):
        """The result of the job ``key`` (queued by the session's prefetch, or now)."""
        return self.jobs[key].result()

    def run(self, argv, *, cwd, env=None, timeout=None) -> subprocess.CompletedProcess:
        """``subprocess.run(argv, capture_output=True, text=True)`` in a process group of its own."""
        with self._lock:
            if self._closed:
                raise RuntimeError("the test session ended before this run started")
            proc = subprocess.Popen([str(a) for a in argv], cwd=cwd, env=self.env if env is None else env,
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                    start_new_session=True)
            self._procs.add(proc)
        try:
            out, err = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            _kill(proc)
            proc.communicate()
            raise
        finally:
            with self._lock:
                self._procs.discard(proc)
        return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)

    def close(self) -> None:
        """Cancel the queued jobs and kill the running subprocesses (with their children)."""
        with self._lock:
            self._closed = True
            procs = list(self._procs)
        for fut in self.jobs.values():
            fut.cancel()
        self._queue.put(None)
        for proc in procs:
            _kill(proc)


def _kill(proc: subprocess.Popen) -> None:
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass


def bin_first(env: dict) -> dict:
    """``env`` with this interpreter's folder first on PATH (the stage commands are ``python -m ...``)."""
    return {**env, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"}


# ------------------------------------------------------------------------------------------------------
# tests/cli/test_end_to_end.py: the real DAG on a tiny synthetic benchmark, in a temporary copy of the repository
# ------------------------------------------------------------------------------------------------------
TINY_DEMO = {
    "data": {"resolution": 48,
             "synthetic": {"train_spacecraft": 3, "train_views": 4, "val_spacecraft": 2, "val_views": 3,
                           "test_groups": ["KCP", "CVI"], "test_spacecraft_per_group": 2, "test_views": 3}},
    "train": {"epochs_stage1": 2, "epochs_stage2": 1, "num_threads": 1},
    "evaluate": {"bootstrap_resamples": 200},
    "deploy": {"benchmark_iters": 2, "benchmark_warmup": 1, "benchmark_batches": [1, 2]},
}


#: what `dvc repro` rewrites in the repository (a demo may be running beside the tests): never copied half-written
DEMO_WRITES = ("dvc.lock", "reports/metrics/", "reports/plots/", "reports/dvclive/")


def committed_text(path: str) -> str:
    """The repository file ``path`` as committed (HEAD), not as a running demo may be rewriting it; the file
    itself outside a git checkout."""
    r = subprocess.run(["git", "show", f"HEAD:{path}"], cwd=REPO, capture_output=True, text=True)
    return r.stdout if r.returncode == 0 else (REPO / path).read_text()


def copy_repo(dst: Path) -> None:
    """The repository's files (tracked and untracked, not ignored), without tests/, reports/reduced and what
    the demo rewrites (:data:`DEMO_WRITES`)."""
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=REPO, capture_output=True,
                           text=True, check=True).stdout.split()
    for f in files:
        src = REPO / f
        if src.is_file() and not f.startswith(("reports/reduced", "tests/", *DEMO_WRITES)):
            (dst / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dst / f)


def tiny_demo_env(lane: Lane, repo: Path) -> dict:
    """The environment the tiny demo's commands run in: quiet, ``repo`` on the path."""
    return {**bin_first(lane.env), "PYTHONPATH": str(repo), "GEODISTILL_QUIET": "1"}


def tiny_demo_run(lane: Lane, repo: Path) -> tuple[Path, dict, str]:
    """Copy the repository to ``repo``, shrink its params.yaml to :data:`TINY_DEMO` with one seed of each
    of the demo's methods (the demo publishes seed means; one seed keeps this fast), re-render dvc.yaml,
    make it a git repository and run ``dvc repro`` there: (repo, env, the repro's stdout)."""
    repo.mkdir(parents=True, exist_ok=True)
    copy_repo(repo)
    params = deep_merge(yaml.safe_load((repo / "params.yaml").read_text()), TINY_DEMO)
    params["protocol"]["runs"] = {m: seeds[:1] for m, seeds in params["protocol"]["runs"].items()}
    (repo / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    env = tiny_demo_env(lane, repo)
    for cmd in ([sys.executable, "-m", "pipeline.cli.generate"],  # the demo's dvc.yaml lists its seeds: re-render
                ["git", "init", "-q"], [sys.executable, "-m", "dvc", "config", "core.analytics", "false"]):
        r = lane.run(cmd, cwd=repo, env=env)
        assert r.returncode == 0, f"{cmd}: {r.stdout[-2000:]}{r.stderr[-2000:]}"
    first = lane.run([sys.executable, "-m", "dvc", "repro"], cwd=repo, env=env)
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    return repo, env, first.stdout


# ------------------------------------------------------------------------------------------------------
# tests/cli/test_distill.py: ``geodistill distill`` with the tests' tiny random SAM 3, with and without masks
# ------------------------------------------------------------------------------------------------------
#: demo-like tiny sizes: 32 px, Stage I 3 epochs (the recipe's resolution schedule trains the first 2 at 16 px,
#: the last, the decay, at 32 px), Stage II 1, one benchmark variant
DISTILL_FAST = ["--device", "cpu"] + [a for kv in (
    "data.resolution=32", "data.contact_sheet_images=2", "teacher.score_threshold=0", "train.epochs_stage1=3",
    "train.epochs_stage2=1", "train.num_threads=1", "deploy.benchmark_variants=[fp32_eager_nchw]",
    "deploy.benchmark_iters=1", "deploy.benchmark_warmup=0", "deploy.benchmark_batches=[1]",
    "deploy.int8_calibration_images=4", "evaluate.bootstrap_resamples=20", "report.qualitative_images=1",
    "report.pseudo_target_images=1") for a in ("--set", kv)]


def distill_run(lane: Lane, images: Path, out: Path, sam3: Path, *extra) -> tuple[Path, subprocess.CompletedProcess]:
    """``geodistill distill IMAGES --out OUT --checkpoint SAM3 EXTRA`` with :data:`DISTILL_FAST`, as a
    command: (OUT, the finished process)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    return out, lane.run([sys.executable, "-m", "pipeline.cli", "distill", images, "--out", out, "--checkpoint", sam3,
                     *extra, *DISTILL_FAST], cwd=out.parent, env={**bin_first(lane.env), "PYTHONPATH": str(REPO)},
                    timeout=900)


# ------------------------------------------------------------------------------------------------------
# tests/benchmarks/test_benchmarks.py: the benchmark scripts at tiny sizes
# ------------------------------------------------------------------------------------------------------
BENCH_CASES = {
    "bench_memory": ["--n", "2", "--factor", "2", "--size", "32", "--label-size", "32", "--read-size", "32",
                     "--reps", "1"],
    "bench_geometry": ["--n", "4", "--size", "64", "--repeats", "1", "--workers", "1"],
    "bench_synthetic": ["--size", "48", "--views", "2", "--baseline-views", "1"],
    "bench_train": ["--images", "4", "--sizes", "32", "--reps", "1", "--profile-size", "32", "--profile-steps", "1",
                    "--epochs", "1", "--val-images", "2", "--threads", "1", "--set", "train.channels=[4,8,16]"],
    "bench_teacher": ["--images", "2", "--resolution", "32"],
    "bench_evaluate": ["--runs", "3", "--images", "6", "--size", "48", "--resamples", "50", "--repeats", "1",
                       "--student-images", "1"],
    # the teacher benchmark's Ray pools (1 and 2 workers)
    "bench_teacher_ray": ["--ray-workers", "1,2", "--images", "8", "--resolution", "32", "--repeats", "1"],
}


def bench_run(lane: Lane, case: str) -> subprocess.CompletedProcess:
    """``python -m benchmarks.<script> ARGS`` of :data:`BENCH_CASES` ``case`` in the repository."""
    script = case.removesuffix("_ray")
    return lane.run([sys.executable, "-m", f"benchmarks.{script}", *BENCH_CASES[case]], cwd=REPO,
                    timeout=600 if case.endswith("_ray") else 300)


# ------------------------------------------------------------------------------------------------------
# tests/house/test_lane_modules.py: whole test modules in a pytest process of their own (conftest.LANE_MODULES)
# ------------------------------------------------------------------------------------------------------
def pytest_run(lane: Lane, nodeids: list[str], on_lane: str) -> subprocess.CompletedProcess:
    """``python -m pytest -q NODEIDS`` in the repository, with ``on_lane`` set so that process runs them itself."""
    return lane.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *nodeids], cwd=REPO,
                    env={**lane.env, on_lane: "1"}, timeout=1200)
