"""Stage ``train`` (``train_<method>@<seed>``, or ``train_<method>`` for a group of seeds): one or several
seeds of one method, one after another in a process (``--jobs`` processes side by side), each run exactly as
a process of its own would make it; per-epoch resume state under ``--resume-dir``/<fingerprint>.  Exit code 1
when training diverged."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path
from typing import Any

import click

from pipeline import catalog
from pipeline.artifacts.atomic import write_json
from pipeline.artifacts.lineage import run_as
from pipeline.artifacts.store import open_artifact
from pipeline.catalog import ARTIFACTS_DIR, META_FILE
from pipeline.training.checkpointing import FileCheckpointer
from pipeline.runtime.device import resolve_device, stage_cores
from pipeline.report.dvc_results import write_live_log
from pipeline.artifacts.provenance import training_runtime
from pipeline.runtime.errors import ArtifactError, InputError, TrainingDiverged
from pipeline.evaluation.inference import load_student, save_checkpoint
from pipeline.methods import SELECTION_TAU_KEY, SUPERVISED_CEILING, fingerprint_params, get_method
from pipeline.params import get_path, section
from pipeline.training.inputs import load_inputs
from stages._common import stage_command, stage_context


def load_init(path: str | Path):
    """Stage-I checkpoint for a warm start: (mask-path state dict, its artifact for the lineage)."""
    p = Path(path)
    if not (p / META_FILE).exists():
        raise ArtifactError(f"--init {p}: not a checkpoint directory (run train_plain first)")
    art = open_artifact(p, "checkpoint")
    model, _ = load_student(p)
    return model.mask_path_state_dict(), art


@dataclasses.dataclass(frozen=True)
class MethodInputs:
    """What every seed of one method reads, opened once: method, train params, arrays, lineage, context."""

    spec: Any
    stage: int
    cfg: dict
    data: Any
    val: Any
    inputs: tuple
    context: Any


def open_method(params: dict, stage: int, method: str, artifacts: str) -> MethodInputs:
    """Check the method against ``--stage`` and the params, then open what its runs read."""
    cfg = section(params, "train")
    spec = get_method(method)
    if spec.stage != stage:
        raise InputError(f"--stage {stage}: method {method!r} belongs to --stage {spec.stage}")
    if not spec.annotation_free and not params["protocol"][SUPERVISED_CEILING]:
        raise InputError(f"--method {method}: trains on reference masks (not annotation-free); "
                         f"needs params protocol.{SUPERVISED_CEILING}: true")
    data, val, inputs = load_inputs(artifacts, spec, cfg, review=section(params, "review"))
    return MethodInputs(spec, stage, cfg, data, val, tuple(inputs), stage_context("train", __file__, params))


def train_seed(m: MethodInputs, params: dict, device: str, seed: int, artifacts: str, init: str | None, out: str,
               resume_dir: str, live_dir: str | None = None) -> Path:
    """One (method, seed) run on the opened inputs: its checkpoint, DVCLive log and timings."""
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


PER_SEED_FLAGS = ("--seed", "--init", "--out", "--live-dir")
#: options that change how the seeds are scheduled, never what they write: left out of the recorded command line
SCHEDULING_FLAGS = ("--jobs",)


def seeds_argv(argv: list[str], keep) -> list[str]:
    """The command line of the seeds at positions ``keep`` alone, without :data:`SCHEDULING_FLAGS`: for one
    seed, its run id (derived from the command line) is then the one a process of its own records."""
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


def seed_argv(argv: list[str], k: int) -> list[str]:
    """The ``k``-th seed's own command line (:func:`seeds_argv`)."""
    return seeds_argv(argv, {k})


def auto_jobs(cfg: dict, device: str, n_seeds: int) -> int:
    """Processes for a group of ``n_seeds`` runs: on a CPU, the stage's cores (under ``geodistill run``, those
    Ray gave it: :func:`pipeline.runtime.device.stage_cores`) over ``train.num_threads`` (a run's bytes depend on
    its thread count, never on what runs beside it); 1 on a GPU or with ``num_threads`` 0 (torch's default:
    every core)."""
    threads = cfg["num_threads"]
    if device != "cpu" or threads <= 0:
        return 1
    return max(1, min(n_seeds, stage_cores() // threads))


def run_in_processes(argv: list[str], n_seeds: int, jobs: int) -> int:
    """This stage's command for the seeds ``k, k + jobs, ...`` in each of ``jobs`` processes, side by side: the
    worst exit code (each prints its own lines)."""
    procs = [subprocess.Popen([sys.executable, "-m", "stages.train", *seeds_argv(argv, set(range(j, n_seeds, jobs))),
                               "--jobs", "1"]) for j in range(jobs)]
    return max(p.wait() for p in procs)


def per_seed(seeds: tuple[int, ...], flag: str, values: tuple[str, ...], required: bool) -> list[str | None]:
    """The values of a per-seed option, one per ``--seed`` (None each when absent and not ``required``)."""
    if not values and not required:
        return [None] * len(seeds)
    if len(values) != len(seeds):
        raise InputError(f"{flag}: {len(values)} given for {len(seeds)} --seed; give one per --seed, in their order")
    return list(values)


def seed_options(seeds: tuple[int, ...], inits: tuple[str, ...], outs: tuple[str, ...],
                 live_dirs: tuple[str, ...] = ()) -> tuple[list, list, list]:
    """(``--init``, ``--out``, ``--live-dir``) of each ``--seed``, checked: InputError naming the option."""
    if not seeds:
        raise InputError("--seed missing: give one or more")
    if len(set(seeds)) != len(seeds):
        raise InputError(f"--seed: {', '.join(str(s) for s in seeds)} names a seed twice")
    return (per_seed(seeds, "--init", inits, required=False), per_seed(seeds, "--out", outs, required=True),
            per_seed(seeds, "--live-dir", live_dirs, required=False))


def run_seeds(params: dict, device: str, stage: int, method: str, seeds: tuple[int, ...], artifacts: str,
              inits: tuple[str, ...], outs: tuple[str, ...], resume_dir: str, live_dirs: tuple[str, ...] = ()
              ) -> list[Path]:
    """Several seeds of one method in this process, the artifacts opened once."""
    init_of, out_of, live_of = seed_options(seeds, inits, outs, live_dirs)
    m = open_method(params, stage, method, artifacts)
    done = []
    for k, (s, i, o, lv) in enumerate(zip(seeds, init_of, out_of, live_of)):
        with run_as(seed_argv(sys.argv[1:], k)):  # the run id its own process records (not fingerprinted)
            done.append(train_seed(m, params, device, s, artifacts, i, o, resume_dir, lv))
    return done


@stage_command("train")
@click.option("--stage", type=click.IntRange(1, 2), required=True, help="1 (Stage-I methods) or 2")
@click.option("--method", required=True, help="plain, geodistill, ... (pipeline.methods.METHODS)")
@click.option("--seed", "seeds", type=int, multiple=True, required=True,
              help="a seed to train (repeatable: the seeds run one after another in this process)")
@click.option("--artifacts", default=ARTIFACTS_DIR, show_default=True, type=click.Path(file_okay=False))
@click.option("--init", "inits", multiple=True,
              help="Stage-I checkpoint dir, one per --seed (warm-started methods only; others ignore it)")
@click.option("--out", "outs", multiple=True, required=True, help="checkpoint directory to write, one per --seed")
@click.option("--resume-dir", default=".cache/train", show_default=True,
              help="per-epoch resume states (outside DVC outs)")
@click.option("--live-dir", "live_dirs", multiple=True,
              help="DVCLive log of the epoch rows, one per --seed (default: reports/dvclive/<method>/<seed> "
                   "beside the artifacts dir)")
@click.option("--jobs", type=click.IntRange(0), default=0, show_default=True,
              help="processes training the seeds side by side (the same bytes as one); 0 = the cores over "
                   "train.num_threads on a CPU, 1 on a GPU")
def main(params, device, stage, method, seeds, artifacts, inits, outs, resume_dir, live_dirs, jobs):
    """Train (method, seed) students on pseudo-targets; write checkpoint + training log per seed."""
    jobs = jobs or auto_jobs(section(params, "train"), str(resolve_device(device)), len(seeds))
    if jobs > 1 and len(seeds) > 1:
        # bad options or inputs are refused here, in one line, not once in every process
        seed_options(seeds, inits, outs, live_dirs)
        open_method(params, stage, method, artifacts)
        sys.exit(run_in_processes(sys.argv[1:], len(seeds), min(jobs, len(seeds))))
    try:
        run_seeds(params, device, stage, method, seeds, artifacts, inits, outs, resume_dir, live_dirs)
    except TrainingDiverged as e:
        click.echo(f"geodistill train: training diverged: {str(e).splitlines()[0]}", err=True)
        sys.exit(1)


if __name__ == "__main__":
    main()
