"""The report's "Environment" section and ``environment.json``.

They record the machine that built the report and where each training run ran (provenance only; nothing here
is fingerprinted).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Sequence

from pipeline.artifacts.store import open_artifact
from pipeline.runtime.errors import ArtifactError
from pipeline.evaluation.inference import iter_runs
from pipeline.methods import method_label
from pipeline.report.document import Section, Table, Text

__all__ = ["opened_runs", "training_runs", "environment_record", "environment_section", "ending_table"]

#: ``extra.autocast`` of a checkpoint -> the precision as the report names it
PRECISION_TEXT = {"bfloat16": "bf16 autocast", "float16": "fp16 autocast", "fp32": "fp32"}
NOT_RECORDED = "not recorded"


def opened_runs(checkpoints: str | Path) -> list:
    """Open the checkpoint of every active run that opens.

    Parameters
    ----------
    checkpoints : str or Path
        The checkpoints folder (``artifacts/checkpoints``).

    Returns
    -------
    list of tuple
        ``(method, seed, opened checkpoint)`` per run; a run whose checkpoint does not open is left out, and
        there are none without a readable checkpoints folder.
    """
    try:
        runs = list(iter_runs(checkpoints))
    except ArtifactError:
        return []
    out = []
    for method, seed, path in runs:
        try:
            out.append((method, seed, open_artifact(path)))
        except ArtifactError:
            continue
    return out


def training_runs(checkpoints: str | Path) -> list[dict[str, Any]]:
    """Record where and how each active training run ran, from its checkpoint's meta.json.

    Parameters
    ----------
    checkpoints : str or Path
        The checkpoints folder.

    Returns
    -------
    list of dict
        One record per run (:func:`opened_runs`): ``method``, ``seed``, ``recipe`` (``train.recipe``),
        ``precision`` (the autocast it used), ``runtime`` (``extra.runtime``), ``torch`` (its version), and how it
        ended: ``steps`` (optimizer steps run), ``epochs``, ``stopped`` (the rule that ended it) and ``selection``
        (the weights it returned); each is None where the run did not record it.
    """
    # unvalidated: the params each run recorded (a run before train.recipe has none)
    return [{"method": method, "seed": int(seed), "recipe": (c.meta.params.get("params") or {}).get("train.recipe"),
             "precision": (c.meta.extra or {}).get("autocast"), "runtime": (c.meta.extra or {}).get("runtime"),
             "torch": (c.meta.library_versions or {}).get("torch"),
             **{k: (c.meta.extra or {}).get(key) for k, key in (("steps", "steps_run"), ("epochs", "epochs"),
                                                                ("stopped", "stopped"), ("selection", "selection"))}}
            for method, seed, c in opened_runs(checkpoints)]


def environment_record(env: Mapping[str, Any] | None, runs: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Assemble what ``environment.json`` holds.

    Parameters
    ----------
    env : Mapping or None
        The report machine's record (:func:`pipeline.artifacts.provenance.collect`); None: not recorded.
    runs : sequence of Mapping
        The training runs' records (:func:`training_runs`).

    Returns
    -------
    dict
        ``{"report": env, "training_runs": runs}``, copied.
    """
    return {"report": dict(env) if env is not None else None, "training_runs": [dict(r) for r in runs]}


def _run_config(run: Mapping[str, Any]) -> tuple[str, ...]:
    """Give the columns of the training table for one run (runs with equal columns share a row)."""
    rt = run.get("runtime") or {}
    device = rt.get("device", NOT_RECORDED) + (f" ({rt['gpu']})" if rt.get("gpu") else "")
    precision = PRECISION_TEXT.get(run.get("precision"), run.get("precision") or NOT_RECORDED)
    threads = str(rt["num_threads"]) if "num_threads" in rt else NOT_RECORDED
    return (device, precision, threads, rt.get("cpu_model") or NOT_RECORDED, rt.get("cpu_capability") or NOT_RECORDED,
            " ".join(rt.get("cpu_flags") or []) or NOT_RECORDED, str(run.get("torch") or NOT_RECORDED))


def training_table(runs: Sequence[Mapping[str, Any]]) -> Table:
    """Tabulate the training runs grouped by identical (device, precision, threads, CPU, kernels, flags, torch)."""
    groups: dict[tuple[str, ...], list[str]] = {}
    for r in runs:
        groups.setdefault(_run_config(r), []).append(f"{r['method']} s{r['seed']}")
    rows = [[f"all {len(runs)} runs" if len(groups) == 1 else ", ".join(names), *config]
            for config, names in groups.items()]
    return Table("tab:environment-training", "Where each training run ran (from its checkpoint's meta.json)",
                 ["Runs", "Device", "Precision", "torch threads", "CPU", "torch CPU kernels", "CPU flags", "torch"],
                 rows, notes=["Precision = the autocast actually used (train.precision resolved on that device); "
                              "threads = torch.get_num_threads() during training."])


def ending_table(runs: Sequence[Mapping[str, Any]]) -> Table:
    """Tabulate how each training run ended: its steps and epochs, the rule that stopped it, the weights it returned.

    Parameters
    ----------
    runs : sequence of Mapping
        The training runs' records (:func:`training_runs`); runs of one method that ended alike share a row, the
        method named by its label (the ceiling's says it is not annotation-free).

    Returns
    -------
    Table
        Method, seeds (in numeric order), steps, epochs, what stopped the run and the returned weights.  A run with
        steps but no stop recorded trained its fixed epochs (Stage II, or a recipe without a stopping rule); one
        without steps did not record them (an older run).
    """
    groups: dict[tuple, list[str]] = {}
    for r in runs:
        steps = r.get("steps")
        stopped = r.get("stopped") or ("its fixed epochs (no stopping rule)" if steps is not None else NOT_RECORDED)
        key = (method_label(r["method"]), NOT_RECORDED if steps is None else f"{steps:,}",
               NOT_RECORDED if r.get("epochs") is None else str(r["epochs"]), stopped,
               r.get("selection") or NOT_RECORDED)
        groups.setdefault(key, []).append(int(r["seed"]))
    rows = [[key[0], ", ".join(map(str, sorted(seeds))), *key[1:]] for key, seeds in groups.items()]
    return Table("tab:training-ending", "How each training run ended (from its checkpoint's meta.json)",
                 ["Method", "Seeds", "Optimizer steps", "Epochs", "Stopped by", "Returned weights"], rows,
                 notes=["A run stopped by its epochs cap has not shown a plateau: its curve may still rise there "
                        "(docs/student.md)."])


def software_table(env: Mapping[str, Any]) -> Table:
    """Tabulate the Python and library versions of the installation that built the report."""
    rows = [["Python", env["python"]]] + [[name, version] for name, version in env["libraries"].items()]
    return Table("tab:environment-software", "Software of the installation that built this report",
                 ["Package", "Version"], rows)


def machine_table(env: Mapping[str, Any]) -> Table:
    """Tabulate the report machine: platform, CPU, torch build, its kernels and libraries, GPUs and threads."""
    t, c = env["torch"], env["cpu"]
    settings = t.get("settings", {})
    onednn = next((x for x in t.get("components", []) if "MKL-DNN" in x or "oneDNN" in x), "--")
    mkl = next((x for x in t.get("components", []) if "Math Kernel Library" in x), "--")
    rows = [["Platform", env["platform"]],
            ["CPU", f"{c['model']} ({c['logical_cpus']} logical CPUs)"],
            ["CPU flags (numeric kernels)", " ".join(c["flags"]) or "--"],
            ["numpy SIMD dispatch", " ".join(env.get("numpy_simd") or []) or "not recorded"],
            ["torch build", f"{t['version']} ({'CUDA ' + t['cuda'] if t.get('cuda') else 'CPU-only'}; git "
                            f"{str(t.get('git') or '--')[:12]})"],
            ["torch CPU kernels", str(t.get("cpu_capability"))],
            ["oneDNN", onednn if t.get("mkldnn") else f"not available ({onednn})"],
            ["MKL", mkl if t.get("mkl") else "not available"],
            ["BLAS / LAPACK", f"{settings.get('BLAS_INFO', '--')} / {settings.get('LAPACK_INFO', '--')}"],
            ["GPUs", ", ".join(t.get("gpus") or []) or "none"],
            ["torch threads (report process)", f"{env['threads']['torch']} intra-op, "
                                               f"{env['threads']['torch_interop']} inter-op"],
            ["Thread / numerics variables set", ", ".join(f"{k}={v}" for k, v in env["env"].items()) or "none"]]
    return Table("tab:environment-machine", "Machine and torch build that built this report", ["Item", "Value"], rows)


def lock_text(lock: Mapping[str, Any]) -> str:
    """Write one sentence on the installed packages against the lock file."""
    if not lock.get("found"):
        return (f"No lock file (`{lock.get('file')}`) was found beside the code, so the installed versions "
                f"were not compared with a lock.")
    head = (f"Lock `{lock['file']}` (sha256 `{lock['sha256'][:12]}`): {lock['matching']} of {lock['pinned']} pinned "
            f"packages installed at the pinned version, {lock['not_installed']} not installed (e.g. the CUDA wheels "
            f"of the public torch build on a CPU machine)")
    if not lock["differ"]:
        return head + ", none at another version."
    diff = "; ".join(f"`{d['package']}` {d['installed']} (lock {d['lock']})" for d in lock["differ"])
    return head + f". **{len(lock['differ'])} installed at another version than the lock**: {diff}."


def environment_section(env: Mapping[str, Any] | None, runs: Sequence[Mapping[str, Any]]) -> Section:
    """Build the "Environment" section: the report machine's software, torch build and CPU, and each run's record.

    Parameters
    ----------
    env : Mapping or None
        The report machine's record (:func:`pipeline.artifacts.provenance.collect`); None: a sentence says it
        was not recorded.
    runs : sequence of Mapping
        The training runs' records (:func:`training_runs`).

    Returns
    -------
    Section
        The section's text and tables.
    """
    blocks = [Text("Where these numbers were computed. Provenance only: none of it enters an artifact's fingerprint. "
                   "The same record, machine-readable: `environment.json` beside this page."),
              training_table(runs) if runs else
              Text("No training run was found, so no run's precision or threads are recorded.")]
    blocks += ([Text(lock_text(env["lock"])), software_table(env), machine_table(env)] if env is not None
               else [Text("The environment of the report process was not recorded.")])
    return Section("Environment", blocks)
