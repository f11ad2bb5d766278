"""``geodistill run`` on Ray: each stale stage is a Ray task running DVC's own command for it (docs/scaling.md)."""

from __future__ import annotations

import dataclasses
import fcntl
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

from pipeline import catalog
from pipeline.artifacts.atomic import write_json
from pipeline.cluster import guard, plan
from pipeline.artifacts.provenance import THREAD_ENV_VARS
from pipeline.runtime.device import STAGE_CPUS_ENV
from pipeline.runtime.errors import InputError
from pipeline.params import DEFAULT_PARAMS, read_yaml_mapping

__all__ = ["run_pipeline"]

LOCK_FILE = ".dvc/tmp/geodistill-run.lock"
NO_RAY = ("geodistill run needs Ray: pip install -e '.[cluster]' "
          "(or run the DAG one stage at a time with dvc repro)")


class RunLock:
    """Hold an exclusive, non-blocking ``flock`` on :data:`LOCK_FILE` while ``geodistill run`` drives.

    A second driver gets :class:`InputError`; the kernel releases the lock however the holder dies.
    """

    def __init__(self, root: Path):
        self.path = Path(root) / LOCK_FILE
        self.fd: int | None = None

    def __enter__(self) -> "RunLock":
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "?"
            os.close(fd)
            raise InputError(f"another geodistill run (pid {holder}) is running on {self.path.parents[2]}; "
                             "wait for it or stop it") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        self.fd = fd
        return self

    def __exit__(self, *exc) -> None:
        if self.fd is not None:
            fcntl.flock(self.fd, fcntl.LOCK_UN)
            os.close(self.fd)
            self.fd = None


def dvc(root: Path, *args: str, env: dict | None = None) -> str:
    """Run ``python -m dvc ARGS`` in ``root`` and return its stdout; DVC's error line as :class:`InputError`."""
    proc = subprocess.run([sys.executable, "-m", "dvc", *args], cwd=root, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise InputError(f"dvc {' '.join(args)}: {plan.error_line(proc.stderr + proc.stdout)}")
    return proc.stdout


def read_plan(root: Path, targets: tuple[str, ...] = ()) -> tuple[list[str], dict[str, set[str]], set[str]]:
    """Read (stages in DVC's order, {stage: upstream}, stale stages) from ``dvc dag --dot`` and ``dvc status``."""
    order, needs = plan.parse_dot(dvc(root, "dag", "--dot"))
    unknown = [t for t in targets if t not in needs]
    if unknown:
        raise InputError(f"geodistill run: no stage named {', '.join(unknown)} (see dvc stage list)")
    raw = dvc(root, "--wait-for-lock", "status", "--json").strip() or "{}"
    stale = {n for n in json.loads(raw) if n in needs}
    return order, needs, stale


def child_env(extra: dict[str, str], threads: int, gpus: float) -> dict[str, str]:
    """Build a stage process's environment: this worker's, ``extra``, ``threads`` per pool, no GPU unless it has one."""
    env = {**os.environ, **extra}
    env.update({k: str(max(1, threads)) for k in (*THREAD_ENV_VARS, STAGE_CPUS_ENV)})
    if gpus <= 0:
        env["CUDA_VISIBLE_DEVICES"] = ""
    return env


def run_stage(root: str, stage: str, extra_env: dict, threads: int, gpus: float, log_path: str, t0: float,
              *upstream: dict) -> dict:
    """Run one stage as a Ray task: ``dvc --wait-for-lock repro --single-item STAGE`` under the guard.

    Its output goes to ``log_path``; the result is ``not_run`` when an ``upstream`` result did not succeed.
    """
    import ray

    failed = [u["stage"] for u in upstream if u["status"] in ("failed", "not_run")]
    if failed:
        return {"stage": stage, "status": "not_run", "error": f"upstream {', '.join(failed)} did not run"}
    cmd = guard.command(os.getpid(), [sys.executable, "-m", "dvc", "--wait-for-lock", "repro", "--single-item", stage])
    start = time.time() - t0
    Path(log_path).parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "w") as log:
        rc = subprocess.call(cmd, cwd=root, env=child_env(extra_env, threads, gpus), stdout=log,
                             stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)
    end = time.time() - t0
    text = Path(log_path).read_text(errors="replace")
    return {"stage": stage, "status": plan.outcome(text) if rc == 0 else "failed", "start": start, "end": end,
            "returncode": rc, "error": None if rc == 0 else f"exit {rc}: {plan.error_line(text)}",
            "node": socket.gethostname(), "node_id": ray.get_runtime_context().get_node_id()}


def driver_env() -> dict[str, str]:
    """Pass on PATH with this interpreter's folder first (stage commands say ``python``), PYTHONPATH, GEODISTILL_*."""
    env = {"PATH": os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")])}
    env.update({k: v for k, v in os.environ.items() if k == "PYTHONPATH" or k.startswith("GEODISTILL_")})
    return env


def read_costs(path: Path) -> dict[str, float]:
    """Read the seconds each stage took when it last ran ({} without a previous timeline)."""
    try:
        return {str(n): float(v) for n, v in json.loads(Path(path).read_text())["costs"].items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}


def stage_log(stage: str) -> str:
    """Name a stage's log file in the run's log folder."""
    return catalog.output_file("run_logs", "stage_log").format(stage=stage)


def write_timeline(path: Path, results: dict[str, dict], resources: dict, wall_s: float,
                   costs: dict[str, float]) -> Path:
    """Write the run as JSON (atomic), ``costs`` updated with the seconds of the stages that ran."""
    ran = {n: r["end"] - r["start"] for n, r in results.items() if r.get("status") == "ran"}
    return write_json(path, {"wall_s": wall_s, "resources": resources, "stages": results, "costs": {**costs, **ran}})


def sizing(ray, stage_cpus: float | None, train_gpu_fraction: float, train_threads: int = 0) -> plan.Sizing:
    """Measure what the connected Ray cluster offers (a CPU stage's default: half the largest node, at least 1)."""
    nodes = [n for n in ray.nodes() if n.get("Alive")]
    node_cpus = max((n["Resources"].get("CPU", 0.0) for n in nodes), default=1.0) or 1.0
    total = ray.cluster_resources()
    return plan.Sizing(node_cpus=node_cpus, gpus=float(total.get("GPU", 0.0)),
                       stage_cpus=stage_cpus or max(1.0, node_cpus // 2), train_gpu_fraction=train_gpu_fraction,
                       train_threads=train_threads, cluster_cpus=float(total.get("CPU", node_cpus)))


def pinned_train_threads(root: Path) -> int:
    """Read ``train.num_threads`` of params.yaml; 0 when unreadable (DVC reports a bad params file itself)."""
    try:
        value = read_yaml_mapping(root / DEFAULT_PARAMS).get("train", {}).get("num_threads", 0)
        return max(0, int(value or 0))
    except (InputError, OSError, TypeError, ValueError, AttributeError):
        return 0


@dataclasses.dataclass
class RunResult:
    """What :func:`run_pipeline` ran: each stage's result record (``status`` among them) and the wall time."""

    results: dict[str, dict]
    wall_s: float

    def count(self, status: str) -> int:
        return sum(r["status"] == status for r in self.results.values())

    @property
    def ok(self) -> bool:
        return all(r["status"] in ("ran", "restored", "up_to_date") for r in self.results.values())


def run_pipeline(root: Path, targets: tuple[str, ...] = (), address: str | None = None,
                 stage_cpus: float | None = None, train_gpu_fraction: float = 0.25, dry_run: bool = False,
                 echo: Callable[[str], None] = print) -> RunResult | None:
    """Run the DVC pipeline's stale stages as Ray tasks: ``geodistill run`` without the CLI.

    Each submitted stage runs ``dvc --wait-for-lock repro --single-item STAGE`` once its upstream stages have
    finished and the cluster has room (:mod:`pipeline.cluster.plan`), so DVC records every stage as ``dvc repro``
    would; a failed stage's dependents do not run.  Ray: this process's session if there is one, else
    ``address``, ``RAY_ADDRESS`` or an embedded local one; a session this call opens is shut down at the end.
    Logs and the timeline go to the ``run_logs`` artifact.

    Parameters
    ----------
    root : Path
        The project folder (holding dvc.yaml).
    targets : tuple[str, ...], optional
        The stages asked for (with their upstream stages); empty: the whole pipeline.
    address : str, optional
        The Ray cluster to join when no session is open; None: ``RAY_ADDRESS``, else a local one.
    stage_cpus : float, optional
        The CPUs a CPU stage takes; None: half the largest node, at least 1.
    train_gpu_fraction : float, optional
        The share of a GPU one training run takes.
    dry_run : bool, optional
        Print each stage's resources and upstream stages through ``echo`` instead of running.
    echo : Callable[[str], None], optional
        Where the progress lines go.

    Returns
    -------
    RunResult or None
        Each stage's result and the wall seconds (no stages: an empty result); None for a dry run.

    Raises
    ------
    pipeline.runtime.errors.InputError
        ``root`` holds no dvc.yaml, another ``geodistill run`` holds the project's lock, Ray is not installed,
        a target is no stage, or a ``dvc`` command fails.
    """
    root = Path(root).resolve()
    if not (root / catalog.DVC_FILE).is_file():
        raise InputError(f"{root / catalog.DVC_FILE}: not found (run geodistill run in the project folder)")
    with RunLock(root):
        try:
            import ray
        except ImportError:
            raise InputError(NO_RAY) from None
        order, needs, stale = read_plan(root, targets)
        chosen = plan.to_submit(needs, stale, targets)
        graph = plan.run_alone(plan.subgraph(needs, chosen))
        log_dir = catalog.path("run_logs", root / catalog.ARTIFACTS_DIR)
        costs = read_costs(log_dir / catalog.output_file("run_logs", "timeline"))
        sequence = plan.submission_order(graph, costs, order)
        echo(f"geodistill run: {len(order)} stages, {len(sequence)} to check with dvc repro: "
             + (", ".join(sequence) or "nothing to do"))
        if not sequence:
            return RunResult({}, 0.0)
        started_here = not ray.is_initialized()
        if started_here:
            addr = address or os.environ.get("RAY_ADDRESS") or "local"
            ray.init(address=addr, include_dashboard=False, log_to_driver=False, logging_level="WARNING",
                     configure_logging=True)
        try:
            return _submit(ray, root, sequence, graph,
                           sizing(ray, stage_cpus, train_gpu_fraction, pinned_train_threads(root)), log_dir,
                           costs, dry_run, echo)
        finally:
            if started_here:
                ray.shutdown()


def _submit(ray, root: Path, sequence: list[str], graph: dict[str, set[str]], size: plan.Sizing, log_dir: Path,
            costs: dict[str, float], dry_run: bool, echo) -> RunResult | None:
    """Run the stages of ``sequence`` as Ray tasks and wait for all.

    Each is handed to Ray when its upstream stages have finished and the cluster has room
    (:func:`pipeline.cluster.plan.startable`, in ``sequence``'s priority).
    """
    res = {n: plan.stage_resources(n, size) for n in sequence}
    echo(f"geodistill run: Ray cluster with {size.node_cpus:g} CPUs on its largest node, {size.gpus:g} GPUs")
    if dry_run:
        for n in sequence:
            ups = ", ".join(sorted(graph[n])) or "-"
            echo(f"  {n}: {res[n]['num_cpus']:g} CPU, {res[n]['num_gpus']:g} GPU; after {ups}")
        return None
    task = ray.remote(run_stage)
    extra, t0 = driver_env(), time.time()
    results: dict[str, dict] = {}
    pending: dict[object, str] = {}
    while len(results) < len(sequence):
        for n in plan.startable(sequence, graph, results, {m: res[m] for m in pending.values()}, res,
                                size.capacity):
            r = res[n]
            pending[task.options(name=f"stage:{n}", max_retries=1, **r).remote(
                str(root), n, extra, int(r["num_cpus"]), r["num_gpus"], str(log_dir / stage_log(n)), t0,
                *[results[u] for u in sorted(graph[n])])] = n
        done, _ = ray.wait(list(pending), num_returns=1)
        n = pending.pop(done[0])
        out = results[n] = {**ray.get(done[0]), **res[n]}
        if out["status"] == "failed":
            echo(f"geodistill run: FAILED {n}: {out['error']} (log: {log_dir / stage_log(n)})")
        elif out["status"] != "not_run":
            echo(f"geodistill run: {n} {out['status']} in {out['end'] - out['start']:.1f} s")
    wall = time.time() - t0
    write_timeline(log_dir / catalog.output_file("run_logs", "timeline"), results,
                   {"node_cpus": size.node_cpus, "gpus": size.gpus}, wall, costs)
    return RunResult(results, wall)
