"""A group of seeds of one method: the ``train`` stage's logic.

Per-seed options, the fan-out over processes, one seed's run and what it writes.  Each seed runs exactly as a process of its own would make it; per-epoch resume state under
``<resume_dir>/<fingerprint>``.  Torch is imported only once a seed runs, so a stage's ``--help`` starts none.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any, Mapping

import click

from pipeline import catalog
from pipeline.artifacts.atomic import write_json
from pipeline.artifacts.lineage import run_as
from pipeline.artifacts.provenance import training_runtime
from pipeline.evaluation.inference import save_checkpoint
from pipeline.methods import SELECTION_TAU_KEY, fingerprint_params
from pipeline.params import get_path
from pipeline.report.dvc_results import write_live_log
from pipeline.runtime.device import resolve_device, stage_cores
from pipeline.runtime.errors import InputError
from pipeline.training.checkpointing import FileCheckpointer
from pipeline.training.inputs import MethodInputs, load_init, open_method

__all__ = ["PER_SEED_FLAGS", "SCHEDULING_FLAGS", "train_seed", "seeds_argv", "auto_jobs", "run_in_processes",
           "seed_options", "run_seeds"]

#: the options given once per ``--seed``, in the seeds' order
PER_SEED_FLAGS = ("--seed", "--init", "--out", "--live-dir")
#: options that change how the seeds are scheduled, never what they write: left out of the recorded command line
SCHEDULING_FLAGS = ("--jobs",)


def train_seed(m: MethodInputs, params: Mapping[str, Any], device: str, seed: int, artifacts: str | Path,
               init: str | None, out: str | Path, resume_dir: str | Path, live_dir: str | Path | None = None) -> Path:
    """Run one (method, seed) on the opened inputs; write its checkpoint, DVCLive log and timings.

    Parameters
    ----------
    m : MethodInputs
        The method's opened inputs (:func:`pipeline.training.inputs.open_method`).
    params : Mapping
        The validated params (fingerprinted into the checkpoint).
    device : str
        ``--device`` (resolved here).
    seed : int
        The run's seed.
    artifacts : str or Path
        The artifacts folder (the timings file and the default DVCLive folder go there).
    init : str or None
        The Stage-I checkpoint of a warm-started method.
    out : str or Path
        The checkpoint folder to write.
    resume_dir : str or Path
        Where per-epoch resume states are kept, one folder per run fingerprint (budget left out).
    live_dir : str or Path, optional
        The DVCLive folder; None: the catalogue's ``train_live`` path.

    Returns
    -------
    Path
        ``out``.

    Raises
    ------
    InputError
        A warm-started method without ``init``.
    pipeline.runtime.errors.TrainingDiverged
        A non-finite loss or weights.
    """
    from pipeline.training import loop as training  # torch: imported once the options are checked

    spec, method, inputs = m.spec, m.spec.name, list(m.inputs)
    init_state = None
    if spec.init == "stage1":
        if not init:
            raise InputError(f"--init missing: method {method!r} warm-starts from a Stage-I checkpoint")
        init_state, init_art = load_init(init)
        inputs.append(init_art)

    def meta_of(fp: dict):
        return m.context.meta("checkpoint", inputs, params={"params": fp, "method": method, "seed": seed,
                                                            "stage": m.stage}, **m.data.stats)

    fp = fingerprint_params(spec, params)
    meta = meta_of(fp)
    # the resume folder's key leaves the budget out: a larger train.step_budget continues the same run
    resume = meta_of({k: v for k, v in fp.items() if k not in training.BUDGET_PARAMS}).fingerprint
    dev = resolve_device(device)
    result = training.train(spec, m.cfg, m.data, m.val, seed, init_state=init_state, device=dev,
                            checkpointer=FileCheckpointer(Path(resume_dir) / resume),
                            selection_tau=get_path(params, SELECTION_TAU_KEY))
    meta.extra.update(result.info)
    meta.extra["runtime"] = training_runtime(dev)  # provenance, not fingerprinted
    save_checkpoint(out, result.model, meta, result.log, method=method, seed=seed, stage=m.stage,
                    selected_epoch=result.selected_epoch, selection=result.info["selection"],
                    resolution=int(m.data.images.shape[1]), mode=result.info["mode"], fingerprint=meta.fingerprint)
    write_live_log(result.log, live_dir or catalog.path("train_live", artifacts, method=method, seed=seed),
                   result.selected_epoch)
    # wall clock beside, not inside, the checkpoint: the checkpoint is byte-identical on a rerun
    write_json(catalog.path("train_timings", artifacts, method=method, seed=seed),
               {"method": method, "seed": seed, "device": str(dev), "epochs": result.timings})
    stopped = f", {result.info['steps_run']} steps, stopped at {result.info['stopped']}" \
        if result.info.get("stopped") else ""
    click.echo(f"train: {method} seed {seed}: selected epoch {result.selected_epoch} "
               f"({result.info['selection']}{stopped}); wrote {out}", err=True)
    return Path(out)


def seeds_argv(argv: list[str], keep) -> list[str]:
    """Cut a group's command line down to the seeds at positions ``keep``, without :data:`SCHEDULING_FLAGS`.

    For one seed, its run id (derived from the command line) is then the one a process of its own records.

    Parameters
    ----------
    argv : list of str
        The group's command line, program name aside.
    keep : Container of int
        The positions (0-based, in ``--seed`` order) of the seeds kept.

    Returns
    -------
    list of str
        The command line of those seeds alone.
    """
    out, seen, i = [], dict.fromkeys(PER_SEED_FLAGS, 0), 0
    while i < len(argv):
        flag, eq, _ = argv[i].partition("=")
        width = 1 if eq else 2
        if flag in SCHEDULING_FLAGS:
            i += width
            continue
        if flag not in PER_SEED_FLAGS:
            out.append(argv[i])
            i += 1
            continue
        if seen[flag] in keep:
            out += argv[i:i + width]
        seen[flag] += 1
        i += width
    return out


def auto_jobs(cfg: Mapping[str, Any], device: str, n_seeds: int) -> int:
    """Choose the processes for a group of ``n_seeds`` runs (``--jobs 0``).

    On a CPU, the stage's cores (under ``geodistill run``, those Ray gave it:
    :func:`pipeline.runtime.device.stage_cores`) over ``train.num_threads`` (a run's bytes depend on its thread
    count, never on what runs beside it); 1 on a GPU or with ``num_threads`` 0 (torch's default: every core).

    Parameters
    ----------
    cfg : Mapping
        The validated ``train:`` section.
    device : str
        The resolved device.
    n_seeds : int
        The group's seeds.

    Returns
    -------
    int
        The processes, 1 to ``n_seeds``.
    """
    threads = cfg["num_threads"]
    if device != "cpu" or threads <= 0:
        return 1
    return max(1, min(n_seeds, stage_cores() // threads))


def run_in_processes(module: str, argv: list[str], n_seeds: int, jobs: int) -> int:
    """Run ``python -m module`` for the seeds ``k, k + jobs, ...`` in each of ``jobs`` processes, side by side.

    Parameters
    ----------
    module : str
        The stage's module (``stages.train``).
    argv : list of str
        The group's command line, program name aside.
    n_seeds : int
        The group's seeds.
    jobs : int
        The processes.

    Returns
    -------
    int
        The worst exit code (each process prints its own lines).
    """
    procs = [subprocess.Popen([sys.executable, "-m", module, *seeds_argv(argv, set(range(j, n_seeds, jobs))),
                               "--jobs", "1"]) for j in range(jobs)]
    return max(p.wait() for p in procs)


def _per_seed(seeds: tuple[int, ...], flag: str, values: tuple[str, ...], required: bool) -> list[str | None]:
    """List a per-seed option's values, one per ``--seed`` (None each when absent and not ``required``)."""
    if not values and not required:
        return [None] * len(seeds)
    if len(values) != len(seeds):
        raise InputError(f"{flag}: {len(values)} given for {len(seeds)} --seed; give one per --seed, in their order")
    return list(values)


def seed_options(seeds: tuple[int, ...], inits: tuple[str, ...], outs: tuple[str, ...],
                 live_dirs: tuple[str, ...] = ()) -> tuple[list, list, list]:
    """Check the per-seed options and pair them with their ``--seed``.

    Parameters
    ----------
    seeds : tuple of int
        ``--seed``, in order.
    inits, outs, live_dirs : tuple of str
        ``--init`` (optional), ``--out`` (one per seed) and ``--live-dir`` (optional).

    Returns
    -------
    tuple of list
        (``--init``, ``--out``, ``--live-dir``) of each seed; None where an optional one is absent.

    Raises
    ------
    InputError
        No seed, a seed named twice, or an option given another number of times than ``--seed``.
    """
    if not seeds:
        raise InputError("--seed missing: give one or more")
    if len(set(seeds)) != len(seeds):
        raise InputError(f"--seed: {', '.join(str(s) for s in seeds)} names a seed twice")
    return (_per_seed(seeds, "--init", inits, required=False), _per_seed(seeds, "--out", outs, required=True),
            _per_seed(seeds, "--live-dir", live_dirs, required=False))


def run_seeds(params: Mapping[str, Any], device: str, stage: int, method: str, seeds: tuple[int, ...],
              artifacts: str | Path, inits: tuple[str, ...], outs: tuple[str, ...], resume_dir: str | Path,
              live_dirs: tuple[str, ...], context: Any, argv: list[str]) -> list[Path]:
    """Run several seeds of one method in this process, one after another, the artifacts opened once.

    Parameters
    ----------
    params : Mapping
        The validated params.
    device : str
        ``--device``.
    stage : int
        ``--stage``.
    method : str
        ``--method``.
    seeds : tuple of int
        ``--seed``, in order.
    artifacts : str or Path
        The artifacts folder.
    inits, outs, live_dirs : tuple of str
        The per-seed options (:func:`seed_options`).
    resume_dir : str or Path
        The per-epoch resume states' folder.
    context : Any
        The stage's context (stamps the checkpoints).
    argv : list of str
        The group's command line, program name aside: each seed runs under its own (:func:`seeds_argv`).

    Returns
    -------
    list of Path
        The checkpoints written.

    Raises
    ------
    InputError
        Bad options or inputs (:func:`seed_options`, :func:`pipeline.training.inputs.open_method`).
    pipeline.runtime.errors.TrainingDiverged
        A run diverged.
    """
    init_of, out_of, live_of = seed_options(seeds, inits, outs, live_dirs)
    m = open_method(params, stage, method, artifacts, context)
    done = []
    for k, (s, i, o, lv) in enumerate(zip(seeds, init_of, out_of, live_of)):
        with run_as(seeds_argv(argv, {k})):  # the run id its own process records (not fingerprinted)
            done.append(train_seed(m, params, device, s, artifacts, i, o, resume_dir, lv))
    return done
