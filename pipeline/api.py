"""The notebook API: ``label(...)``, ``distill(...)`` and ``Segmenter.from_bundle(path).predict(image)``.

The same runs as the ``geodistill label`` / ``geodistill distill`` commands (which call the helpers here),
with the same params rules: ``params`` is a params file (default: the command's profile -- ``paper``
for label, ``distill`` for distill -- not ./params.yaml, since a notebook may run anywhere), and
``overrides`` are ``--set`` items, as ``["train.epochs_stage1=3"]`` or ``{"train.epochs_stage1": 3}``.
Errors are :class:`pipeline.errors.InputError` with one line naming the file or option.

>>> import pipeline                                                                   # doctest: +SKIP
>>> res = pipeline.label("images/", checkpoint="sam3/", out="labels/")               # doctest: +SKIP
>>> res.table[["image_id", "c", "v", "a", "g"]].head()                             # doctest: +SKIP
>>> out = pipeline.distill("images/", out="run/", checkpoint="sam3/", val_masks="masks/")  # doctest: +SKIP
>>> mask = pipeline.Segmenter.from_bundle(out["deploy"]).predict("images/x.png")   # doctest: +SKIP
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Iterable, Mapping, Sequence

from pipeline.errors import InputError
from pipeline.labeling import label_folder
from pipeline.labeling.run import parse_formats
from pipeline.params import deep_merge, validate
from pipeline.profiles import load_params_or_profile
from pipeline.standalone import project_outputs, run_project, write_project

LABEL_PROFILE = "paper"
DISTILL_PROFILE = "distill"


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
        raise InputError("--checkpoint SAM3_DIR is required (or --backend imported|simulated)")
    return validate(deep_merge(params, {"teacher": chosen}), "options")


def with_skip_bad(params: dict, skip_bad: bool) -> dict:
    """``params`` with ``data.skip_bad`` true when ``--skip-bad`` was given (it never turns it off)."""
    return deep_merge(params, {"data": {"skip_bad": True}}) if skip_bad else params


def label(input: str | Path, checkpoint: str | Path | None = None, out: str | Path | None = None,
          formats: str | Sequence[str] = ("png", "coco", "yolo"), *, backend: str | None = None,
          imported_dir: str | Path | None = None, reference_masks: str | Path | None = None,
          params: str | Path | None = None, overrides: Mapping | Iterable[str] | None = None,
          device: str = "auto", skip_bad: bool = False, overwrite: bool = False):
    """Pseudo-label the images under ``input`` into ``out`` (``geodistill label``;
    :mod:`pipeline.labeling.run`): voted masks as PNG / COCO RLE / YOLO files, the gate table and a
    contact sheet.  Returns a :class:`pipeline.labeling.LabelResult` (``.table``: c, v, a, g per image).
    ``backend="simulated"`` is a SIMULATOR that needs ``reference_masks``.  ``skip_bad`` and
    ``overwrite``: the command's ``--skip-bad`` and ``--overwrite`` (docs/own-data.md)."""
    if out is None:
        raise InputError("label: out= (the output folder) is required")
    fmts = parse_formats(formats)
    p = choose_teacher(effective_params(params, overrides, LABEL_PROFILE), backend, checkpoint, imported_dir)
    p = with_skip_bad(p, skip_bad)
    return label_folder(input, out, p, device=device, formats=fmts, reference_masks=reference_masks,
                        overwrite=overwrite)


def distill(input: str | Path, out: str | Path | None = None, val_masks: str | Path | None = None,
            checkpoint: str | Path | None = None, *, backend: str | None = None,
            imported_dir: str | Path | None = None, params: str | Path | None = None,
            overrides: Mapping | Iterable[str] | None = None, device: str = "auto", run: bool = True,
            skip_bad: bool = False, overwrite: bool = False) -> dict:
    """Train a deployable student on the images under ``input`` (``geodistill distill``;
    :mod:`pipeline.standalone`): ``out`` becomes a DVC project running the pipeline's DAG (rerun to
    resume).  Returns ``{"deploy", "report", "thresholds", "checkpoints"}`` paths; ``run=False`` only
    writes the project."""
    if out is None:
        raise InputError("distill: out= (the project folder) is required")
    p = choose_teacher(effective_params(params, overrides, DISTILL_PROFILE), backend, checkpoint, imported_dir)
    project = write_project(input, out, with_skip_bad(p, skip_bad), val_masks=val_masks, overwrite=overwrite)
    if run:
        run_project(project, device)
    return project_outputs(project)
