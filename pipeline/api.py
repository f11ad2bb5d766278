"""The notebook API: ``label(...)``, ``distill(...)`` and ``Segmenter.from_bundle(path).predict(image)``.

The same runs as the ``geodistill label`` / ``geodistill distill`` commands (which call the helpers here),
with the same params rules: ``params`` is a params file (default: the command's profile -- ``paper``
for label, ``distill`` for distill -- not ./params.yaml, since a notebook may run anywhere), and
``overrides`` are ``--set`` items, as ``["train.epochs_stage1=3"]`` or ``{"train.epochs_stage1": 3}``.
Errors are :class:`pipeline.errors.InputError` with one line naming the file or option -- here by its
keyword argument (``skip_bad=True``, ``max_pixels=``), on the command line by its flag (``--skip-bad``,
``--max-pixels``): the same error, rendered in the caller's terms (docs/own-data.md).

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

from pipeline.datasets.loading import pixel_limit
from pipeline.errors import BACKEND, CHECKPOINT, OUT, InputError
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
        raise InputError("{} is required (or {})", CHECKPOINT("SAM3_DIR"), BACKEND("imported|simulated"))
    return validate(deep_merge(params, {"teacher": chosen}), "options")


def with_data_options(params: dict, skip_bad: bool = False, max_pixels: int | None = None) -> dict:
    """``params`` with the bad-file options of label and distill (``--skip-bad`` / ``skip_bad=``,
    ``--max-pixels`` / ``max_pixels=``): ``data.skip_bad`` true when ``skip_bad`` (it never turns it
    off), ``data.max_pixels`` when ``max_pixels`` is given (checked, InputError naming the option;
    None keeps the params' value)."""
    data: dict = {}
    if skip_bad:
        data["skip_bad"] = True
    if max_pixels is not None:
        data["max_pixels"] = pixel_limit(max_pixels)
    return deep_merge(params, {"data": data}) if data else params


def label(input: str | Path, checkpoint: str | Path | None = None, out: str | Path | None = None,
          formats: str | Sequence[str] = ("png", "coco", "yolo"), *, backend: str | None = None,
          imported_dir: str | Path | None = None, reference_masks: str | Path | None = None,
          params: str | Path | None = None, overrides: Mapping | Iterable[str] | None = None,
          device: str = "auto", skip_bad: bool = False, overwrite: bool = False, max_pixels: int | None = None):
    """Pseudo-label the images under ``input`` into ``out`` (``geodistill label``;
    :mod:`pipeline.labeling.run`): voted masks as PNG / COCO RLE / YOLO files, the gate table and a
    contact sheet.  Returns a :class:`pipeline.labeling.LabelResult` (``.table``: c, v, a, g per image).
    ``backend="simulated"`` is a SIMULATOR that needs ``reference_masks``.  ``skip_bad``, ``overwrite``
    and ``max_pixels`` (None: the params' ``data.max_pixels``, 2**26 by default): the command's
    ``--skip-bad``, ``--overwrite`` and ``--max-pixels`` (docs/own-data.md)."""
    if out is None:
        raise InputError("label: {} (the output folder) is required", OUT)
    fmts = parse_formats(formats)
    p = choose_teacher(effective_params(params, overrides, LABEL_PROFILE), backend, checkpoint, imported_dir)
    p = with_data_options(p, skip_bad, max_pixels)
    return label_folder(input, out, p, device=device, formats=fmts, reference_masks=reference_masks,
                        overwrite=overwrite)


def distill(input: str | Path, out: str | Path | None = None, val_masks: str | Path | None = None,
            checkpoint: str | Path | None = None, *, backend: str | None = None,
            imported_dir: str | Path | None = None, params: str | Path | None = None,
            overrides: Mapping | Iterable[str] | None = None, device: str = "auto", run: bool = True,
            skip_bad: bool = False, overwrite: bool = False, max_pixels: int | None = None) -> dict:
    """Train a deployable student on the images under ``input`` (``geodistill distill``;
    :mod:`pipeline.standalone`): ``out`` becomes a DVC project running the pipeline's DAG (rerun to
    resume).  Returns ``{"deploy", "report", "thresholds", "checkpoints"}`` paths; ``run=False`` only
    writes the project.  ``skip_bad``, ``overwrite``, ``max_pixels``: as for :func:`label`."""
    if out is None:
        raise InputError("distill: {} (the project folder) is required", OUT)
    p = choose_teacher(effective_params(params, overrides, DISTILL_PROFILE), backend, checkpoint, imported_dir)
    p = with_data_options(p, skip_bad, max_pixels)
    project = write_project(input, out, p, val_masks=val_masks, overwrite=overwrite)
    if run:
        run_project(project, device)
    return project_outputs(project)
