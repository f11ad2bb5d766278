"""The notebook API: ``label(...)``, ``distill(...)`` and ``Segmenter.from_bundle(path).predict(image)``.

The same runs as ``geodistill label`` / ``geodistill distill``, with the same params rules: ``params`` is a
params file (default: the command's profile, not ./params.yaml) and ``overrides`` are ``--set`` items, as
``["train.epochs_stage1=3"]`` or ``{"train.epochs_stage1": 3}``.  Errors are one-line InputErrors naming the
keyword argument where the command names its flag.

>>> res = pipeline.label("images/", checkpoint="sam3/", out="labels/")               # doctest: +SKIP
>>> out = pipeline.distill("images/", out="run/", labels="labels/")                  # doctest: +SKIP
>>> mask = pipeline.Segmenter.from_bundle(out["deploy"]).predict("images/x.png")   # doctest: +SKIP
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Iterable, Mapping, Sequence

from pipeline.datasets.loading import check_bit_depth, pixel_limit
from pipeline.runtime.errors import BACKEND, CHECKPOINT, IMPORTED_DIR, LABELS, InputError, literal
from pipeline.labeling import LabelResult, label_folder
from pipeline.labeling.run import check_label_folder, parse_formats
from pipeline.params import deep_merge, validate
from pipeline.profiles import load_params_or_profile
from pipeline.orchestration.standalone import project_outputs, run_project, time_budget_params, write_project
from pipeline.teacher_table import TEACHER_TABLE, is_simulator, load

LABEL_PROFILE = "paper"
DISTILL_PROFILE = "distill"
#: the teacher keys that do not change its answers; ``distill --labels`` takes every other one from label.json
TEACHER_RUN_KEYS = ("base_prompt_index", "vflip_base_prompt", "splits", "batch_size", "compile", "cache_dir")


def effective_params(params: str | Path | None = None, overrides: Mapping | Iterable[str] | None = None,
                     default_profile: str = LABEL_PROFILE) -> dict:
    """Validated params: the file ``params`` (None: ``default_profile``) with ``overrides`` applied."""
    if isinstance(overrides, Mapping):
        items = [f"{k}={json.dumps(v)}" for k, v in overrides.items()]  # JSON values are YAML
    else:
        items = list(overrides or [])
    return load_params_or_profile(params, items, default_profile)


def teacher_overrides(backend: str | None, checkpoint: str | Path | None, imported_dir: str | Path | None) -> dict:
    """The ``teacher`` keys the options set: a folder option means the first backend of
    :data:`~pipeline.teacher_table.TEACHER_TABLE` that requires it (``checkpoint``: sam3, ``imported_dir``:
    imported), unless ``backend`` says otherwise."""
    given = {o: v for o, v in ((CHECKPOINT, checkpoint), (IMPORTED_DIR, imported_dir)) if v}
    if backend is None:
        backend = next((name for name, spec in TEACHER_TABLE.items() for o in given if o.keyword in spec.settings[:1]),
                       None)
    out = {} if backend is None else {"backend": backend}
    spec = TEACHER_TABLE.get(backend)
    for option, value in given.items():
        if spec is not None and spec.check and option.keyword in spec.settings[:1]:
            load(spec.check)(value, option)  # checked here: the error names the option the user gave
        out[option.keyword] = str(Path(value).resolve())
    return out


def choose_teacher(params: dict, backend: str | None, checkpoint: str | Path | None,
                   imported_dir: str | Path | None) -> dict:
    """``params`` with the chosen teacher, validated again; InputError when neither an option nor a params
    file naming a real teacher (one with its settings, e.g. a SAM 3 checkpoint) chose one: a SIMULATOR,
    the schema's default, is never picked silently."""
    chosen = teacher_overrides(backend, checkpoint, imported_dir)
    if not chosen and is_simulator(params["teacher"]["backend"]):
        raise InputError("{} is required (or {})", CHECKPOINT("SAM3_DIR"), BACKEND("imported|simulated"))
    return validate(deep_merge(params, {"teacher": chosen}), "options")


def params_from_labels(params: dict, labels: str | Path, input_dir: str | Path, backend: str | None = None,
                       checkpoint: str | Path | None = None, imported_dir: str | Path | None = None,
                       default_profile: str = DISTILL_PROFILE) -> dict:
    """``params`` for a distill from the unmodified label folder ``labels`` of ``input_dir`` (``--labels``):
    the teacher, ``data.resolution``, ``consensus.vote_threshold`` and ``geometry`` from its label.json (a
    value the caller set otherwise is refused, naming both), and label's teacher cache unless the caller
    chose one."""
    record = check_label_folder(labels, input_dir)
    base = load_params_or_profile(None, [], default_profile)
    chosen = teacher_overrides(backend, checkpoint, imported_dir)
    taken = {("teacher", k): v for k, v in record["teacher"].items() if k not in TEACHER_RUN_KEYS}
    taken.update({("geometry", k): v for k, v in record["geometry"].items()})
    taken.update({("data", "resolution"): record["resolution"], ("consensus", "vote_threshold"): record["vote_threshold"]})
    for (sec, key), value in taken.items():
        given = chosen.get(key) if sec == "teacher" and key in chosen else params[sec].get(key)
        if (given != base[sec].get(key) or (sec == "teacher" and key in chosen)) and given != value:
            raise InputError(f"{{}}: label made these pseudo-labels with {sec}.{key}={literal(repr(value))}, "
                             f"not {literal(repr(given))}; leave it out, or rerun label with it", LABELS(labels))
    merged = deep_merge(params, {})  # a copy
    for (sec, key), value in taken.items():
        merged[sec][key] = value
    if params["teacher"]["cache_dir"] == base["teacher"]["cache_dir"]:
        merged["teacher"]["cache_dir"] = str(Path(record["teacher"]["cache_dir"]).resolve())
    return validate(merged, "labels")


def distill_params(params: dict, input_dir: str | Path, labels: str | Path | None, backend: str | None,
                   checkpoint: str | Path | None, imported_dir: str | Path | None, skip_bad: bool = False,
                   max_pixels: int | None = None, bit_depth: str | int | None = None) -> dict:
    """The params of a distill project: the teacher from a label folder or the teacher options, then the
    data options."""
    if labels is not None:
        params = params_from_labels(params, labels, input_dir, backend, checkpoint, imported_dir)
    else:
        params = choose_teacher(params, backend, checkpoint, imported_dir)
    return with_data_options(params, skip_bad, max_pixels, bit_depth)


def with_data_options(params: dict, skip_bad: bool = False, max_pixels: int | None = None,
                      bit_depth: str | int | None = None) -> dict:
    """``params`` with the data options of label and distill: ``skip_bad`` only turns ``data.skip_bad`` on;
    ``max_pixels`` and ``bit_depth`` are checked, None keeps the params' value."""
    data: dict = {}
    if skip_bad:
        data["skip_bad"] = True
    if max_pixels is not None:
        data["max_pixels"] = pixel_limit(max_pixels)
    if bit_depth is not None:
        data["bit_depth"] = check_bit_depth(bit_depth)
    return deep_merge(params, {"data": data}) if data else params


def label(input: str | Path, *, out: str | Path, checkpoint: str | Path | None = None,
          formats: str | Sequence[str] | None = None, backend: str | None = None,
          imported_dir: str | Path | None = None, reference_masks: str | Path | None = None,
          params: str | Path | None = None, overrides: Mapping | Iterable[str] | None = None,
          device: str = "auto", skip_bad: bool = False, overwrite: bool = False,
          max_pixels: int | None = None, bit_depth: str | int | None = None) -> LabelResult:
    """Pseudo-label the images under ``input`` into ``out`` (``geodistill label``): voted masks as PNG /
    COCO RLE / YOLO files, the gate table and a contact sheet.  A teacher is required: ``checkpoint``
    (SAM 3), ``backend="imported"`` with ``imported_dir``, or a ``params`` file naming a checkpoint;
    ``backend="simulated"`` (a SIMULATOR) needs ``reference_masks``; ``formats``: a subset of
    :data:`~pipeline.labeling.formats.LABEL_FORMATS` (None: its default ones, png, coco and yolo).  The other
    keywords are the command's options."""
    fmts = parse_formats(formats)
    p = choose_teacher(effective_params(params, overrides, LABEL_PROFILE), backend, checkpoint, imported_dir)
    p = with_data_options(p, skip_bad, max_pixels, bit_depth)
    return label_folder(input, out, p, device=device, formats=fmts, reference_masks=reference_masks,
                        overwrite=overwrite)


def distill(input: str | Path, *, out: str | Path, val_masks: str | Path | None = None,
            checkpoint: str | Path | None = None, backend: str | None = None,
            imported_dir: str | Path | None = None, params: str | Path | None = None,
            overrides: Mapping | Iterable[str] | None = None, device: str = "auto", run: bool = True,
            skip_bad: bool = False, overwrite: bool = False, max_pixels: int | None = None,
            labels: str | Path | None = None, bit_depth: str | int | None = None, benchmark: bool = True,
            time: str | None = None) -> dict:
    """Train a deployable student on the images under ``input`` (``geodistill distill``): ``out`` becomes a
    DVC project running the DAG (rerun to resume); returns the ``deploy``, ``report``, ``thresholds`` and
    ``checkpoints`` paths.  ``run=False`` only writes the project; ``labels``: a :func:`label` output
    folder of the same images, whose teacher answers are reused; ``time`` (e.g. ``"20m"``): Stage I's
    budget.  The other keywords are the command's options."""
    p = distill_params(effective_params(params, overrides, DISTILL_PROFILE), input, labels, backend, checkpoint,
                       imported_dir, skip_bad, max_pixels, bit_depth)
    p = time_budget_params(p, time, out, device, input, val_masks)
    project = write_project(input, out, p, val_masks=val_masks, overwrite=overwrite, labels=labels,
                            benchmark=benchmark)
    if run:
        run_project(project, device)
    return project_outputs(project)
