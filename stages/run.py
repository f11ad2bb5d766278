"""``geodistill run``: the DVC pipeline with concurrency, DVC staying the record of what ran.

``dvc repro`` runs one stage at a time, and several ``dvc repro`` processes in one workspace fight over
DVC's repository lock ("Unable to acquire lock"; treeverse/dvc#10465, #9805): repro holds it except
while a stage's command runs, and ``dvc commit`` holds it throughout.  So one process orchestrates:

1. it takes DVC's repository lock for the whole run (other DVC commands wait or fail, as during a
   ``dvc repro``) and reads the stage graph from DVC itself (``dvc.yaml`` with its ``matrix``
   expanded, so ``train_plain@42`` ... are separate jobs);
2. when all of a stage's upstream stages are done it asks DVC whether the stage changed, exactly as
   ``dvc repro`` does at that point (:meth:`dvc.stage.Stage.changed`); unchanged -> skipped; changed ->
   its outputs are removed and DVC's run cache is tried (``dvc repro``'s behaviour), else its ``cmd``
   is queued;
3. queued commands run as concurrent processes (:func:`pipeline.runner.run_jobs`: bounded pool,
   dependencies, GPU slots, a CPU-thread budget, timing stages alone);
4. each stage that exits 0 is recorded in this process, one at a time, with the calls ``dvc repro``
   makes after a command (save deps/outs/md5 + run cache, commit outputs to the cache, write its
   dvc.lock entry) -- so after the run ``dvc.lock`` is complete and ``dvc repro``/``dvc status`` find
   nothing to do, and after a failure every finished stage is recorded and a rerun resumes.

Machine-dependent knobs are options, not params: params.yaml describes the experiment, and DVC tracks
it key by key, so how many processes ran must never make a stage stale.
"""

from __future__ import annotations

import logging
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import click

from pipeline.errors import InputError
from stages._common import setup_logging

#: Stages whose command takes ``--shard i/n`` to fill a cache for 1/n of the work (stages/teacher.py):
#: with ``--teacher-shards N`` they run as N shard processes, then the stage's own command assembles.
SHARDED = {"teacher": "--shard {i}/{n}"}
#: GPU memory assumed per concurrent GPU job when ``--gpu-jobs`` is not given (TinyUNet training at
#: 384^2 batch 4 plus a CUDA context stays well under it; conservative on purpose).
GPU_JOB_MIB = 4096


def detect_gpus(env=None) -> dict[str, int]:
    """{device id: free MiB} of the GPUs this process may use: nvidia-smi's indices, narrowed to
    ``CUDA_VISIBLE_DEVICES`` when that is set; {} without nvidia-smi or GPUs.  Does not import torch or
    create a CUDA context."""
    env = os.environ if env is None else env
    exe = shutil.which("nvidia-smi", path=env.get("PATH"))
    if exe is None or env.get("CUDA_VISIBLE_DEVICES", None) == "":
        return {}
    try:
        out = subprocess.run([exe, "--query-gpu=index,memory.free", "--format=csv,noheader,nounits"],
                             capture_output=True, text=True, timeout=30, check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return {}
    free = {}
    for line in out.splitlines():
        parts = [p.strip() for p in line.split(",")]
        if len(parts) == 2 and parts[0].isdigit():
            free[parts[0]] = int(float(parts[1])) if parts[1].replace(".", "", 1).isdigit() else 0
    visible = env.get("CUDA_VISIBLE_DEVICES")
    if visible and free:
        # indices as nvidia-smi numbers them; a UUID / MIG id passes through (memory: the smallest GPU's)
        wanted = [v.strip() for v in visible.split(",") if v.strip()]
        free = {d: free.get(d, min(free.values())) for d in wanted if d in free or not d.isdigit()}
    return free


def default_gpu_jobs(free_mib: int, cores: int, n_gpus: int) -> int:
    """Concurrent jobs per GPU: as many as fit in its free memory at ``GPU_JOB_MIB`` each, at most one per
    two CPU cores of this machine's share (each GPU job still feeds its batches from the CPU), >= 1."""
    return max(1, min(free_mib // GPU_JOB_MIB, cores // (2 * max(1, n_gpus))))


def parse_gpus(text: str | None, detected: dict[str, int]) -> dict[str, int]:
    """``--gpus``: None -> the detected GPUs; "none" -> no GPU; "0,2" -> those indices."""
    if text is None:
        return detected
    if text.strip().lower() == "none":
        return {}
    ids = [t.strip() for t in text.split(",") if t.strip()]
    if not ids or not all(i.isdigit() for i in ids):
        raise InputError(f"--gpus {text!r}: expected 'none' or GPU indices like 0,1")
    return {i: detected.get(i, 0) for i in ids}


class DvcPipeline:
    """The DVC side of ``geodistill run``: jobs from the stage graph, staleness, recording.

    Every method runs in the orchestrating process while it holds the repository lock (see the
    module docstring); nothing here is called concurrently."""

    def __init__(self, root: Path, targets: tuple[str, ...] = (), echo=click.echo):
        from dvc.repo import Repo

        dvc_log = logging.getLogger("dvc")  # DVC configures it on import: warnings and errors only, once
        dvc_log.setLevel(logging.WARNING)
        dvc_log.propagate = False
        self.root = Path(root).resolve()
        self.repo = Repo(str(self.root))
        self.targets = targets
        self.echo = echo
        self.stages: dict = {}
        self.graph = None

    # -- graph ---------------------------------------------------------------------------------------
    def load(self) -> None:
        """The stage graph (call with the lock held): every stage, or ``targets`` and their upstream."""
        from dvc.exceptions import DvcException
        from dvc.repo.reproduce import collect_stages, get_active_graph, plan_repro

        try:
            graph = get_active_graph(self.repo.index.graph)
        except DvcException as e:  # e.g. a matrix key params.yaml lacks: DVC's message names it
            raise InputError(f"dvc.yaml: {str(e).splitlines()[0]}") from e
        if self.targets:
            try:
                selected = collect_stages(self.repo, self.targets)
            except Exception as e:  # dvc's own message names the target
                raise InputError(f"geodistill run {' '.join(self.targets)}: {str(e).splitlines()[0]}") from e
            keep = set(plan_repro(graph, selected))
            graph = graph.subgraph(keep)
        self.graph = graph
        self.stages = {s.addressing: s for s in graph}

    def jobs(self, path: str, teacher_shards: int = 1) -> list:
        """One :class:`pipeline.runner.Job` per stage (its ``cmd`` through the shell, as DVC runs it), in
        DVC's planning order, plus the shard jobs of :data:`SHARDED` stages when ``teacher_shards`` > 1."""
        from dvc.repo.reproduce import plan_repro

        from pipeline.catalog import STAGES
        from pipeline.runner import Job

        jobs = []
        for stage in plan_repro(self.graph):
            name = stage.addressing
            needs = frozenset(s.addressing for s in self.graph.successors(stage))
            cmds = stage.cmd if isinstance(stage.cmd, list) else [stage.cmd]
            # a stage that imports pipeline/device.py (its code deps are derived from its imports) may use a GPU
            gpu = any(d.def_path.endswith("pipeline/device.py") for d in stage.deps)  # absolute in a distill project
            spec = STAGES.get(name)
            env = {"DVC_ROOT": str(self.root), "DVC_STAGE": name}
            if name in SHARDED and teacher_shards > 1:
                shard_names = []
                for i in range(teacher_shards):
                    shard = f"{name}#shard{i}"
                    arg = SHARDED[name].format(i=i, n=teacher_shards)
                    jobs.append(Job(shard, ("/bin/sh", "-c", " && ".join(f"{c} {arg}" for c in cmds)), needs, gpu,
                                    False, stage.wdir, {**env, "PATH": path}))
                    shard_names.append(shard)
                needs = needs | frozenset(shard_names)
            jobs.append(Job(name, ("/bin/sh", "-c", " && ".join(cmds)), needs, gpu,
                            bool(spec and spec.exclusive), stage.wdir, {**env, "PATH": path}))
        return jobs

    # -- hooks for pipeline.runner.run_jobs ------------------------------------------------------------
    def _stage(self, job):
        return self.stages[job.name.split("#", 1)[0]]

    def changed(self, stage) -> bool:
        if stage.frozen:
            return False
        return stage.changed(upstream=list(self.graph.successors(stage)))

    def prepare(self, job) -> bool:
        """True: the job must run.  For a stage: DVC says it changed -> outs removed, run cache tried
        (restored -> recorded, nothing to run), deps saved -> True.  For a shard job: its stage changed."""
        from dvc.stage.cache import RunCacheNotFoundError

        stage = self._stage(job)
        if "#" in job.name:
            return self.changed(stage)
        if not self.changed(stage):
            return False
        stage.remove_outs(ignore_remove=False, force=False)
        try:
            self.repo.stage_cache.restore(stage)
        except RunCacheNotFoundError:
            stage.save_deps()
            return True
        self.record(job)
        self.echo(f"restored {job.name} from DVC's run cache")
        return False

    def record(self, job) -> None:
        """What ``dvc repro`` does after a stage's command exits 0 (dvc.stage.Stage.run + repro's dump)."""
        if "#" in job.name:
            return  # a shard fills a cache only; its stage records
        stage = self._stage(job)
        uncached = any(not o.use_cache for o in stage.outs if not (o.is_metric or o.is_plot))
        stage.save(run_cache=not uncached)
        stage.commit()
        stage.dump(update_pipeline=False)


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


@click.command(name="run")
@click.argument("targets", nargs=-1)
@click.option("--jobs", "-j", type=click.IntRange(min=1), default=None,
              help="processes at once [default: CPU cores with a GPU, cores/2 without]")
@click.option("--gpu-jobs", type=click.IntRange(min=1), default=None,
              help=f"concurrent jobs per GPU [default: free memory / {GPU_JOB_MIB} MiB, at most cores/2 per GPU]")
@click.option("--gpus", default=None, metavar="LIST|none",
              help="GPU indices to use, e.g. 0,1; 'none' runs everything on the CPU [default: all visible]")
@click.option("--teacher-shards", type=click.IntRange(min=1), default=1, show_default=True,
              help="run a stale teacher as N concurrent `--shard i/N` processes, then assemble")
@click.option("--keep-going", is_flag=True, help="after a failure, go on with stages that do not depend on it")
@click.option("--dry-run", is_flag=True, help="print the plan (stages by wave, which are stale now) and exit")
def main(targets, jobs, gpu_jobs, gpus, teacher_shards, keep_going, dry_run):
    """Run the DVC pipeline (or TARGETS and their upstream stages) with stages as concurrent processes.

    Stale stages run as soon as their upstream stages are done: the train_<method>@<seed> runs side by
    side (several per GPU), analyze_teacher beside training, export beside evaluate; the benchmark
    runs alone (it measures time).  Each process gets a share of the CPU cores (OMP_NUM_THREADS) and,
    on a GPU machine, one GPU (CUDA_VISIBLE_DEVICES).  DVC decides what is stale and records every
    finished stage (dvc.lock, cache, run cache), so afterwards `dvc status` is clean and `dvc repro`
    does nothing.  Logs: artifacts/logs/run/<stage>.log and timeline.json.

    On a failure: the stage's error line is printed, its dependents do not run, finished stages stay
    recorded (a rerun resumes), exit code 1.  On a SLURM cluster: fill the teacher cache with the
    array job of stages/teacher.py (--shard), then `geodistill run` assembles the teacher from it.
    """
    from dvc.exceptions import DvcException

    setup_logging()
    # SIGTERM (scancel, kill) as Ctrl-C: the running stages are stopped, not orphaned
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    try:
        report = run_pipeline(Path.cwd(), tuple(targets), jobs, gpu_jobs, gpus, teacher_shards, keep_going, dry_run)
    except (InputError, DvcException) as e:  # e.g. DVC's lock held by another dvc process
        click.echo(f"geodistill run: error: {str(e).splitlines()[0]}", err=True)
        sys.exit(2)
    if report is None:
        return
    counts = {s: sum(r.status == s for r in report.records.values()) for s in ("ran", "up_to_date", "failed", "not_run")}
    click.echo(f"geodistill run: {counts['ran']} ran, {counts['up_to_date']} up to date, {counts['failed']} failed, "
               f"{counts['not_run']} not run; {report.wall_s:.1f} s wall")
    if not report.ok:
        first = report.failed()[0]
        not_run = [n for n, r in report.records.items() if r.status == "not_run"]
        click.echo(f"geodistill run: error: stage {first} failed: {report.records[first].error}"
                   + (f"; not run: {', '.join(not_run)}" if not_run else ""), err=True)
        sys.exit(1)


def run_pipeline(root: Path, targets: tuple[str, ...] = (), jobs: int | None = None, gpu_jobs: int | None = None,
                 gpus: str | None = None, teacher_shards: int = 1, keep_going: bool = False, dry_run: bool = False):
    """``geodistill run`` without the CLI: returns the :class:`pipeline.runner.RunReport` (None for a dry run)."""
    from dvc.repo import lock_repo

    from pipeline import catalog
    from pipeline.runner import Resources, read_costs, run_jobs, waves, write_timeline

    if not (root / "dvc.yaml").is_file():
        raise InputError(f"{root / 'dvc.yaml'}: not found (run geodistill run in the project folder)")
    cores = _cores()
    detected = detect_gpus()
    gpu_ids = parse_gpus(gpus, detected)
    slots = {d: gpu_jobs or default_gpu_jobs(detected.get(d, 0), cores, len(gpu_ids)) for d in gpu_ids}
    # without a GPU every job is a CPU job: at most one per two cores, so each gets >= 2 threads
    res = Resources(jobs=jobs or (cores if slots else max(1, cores // 2)), cores=cores, gpu_slots=slots)
    log_dir = catalog.path("run_logs", root / catalog.ARTIFACTS_DIR)
    # stage commands say `python`: the interpreter running this command, whatever PATH says
    path = os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")])
    pipe = DvcPipeline(root, targets)
    with lock_repo(pipe.repo):  # held throughout, as no other DVC process may record meanwhile
        pipe.load()
        job_list = pipe.jobs(path, teacher_shards)
        gpu_text = ", ".join(f"GPU {d} x{n}" for d, n in slots.items()) or "no GPU"
        click.echo(f"geodistill run: {len(pipe.stages)} stages; at most {res.jobs} at once, {cores} CPU cores, "
                   f"{gpu_text}")
        if dry_run:
            for k, wave in enumerate(waves(job_list)):
                marks = [n if "#" in n or pipe.changed(pipe.stages[n]) else f"{n} (up to date now)" for n in wave]
                click.echo(f"wave {k}: " + ", ".join(marks))
            return None
        costs = read_costs(log_dir / "timeline.json")
        report = run_jobs(job_list, res, log_dir, prepare=pipe.prepare, record=pipe.record, costs=costs,
                          keep_going=keep_going, echo=click.echo)
    write_timeline(report, log_dir / "timeline.json", costs)
    return report


if __name__ == "__main__":
    main()
