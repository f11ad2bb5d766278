"""The notebook API: ``label(...)``, ``distill(...)`` and ``Segmenter.from_bundle(path).predict(image)``.

The same runs as the ``geodistill label`` / ``geodistill distill`` commands (which call the helpers here),
with the same params rules: ``params`` is a params file (default: the command's profile -- ``paper``
for label, ``distill`` for distill -- not ./params.yaml, since a notebook may run anywhere), and
``overrides`` are ``--set`` items, as ``["train.epochs_stage1=3"]`` or ``{"train.epochs_stage1": 3}``.
Errors are :class:`pipeline.runtime.errors.InputError` with one line naming the file or option -- here by its
keyword argument (``skip_bad=True``, ``max_pixels=``), on the command line by its flag (``--skip-bad``,
``--max-pixels``): the same error, rendered in the caller's terms (docs/own-data.md).

>>> import pipeline                                                                   # doctest: +SKIP
>>> res = pipeline.label("images/", checkpoint="sam3/", out="labels/")               # doctest: +SKIP
>>> res.table[["image_id", "c", "v", "a", "g"]].head()                             # doctest: +SKIP
>>> out = pipeline.distill("images/", out="run/", checkpoint="sam3/", val_masks="masks/")  # doctest: +SKIP
>>> out = pipeline.distill("images/", out="run/", labels="labels/")  # label's teacher answers  # doctest: +SKIP
>>> mask = pipeline.Segmenter.from_bundle(out["deploy"]).predict("images/x.png")   # doctest: +SKIP
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Iterable, Mapping, Sequence

from pipeline.datasets.loading import check_bit_depth, pixel_limit
from pipeline.runtime.errors import BACKEND, CHECKPOINT, LABELS, InputError, literal
from pipeline.labeling import LabelResult, label_folder
from pipeline.labeling.run import check_label_folder, parse_formats
from pipeline.params import SAM3, deep_merge, validate
from pipeline.profiles import load_params_or_profile
from pipeline.orchestration.standalone import project_outputs, run_project, time_budget_params, write_project
from pipeline.teachers.sam3 import check_checkpoint_dir

LABEL_PROFILE = "paper"
DISTILL_PROFILE = "distill"
#: the teacher keys that do not change its answers: everything else in label.json's teacher section is
#: what made the pseudo-labels, and ``distill --labels`` takes it (:func:`params_from_labels`)
TEACHER_RUN_KEYS = ("base_prompt_index", "vflip_base_prompt", "splits", "batch_size", "compile", "cache_dir")


def effective_params(params: str | Path | None = None, overrides: Mapping | Iterable[str] | None = None,
                     default_profile: str = LABEL_PROFILE) -> dict:
    """Validated params: the file ``params`` (or, when None, ``default_profile``'s values) with
    ``overrides`` applied (``--set profile=X`` picks another profile, as on the command line)."""
    if isinstance(overrides, Mapping):
        items = [f"{k}={json.dumps(v)}" for k, v in overrides.items()]  # JSON values are YAML
    else:
        items = list(overrides or [])
    return load_params_or_profile(params, items, default_profile)


def teacher_overrides(backend: str | None, checkpoint: str | Path | None, imported_dir: str | Path | None) -> dict:
    """The ``teacher`` keys the label/distill options set: ``checkpoint`` means backend sam3 unless
    ``backend`` says otherwise; ``imported_dir`` means imported."""
    if backend is None:
        backend = "sam3" if checkpoint else "imported" if imported_dir else None
    out = {} if backend is None else {"backend": backend}
    if checkpoint and backend == SAM3:  # checked here: the error names the option the user gave
        check_checkpoint_dir(checkpoint, CHECKPOINT)
    if checkpoint:
        out["checkpoint"] = str(Path(checkpoint).resolve())
    if imported_dir:
        out["imported_dir"] = str(Path(imported_dir).resolve())
    return out


def choose_teacher(params: dict, backend: str | None, checkpoint: str | Path | None,
                   imported_dir: str | Path | None) -> dict:
    """``params`` with the chosen teacher, validated again.  InputError when none was chosen: without
    ``checkpoint``, ``imported_dir`` or ``backend`` only a params file naming a SAM 3 checkpoint
    chooses one (the schema's default backend is the synthetic benchmark's SIMULATOR, never picked
    silently)."""
    chosen = teacher_overrides(backend, checkpoint, imported_dir)
    if not chosen and not (params["teacher"]["backend"] == "sam3" and params["teacher"]["checkpoint"]):
        raise InputError("{} is required (or {})", CHECKPOINT("SAM3_DIR"), BACKEND("imported|simulated"))
    return validate(deep_merge(params, {"teacher": chosen}), "options")


def params_from_labels(params: dict, labels: str | Path, input_dir: str | Path, backend: str | None = None,
                       checkpoint: str | Path | None = None, imported_dir: str | Path | None = None,
                       default_profile: str = DISTILL_PROFILE) -> dict:
    """``params`` for a distill that trains from the ``label`` output folder ``labels`` without running
    the teacher again (``--labels`` / ``labels=``).  The folder must be an unmodified, complete label
    output of ``input_dir`` (:func:`pipeline.labeling.run.check_label_folder`).  What made its
    pseudo-labels is taken from its label.json: the teacher (every key but :data:`TEACHER_RUN_KEYS`),
    ``data.resolution``, ``consensus.vote_threshold`` and ``geometry``; a value the caller set otherwise
    (``--set``/``--params``/``--checkpoint``, or their keywords; anything not ``default_profile``'s
    value) is refused, naming both.  Unless the caller set ``teacher.cache_dir``, the teacher cache is
    label's, so the teacher stage finds every answer there (the keys are the image bytes and the
    teacher: :mod:`pipeline.teachers.cache`)."""
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
    """The params of a distill project (command and API): the teacher from a label folder
    (:func:`params_from_labels`) or from the teacher options (:func:`choose_teacher`), then the data
    options (:func:`with_data_options`)."""
    if labels is not None:
        params = params_from_labels(params, labels, input_dir, backend, checkpoint, imported_dir)
    else:
        params = choose_teacher(params, backend, checkpoint, imported_dir)
    return with_data_options(params, skip_bad, max_pixels, bit_depth)


def with_data_options(params: dict, skip_bad: bool = False, max_pixels: int | None = None,
                      bit_depth: str | int | None = None) -> dict:
    """``params`` with the data options of label and distill (``--skip-bad`` / ``skip_bad=``,
    ``--max-pixels`` / ``max_pixels=``, ``--bit-depth`` / ``bit_depth=``): ``data.skip_bad`` true when
    ``skip_bad`` (it never turns it off), ``data.max_pixels`` and ``data.bit_depth`` when given (checked,
    InputError naming the option; None keeps the params' value)."""
    data: dict = {}
    if skip_bad:
        data["skip_bad"] = True
    if max_pixels is not None:
        data["max_pixels"] = pixel_limit(max_pixels)
    if bit_depth is not None:
        data["bit_depth"] = check_bit_depth(bit_depth)
    return deep_merge(params, {"data": data}) if data else params


def label(input: str | Path, *, out: str | Path, checkpoint: str | Path | None = None,
          formats: str | Sequence[str] = ("png", "coco", "yolo"), backend: str | None = None,
          imported_dir: str | Path | None = None, reference_masks: str | Path | None = None,
          params: str | Path | None = None, overrides: Mapping | Iterable[str] | None = None,
          device: str = "auto", skip_bad: bool = False, overwrite: bool = False,
          max_pixels: int | None = None, bit_depth: str | int | None = None) -> LabelResult:
    """Pseudo-label the images under ``input`` into ``out`` (``geodistill label``;
    :mod:`pipeline.labeling.run`): voted masks as PNG / COCO RLE / YOLO files, the gate table and a
    contact sheet.  Returns a :class:`pipeline.labeling.LabelResult` (``.table``: c, v, a, g per image;
    ``.masks``: image id -> mask PNG).  Every argument but ``input`` is a keyword; ``out`` is required,
    and a teacher: ``checkpoint`` (SAM 3), ``backend="imported"`` with ``imported_dir``, or a ``params``
    file naming a checkpoint.  ``backend="simulated"`` is a SIMULATOR that needs ``reference_masks``.
    ``skip_bad``, ``overwrite`` and ``max_pixels`` (None: the params' ``data.max_pixels``, 2**26 by
    default): the command's ``--skip-bad``, ``--overwrite`` and ``--max-pixels`` (docs/own-data.md);
    ``bit_depth`` (auto, 10, 12, 14, 16; None: the params' ``data.bit_depth``): ``--bit-depth``."""
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
    """Train a deployable student on the images under ``input`` (``geodistill distill``;
    :mod:`pipeline.orchestration.standalone`): ``out`` becomes a DVC project running the pipeline's DAG (rerun to
    resume).  Returns ``{"deploy", "report", "thresholds", "checkpoints"}`` paths; ``run=False`` only
    writes the project.  Every argument but ``input`` is a keyword; ``out`` is required.  ``skip_bad``,
    ``overwrite``, ``max_pixels``, ``bit_depth``: as for :func:`label`.
    ``labels``: an unmodified :func:`label` output folder of the same images -- its teacher, resolution,
    vote and gate are used and its teacher cache is read, so the teacher computes nothing again
    (:func:`params_from_labels`; no ``checkpoint`` needed).  ``benchmark=False``: no benchmark stage
    (``--no-benchmark``).  ``time`` (e.g. ``"20m"``): Stage I's budget (``--time``;
    :func:`pipeline.orchestration.standalone.time_budget_params`)."""
    p = distill_params(effective_params(params, overrides, DISTILL_PROFILE), input, labels, backend, checkpoint,
                       imported_dir, skip_bad, max_pixels, bit_depth)
    p = time_budget_params(p, time, out, device)
    project = write_project(input, out, p, val_masks=val_masks, overwrite=overwrite, labels=labels,
                            benchmark=benchmark)
    if run:
        run_project(project, device)
    return project_outputs(project)
