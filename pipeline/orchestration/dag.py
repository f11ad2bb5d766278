"""The DVC DAG, derived rather than typed.

dvc.yaml from the catalogue, the method table and the stages' imports (one ``train_<method>`` stage per method,
active runs only), and params.yaml for a profile.
"""

from __future__ import annotations

import contextlib
import re
from pathlib import Path
from typing import Any

import yaml

from pipeline.catalog import ARTIFACTS, EXTRA_PATHS, PLOTS, PLOT_TEMPLATE, STAGES, StageSpec, dvc_path
from pipeline.runtime.codeversion import code_deps
from pipeline.methods import METHODS, STAGE_ONE, input_artifacts, param_keys
from pipeline.params import Params, deep_merge, get_path, unresolved, validate
from pipeline.profiles import profile_params

__all__ = ["stage_modules", "live_plots", "render_dvc_yaml", "project_dvc_yaml", "is_generated_params",
           "render_params_yaml"]


def _fill(template: str) -> str:
    """Replace ``{artifact}`` placeholders by catalogue paths; ``${...}`` stays a DVC template."""
    values = {n: dvc_path(n, method="${item.method}", seed="${item.seed}", profile="${profile}") for n in ARTIFACTS}
    values.update(EXTRA_PATHS)
    return re.sub(r"(?<!\$)\{(\w+)\}", lambda m: values[m.group(1)], template)


def _paths(names) -> list[str]:
    return [_fill("{" + n + "}") for n in names]


def _stage_entry(spec, matrix: dict | None = None, code_root: Path | None = None,
                 data_deps: dict[str, list[str]] | None = None) -> dict:
    """Write the dvc.yaml entry of a stage: code deps, data deps, input artifacts; params; outs and metrics.

    Outs and metrics outside artifacts/ are uncached, so git tracks them.  ``data_deps`` ({stage: paths}) replace
    the spec's.
    """
    entry: dict[str, Any] = {"matrix": matrix} if matrix else {}
    entry["cmd"] = f"python -m {spec.module} {_fill(spec.args)}"
    own_data = list(spec.data_deps) if data_deps is None else list(data_deps.get(spec.name, []))
    entry["deps"] = code_deps(spec.module, code_root=code_root) + own_data + _paths(spec.deps)
    entry["params"] = list(spec.params)
    entry["outs"] = [{p: {"cache": False}} if ARTIFACTS[o].path.startswith("../") else p
                     for o, p in zip(spec.outs, _paths(spec.outs))]
    if spec.metrics:
        entry["metrics"] = [{p: {"cache": False}} for p in _paths(spec.metrics)]
    return entry


#: the script of every ``train_<method>`` stage (the catalogue lists the other stages)
TRAIN_MODULE = "stages.train"


def upstream_stages() -> list[str]:
    """List the catalogue stages upstream of the training stages, in catalogue order."""
    producer = {a: s.name for s in STAGES.values() for a in s.outs}
    todo = [a for m in METHODS.values() for a in input_artifacts(m)]
    need: set[str] = set()
    while todo:
        stage = producer.get(todo.pop())
        if stage is not None and stage not in need:
            need.add(stage)
            todo.extend(STAGES[stage].deps)
    return [n for n in STAGES if n in need]


def stage_modules() -> dict[str, str]:
    """Map every stage of the DAG to its script module, in DAG order.

    Returns
    -------
    dict
        ``{stage: module}``; one ``train`` entry stands for all ``train_<method>`` stages.
    """
    up = upstream_stages()
    return {**{n: STAGES[n].module for n in up}, "train": TRAIN_MODULE,
            **{n: s.module for n, s in STAGES.items() if n not in up}}


def train_stage(method_name: str, code_root: Path | None = None, seeds: list[int] | None = None) -> dict:
    """Write the ``train_<method>`` stage entry.

    A matrix stage over ``protocol.runs.<method>`` (``seeds`` None), or one stage training ``seeds`` in one
    process, each seed with its own outs.
    """
    m = METHODS[method_name]
    items = ["${item.seed}"] if seeds is None else [str(s) for s in seeds]
    outs = [dvc_path("checkpoint", method=m.name, seed=s) for s in items]
    lives = [dvc_path("train_live", method=m.name, seed=s) for s in items]
    inits = [dvc_path("checkpoint", method=STAGE_ONE, seed=s) for s in items] if m.init == "stage1" else []
    args = (f"--stage {m.stage} --method {m.name}" + "".join(f" --seed {s}" for s in items)
            + " --artifacts {artifacts_dir}" + "".join(f" --init {i}" for i in inits)
            + "".join(f" --out {o}" for o in outs) + "".join(f" --live-dir {v}" for v in lives))
    spec = StageSpec(f"train_{m.name}", TRAIN_MODULE, args, input_artifacts(m), (), param_keys(m))
    matrix = {"seed": f"${{protocol.runs.{m.name}}}"} if seeds is None else None
    entry = _stage_entry(spec, matrix=matrix, code_root=code_root)
    entry["deps"] += inits
    entry["outs"] = [o for out, live in zip(outs, lives) for o in (out, {live: {"cache": False}})]
    return entry


SEEDS_PER_STAGE_KEY = "protocol.seeds_per_stage"


def train_stage_name(method_name: str, seeds: list[int] | None = None, all_seeds: list[int] | None = None) -> str:
    """Name a training stage: ``train_<method>``, or ``train_<method>-<seed>-<seed>...`` for a group of seeds.

    The short name serves the matrix stage and a group holding all the method's seeds.
    """
    if seeds is None or all_seeds is None or list(seeds) == list(all_seeds):
        return f"train_{method_name}"
    return f"train_{method_name}-" + "-".join(str(s) for s in seeds)


def seed_groups(params: dict | None) -> dict[str, list[list[int]]] | None:
    """Group each method's seeds by ``protocol.seeds_per_stage``, from params.yaml as read.

    ``{method: [[seed, ...], ...]}``; None when the key is 1 or absent (one templated stage per run).
    """
    protocol = (params or {}).get("protocol") or {}  # unvalidated: params.yaml as read
    per_stage = protocol.get(SEEDS_PER_STAGE_KEY.split(".")[-1]) or 1
    if per_stage <= 1:
        return None
    return {m: [list(seeds[i:i + per_stage]) for i in range(0, len(seeds), per_stage)]
            for m, seeds in (protocol.get("runs") or {}).items() if seeds}


def train_stages(code_root: Path | None = None, groups: dict[str, list[list[int]]] | None = None) -> dict[str, dict]:
    """List the training stages in method-table order: a matrix stage per method, or one per group of seeds."""
    if groups is None:
        return {f"train_{name}": train_stage(name, code_root) for name in METHODS}
    everyone = {m: [s for g in gs for s in g] for m, gs in groups.items()}
    return {train_stage_name(name, g, everyone[name]): train_stage(name, code_root, g)
            for name in METHODS for g in groups.get(name, [])}


#: catalogue stages in dvc.yaml only when a param is set (stage -> dotted key); unset, nothing changes
OPTIONAL_STAGES = {"corrections": "review.corrections"}
#: params keys in dvc.yaml only when set (key -> the stage reading it): a plug-in teacher's own settings
OPTIONAL_PARAMS = {"teacher.options": "teacher"}
#: what the training stages read from the ``corrections`` stage when it exists
REVIEW_TRAIN_DEPS = ("corrected",)
REVIEW_TRAIN_PARAMS = ("review.corrections", "review.mode", "review.human_targets")
#: the stages past training that read the corrected masks as validation masks
REVIEW_VALIDATION_STAGES = ("calibrate",)
REVIEW_VALIDATION_PARAMS = ("review.corrections", "review.mode")


def optional_stages_on(params: dict | None) -> tuple[str, ...]:
    """List the :data:`OPTIONAL_STAGES` whose key is set in ``params``, and the :data:`OPTIONAL_PARAMS` set there."""
    def get(key):
        with contextlib.suppress(KeyError, TypeError):
            return get_path(params or {}, key)

    return tuple(n for n, key in OPTIONAL_STAGES.items() if get(key)) + tuple(k for k in OPTIONAL_PARAMS if get(k))


def dvc_stages(code_root: Path | None = None, data_deps: dict[str, list[str]] | None = None,
               omit: tuple[str, ...] = (), optional: tuple[str, ...] = (),
               groups: dict[str, list[list[int]]] | None = None) -> dict[str, dict]:
    """Every stage of dvc.yaml in DAG order (arguments: :func:`render_dvc_yaml`)."""
    upstream = upstream_stages()
    out = {n: _stage_entry(STAGES[n], code_root=code_root, data_deps=data_deps) for n in upstream}
    if "corrections" in optional:  # before the training stages, which read its out
        out["corrections"] = _stage_entry(STAGES["corrections"], code_root=code_root)
    trains = train_stages(code_root, groups)
    if "corrections" in optional:
        for e in trains.values():
            e["deps"] += _paths(REVIEW_TRAIN_DEPS)
            e["params"] += list(REVIEW_TRAIN_PARAMS)
    out.update(trains)
    out.update({n: _stage_entry(s, code_root=code_root, data_deps=data_deps)
                for n, s in STAGES.items() if n not in upstream and n not in OPTIONAL_STAGES})
    if "corrections" in optional:
        for n in REVIEW_VALIDATION_STAGES:
            out[n]["deps"] += _paths(REVIEW_TRAIN_DEPS)
            out[n]["params"] += list(REVIEW_VALIDATION_PARAMS)
    for key, stage in OPTIONAL_PARAMS.items():
        if key in optional:
            out[stage]["params"].append(key)
    if omit:  # the omitted stages' outputs are no one's deps any more (their readers cope without them)
        gone = set(_paths(o for n in omit for o in STAGES[n].outs + STAGES[n].metrics))
        out = {n: {**e, "deps": [d for d in e["deps"] if d not in gone]} for n, e in out.items() if n not in omit}
    return out


DVC_HEADER = """\
# GeoDistill-Refine DAG -- GENERATED by `geodistill dag` from pipeline/catalog.py (artifacts, params
# keys), pipeline/methods.py (one train_<method> stage per method) and the stages' imports (code deps).
# Edit those, not this file; a test fails when this file is out of date.
#
#   prepare -> teacher -> consensus -> geometry -> train_<method>@<seed> -> calibrate -> evaluate -> report
#   analyze_teacher -> report;   export -> benchmark -> report
#
# Which runs exist is params.yaml's protocol.runs: train_<method> has one stage per listed seed (an
# empty list: no stage) -- or, with protocol.seeds_per_stage > 1, one stage per group of that many seeds
# (train_<method>, or train_<method>-<seed>-...), one process each, listing its seeds (rerun `geodistill
# dag` after editing protocol.runs then).  Params are tracked key by key: a change reruns exactly the
# stages reading it.
#
# Results, git-tracked (cache: false): reports/metrics/ (`dvc metrics show`, `dvc metrics diff <commit>`),
# reports/plots/ (`geodistill plots`: `dvc plots show` offline, one line per method), reports/dvclive/<method>/<seed>/.
"""


def dvc_plots(omit: tuple[str, ...] = ()) -> list[dict]:
    """dvc.yaml's top-level plots, without those of omitted stages."""
    return [{p.name: {"template": PLOT_TEMPLATE, "x": p.x, "y": {dvc_path(p.data): p.y}, "title": p.title,
                      "x_label": p.x_label, "y_label": p.y_label}}
            for p in PLOTS if ARTIFACTS[p.data].stage not in omit]


#: the DVCLive column a run always logs, plotted where no validation curve is
LIVE_PLOT_METRIC = "loss"


def live_plots(runs: dict[str, list[int]], metric: str = LIVE_PLOT_METRIC) -> list[dict]:
    """Plot the runs' DVCLive logs, one line per run: the plot of a project without validation masks.

    Parameters
    ----------
    runs : dict
        ``{method: [seed, ...]}``.
    metric : str
        The DVCLive column plotted.

    Returns
    -------
    list of dict
        One dvc.yaml top-level plot; empty when there is no run.
    """
    y = {f"{dvc_path('train_live', method=m, seed=s)}/plots/metrics/{metric}.tsv": metric
         for m, seeds in runs.items() for s in seeds}
    if not y:
        return []
    return [{f"training_{metric}": {"template": "linear", "x": "step", "y": y,
                                    "title": f"Training {metric} per epoch (DVCLive, one line per run)",
                                    "x_label": "epoch", "y_label": f"training {metric}"}}]


def render_dvc_yaml(code_root: Path | None = None, data_deps: dict[str, list[str]] | None = None,
                    header: str = DVC_HEADER, omit: tuple[str, ...] = (), extra_plots: list[dict] = (),
                    optional: tuple[str, ...] = (), groups: dict[str, list[list[int]]] | None = None) -> str:
    """Render dvc.yaml's text; by default this repository's DAG.

    Parameters
    ----------
    code_root : Path, optional
        Where the code deps point: a distill project names the installed code by absolute path; None: this
        repository, by relative path.
    data_deps : dict, optional
        ``{stage: paths}`` replacing the catalogue's data deps (a distill project's input folder).
    header : str
        The comment opening the file.
    omit : tuple of str
        Stages left out; their outputs leave their readers' deps.
    extra_plots : list of dict
        Top-level plots added after the catalogue's (:func:`live_plots`).
    optional : tuple of str
        The :data:`OPTIONAL_STAGES` to render and the :data:`OPTIONAL_PARAMS` to track (:func:`optional_stages_on`).
    groups : dict, optional
        Seeds grouped per training stage (:func:`seed_groups`); None: a matrix stage per method.

    Returns
    -------
    str
        The YAML text.
    """
    doc = {"stages": dvc_stages(code_root, data_deps, omit, optional, groups),
           "plots": dvc_plots(omit) + list(extra_plots)}
    return header + yaml.safe_dump(doc, sort_keys=False, width=110, default_flow_style=False)


def project_dvc_yaml(params: dict | None) -> str:
    """Render this repository's dvc.yaml for ``params``, as ``geodistill dag`` writes it.

    Parameters
    ----------
    params : dict or None
        params.yaml as read (its optional stages and seed groups); None: neither.

    Returns
    -------
    str
        The YAML text.
    """
    return render_dvc_yaml(optional=optional_stages_on(params), groups=seed_groups(params))


PARAMS_HEADER = """\
# GeoDistill-Refine params -- the effective values of profile {profile!r}, written by
# `geodistill profile {profile}` from the schema defaults (pipeline/params.py, the paper's values) and the
# profile's overrides (pipeline/profiles.py).  Edit single values here (or `dvc exp run -S key=value`):
# DVC tracks every key, so a change reruns exactly the stages that read it.  Switch profile with
# `geodistill profile demo|reduced|reduced-strong|paper` (this file is rewritten).  Every stage validates this file first.
"""


def _flow(v: Any) -> str:
    return yaml.safe_dump(v, default_flow_style=True, width=10_000).strip().removesuffix("\n...").strip()


def _emit(model_cls, values: dict, indent: int, lines: list[str]) -> None:
    from pydantic import BaseModel

    pad = "  " * indent
    fields = model_cls.model_fields
    for key, value in values.items():
        f = fields.get(key)
        ann = f.annotation if f is not None else None
        desc = f" # {f.description}" if f is not None and f.description else ""
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            lines.append(f"{pad}{key}:{desc}")
            _emit(ann, value, indent + 1, lines)
        elif key == "runs":
            lines.append(f"{pad}{key}:{desc}")
            for m, seeds in value.items():
                lines.append(f"{pad}  {m}: {_flow(seeds)}")
        else:
            lines.append(f"{pad}{key}: {_flow(value)}{' ' if desc else ''}{desc}")


#: how every generated params file begins: how `profile` recognises its own output
GENERATED_PARAMS_MARK = "# GeoDistill-Refine params"


def is_generated_params(path: str | Path) -> bool:
    """Tell whether ``path`` is a params file written by ``geodistill profile`` / ``distill``.

    Parameters
    ----------
    path : str or Path
        A file.

    Returns
    -------
    bool
        Whether its first line is :data:`GENERATED_PARAMS_MARK`'s; False when it cannot be read.
    """
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            return f.readline().startswith(GENERATED_PARAMS_MARK)
    except OSError:
        return False


def render_params_yaml(profile: str, overrides: dict | None = None, header: str | None = None) -> str:
    """Render params.yaml's text for ``profile``: every key with its value and the schema's description.

    Parameters
    ----------
    profile : str
        A profile of :mod:`pipeline.profiles` (``demo``, ``reduced``, ``paper``, ...).
    overrides : dict, optional
        Nested values merged over the profile's.
    header : str, optional
        Replaces the standard header (:data:`PARAMS_HEADER`).

    Returns
    -------
    str
        The YAML text, validated.

    Raises
    ------
    InputError
        An override the schema refuses (from :func:`pipeline.params.validate`).
    """
    raw = deep_merge(profile_params(profile), overrides or {})
    values = unresolved(validate(raw, f"profile {profile}"), raw)  # recipe parts: null = the recipe's value
    lines: list[str] = []
    _emit(Params, values, 0, lines)
    return (header if header is not None else PARAMS_HEADER.format(profile=profile)) + "\n".join(lines) + "\n"
