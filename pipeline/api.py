"""The notebook API: ``label(...)``, ``distill(...)`` and ``Segmenter.from_bundle(path).predict(image)``.

The same runs as ``geodistill label`` / ``geodistill distill``, with the same params rules: ``params`` is a
params file (default: the command's profile, ``paper`` for label and ``distill`` for distill, not
./params.yaml) and ``overrides`` are ``--set`` items, as ``["train.epochs_stage1=3"]`` or
``{"train.epochs_stage1": 3}``.  Errors are one-line :class:`pipeline.runtime.errors.InputError` naming the
keyword argument (``skip_bad=True``) where the command names its flag (``--skip-bad``).

>>> res = pipeline.label("images/", checkpoint="sam3/", out="labels/")               # doctest: +SKIP
>>> out = pipeline.distill("images/", out="run/", labels="labels/")                  # doctest: +SKIP
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
from pipeline.params import deep_merge, validate
from pipeline.profiles import load_params_or_profile
from pipeline.orchestration.standalone import project_outputs, run_project, time_budget_params, write_project
from pipeline.teacher_table import find_teacher, folder_options, is_simulator, load

__all__ = ["LABEL_PROFILE", "DISTILL_PROFILE", "TEACHER_RUN_KEYS", "effective_params", "teacher_overrides",
           "choose_teacher", "params_from_labels", "distill_params", "with_data_options", "label", "distill"]

#: the profile whose values ``label`` uses without a params file
LABEL_PROFILE = "paper"
#: the profile whose values ``distill`` uses without a params file
DISTILL_PROFILE = "distill"
#: the teacher keys that do not change its answers; ``distill --labels`` takes every other one from label.json
TEACHER_RUN_KEYS = ("base_prompt_index", "vflip_base_prompt", "splits", "batch_size", "compile", "cache_dir")


def effective_params(params: str | Path | None = None, overrides: Mapping | Iterable[str] | None = None,
                     default_profile: str = LABEL_PROFILE) -> dict:
    """Read validated params: a params file or a profile, with overrides applied.

    Parameters
    ----------
    params : str or Path, optional
        A params file; None: ``default_profile``'s values.
    overrides : mapping or iterable of str, optional
        ``--set`` items (``"key=value"``) or a mapping key -> value (values written as JSON, read as YAML);
        ``profile=X`` picks another profile, as on the command line.
    default_profile : str, optional
        The profile used without ``params`` (default :data:`LABEL_PROFILE`).

    Returns
    -------
    dict
        The validated params.

    Raises
    ------
    InputError
        The file, a key or a value is invalid, naming it.
    """
    if isinstance(overrides, Mapping):
        items = [f"{k}={json.dumps(v)}" for k, v in overrides.items()]  # JSON values are YAML
    else:
        items = list(overrides or [])
    return load_params_or_profile(params, items, default_profile)


def teacher_overrides(backend: str | None, folders: Mapping[str, str | Path | None]) -> dict:
    """Return the ``teacher`` keys the label/distill options set.

    A folder option (a backend row's ``folder``: ``--checkpoint``, ``--imported-dir``) sets that row's first
    setting and means the first backend of :data:`~pipeline.teacher_table.TEACHER_TABLE` whose folder it is,
    unless ``backend`` says otherwise; where that backend's row has a ``check`` (SAM 3's checkpoint folder),
    the folder is checked here, so the error names the option the user gave.

    Parameters
    ----------
    backend : str, optional
        A backend of :data:`~pipeline.teacher_table.TEACHER_TABLE` or an installed plug-in's name; None:
        inferred from ``folders``.
    folders : mapping of str to (str or Path or None)
        The folder options by setting (``{"checkpoint": "sam3/"}``); None is not given.  Stored resolved.

    Returns
    -------
    dict
        ``backend`` (given or inferred) and the folders given; empty when none is.

    Raises
    ------
    InputError
        From the backend's ``check`` (``checkpoint`` is not a SAM 3 folder), or a plug-in fails to load.
    """
    options = folder_options()
    given = {o: folders[o.keyword] for o, _ in options.values() if folders.get(o.keyword)}
    if backend is None:
        backend = next((name for name, (o, _) in options.items() if o in given), None)
    out = {} if backend is None else {"backend": backend}
    spec = find_teacher(backend) if backend is not None else None
    for option, value in given.items():
        if spec is not None and spec.check and option.keyword in spec.settings[:1]:
            load(spec.check)(value, option)  # checked here: the error names the option the user gave
        out[option.keyword] = str(Path(value).resolve())
    return out


def choose_teacher(params: dict, backend: str | None, folders: Mapping[str, str | Path | None]) -> dict:
    """Return ``params`` with the chosen teacher, validated again.

    Without ``checkpoint``, ``imported_dir`` or ``backend``, only a params file naming a real teacher (a backend of
    :data:`~pipeline.teacher_table.TEACHER_TABLE` that is not a SIMULATOR, with its settings, e.g. a SAM 3
    checkpoint or an imported folder) chooses one: the schema's default backend, the synthetic benchmark's
    SIMULATOR, is never picked silently.

    Parameters
    ----------
    params : dict
        Validated params.
    backend : str, optional
        The teacher backend (:func:`teacher_overrides`).
    folders : mapping of str to (str or Path or None)
        The folder options by setting (:func:`teacher_overrides`).

    Returns
    -------
    dict
        The validated params.

    Raises
    ------
    InputError
        No teacher was chosen, a teacher option is invalid, or the merged params do not validate.
    """
    chosen = teacher_overrides(backend, folders)
    if not chosen and is_simulator(params["teacher"]["backend"]):
        raise InputError("{} is required (or {})", CHECKPOINT("SAM3_DIR"), BACKEND("imported|simulated"))
    return validate(deep_merge(params, {"teacher": chosen}), "options")


def params_from_labels(params: dict, labels: str | Path, input_dir: str | Path, backend: str | None = None,
                       folders: Mapping[str, str | Path | None] | None = None,
                       default_profile: str = DISTILL_PROFILE) -> dict:
    """Return the params of a distill that trains from a ``label`` output folder (``--labels`` / ``labels=``).

    The folder must be an unmodified, complete label output of ``input_dir``
    (:func:`pipeline.labeling.run.check_label_folder`).  What made its pseudo-labels comes from its label.json:
    the teacher (every key but :data:`TEACHER_RUN_KEYS`), ``data.resolution``, ``consensus.vote_threshold`` and
    ``geometry``.  Unless the caller set ``teacher.cache_dir``, the teacher cache is label's, so the teacher
    computes nothing again.

    Parameters
    ----------
    params : dict
        Validated params.
    labels : str or Path
        The label output folder.
    input_dir : str or Path
        The images it labelled.
    backend : str, optional
        The teacher backend (:func:`teacher_overrides`); it must agree with label.json.
    folders : mapping of str to (str or Path or None), optional
        The folder options by setting (:func:`teacher_overrides`); each must agree with label.json.
    default_profile : str, optional
        The profile whose values count as not set by the caller (default :data:`DISTILL_PROFILE`).

    Returns
    -------
    dict
        The validated params.

    Raises
    ------
    InputError
        The folder is not an unmodified label output of ``input_dir``, or a value the caller set differs from
        the one label used (naming both).
    """
    record = check_label_folder(labels, input_dir)
    base = load_params_or_profile(None, [], default_profile)
    chosen = teacher_overrides(backend, folders or {})
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
                   folders: Mapping[str, str | Path | None], skip_bad: bool | None = None,
                   max_pixels: int | None = None, bit_depth: str | int | None = None) -> dict:
    """Return the params of a distill project (command and API).

    The teacher from a label folder (:func:`params_from_labels`) or from the teacher options
    (:func:`choose_teacher`), then the data options (:func:`with_data_options`).

    Parameters
    ----------
    params : dict
        Validated params.
    input_dir : str or Path
        The images to train on.
    labels : str or Path or None
        A label output folder of the same images, or None.
    backend : str, optional
        The teacher backend (:func:`teacher_overrides`).
    folders : mapping of str to (str or Path or None)
        The folder options by setting (:func:`teacher_overrides`).
    skip_bad : bool, optional
        True: leave unreadable images out (listed) instead of stopping; None (default) or False: the params'
        ``data.skip_bad`` (:func:`with_data_options`).
    max_pixels : int, optional
        Refuse images above this many pixels (None: the params' value).
    bit_depth : str or int, optional
        Bits a 16-bit frame's sensor fills (None: the params' value).

    Returns
    -------
    dict
        The validated params.

    Raises
    ------
    InputError
        As :func:`params_from_labels`, :func:`choose_teacher` and :func:`with_data_options`.
    """
    if labels is not None:
        params = params_from_labels(params, labels, input_dir, backend, folders)
    else:
        params = choose_teacher(params, backend, folders)
    return with_data_options(params, skip_bad, max_pixels, bit_depth)


def with_data_options(params: dict, skip_bad: bool | None = None, max_pixels: int | None = None,
                      bit_depth: str | int | None = None) -> dict:
    """Return ``params`` with the data options of label and distill applied.

    Parameters
    ----------
    params : dict
        Validated params.
    skip_bad : bool, optional
        True sets ``data.skip_bad`` (``--skip-bad``); None (default) or False keeps the params' value: the
        option never turns it off.
    max_pixels : int, optional
        ``data.max_pixels`` (``--max-pixels``), checked; None keeps the params' value.
    bit_depth : str or int, optional
        ``data.bit_depth`` (``--bit-depth``: auto, 10, 12, 14, 16), checked; None keeps the params' value.

    Returns
    -------
    dict
        The params (the same object when no option is given).

    Raises
    ------
    InputError
        ``max_pixels`` or ``bit_depth`` is invalid, naming the option.
    """
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
          device: str = "auto", skip_bad: bool | None = None, overwrite: bool = False,
          max_pixels: int | None = None, bit_depth: str | int | None = None) -> LabelResult:
    """Pseudo-label the images under ``input`` into ``out`` (``geodistill label``).

    Writes the voted masks (eq:majority-vote) in each of ``formats`` (by default PNG / COCO RLE / YOLO files),
    the table of c, v, a and g per image (eq:foreground-agreement .. eq:reliability-gate) and a contact sheet.
    A teacher is required: ``checkpoint`` (SAM 3), ``backend="imported"`` with ``imported_dir``, or a ``params``
    file naming a real teacher with its settings (:func:`choose_teacher`).  Reruns resume from the teacher cache
    inside ``out``.

    Parameters
    ----------
    input : str or Path
        A folder of images, searched recursively.
    out : str or Path
        The output folder; it must not be ``input`` or inside it.
    checkpoint : str or Path, optional
        A SAM 3 folder (save_pretrained layout); implies ``backend="sam3"``.
    formats : str or sequence of str, optional
        A subset of :data:`~pipeline.labeling.formats.LABEL_FORMATS` (a comma-separated string or a list); None
        (default): its default formats, ``png``, ``coco`` and ``yolo`` unless a registered format says otherwise.
    backend : str, optional
        A backend of :data:`~pipeline.teacher_table.TEACHER_TABLE`: ``sam3``, ``imported`` (masks made
        elsewhere), ``simulated`` (a SIMULATOR of teacher errors that needs ``reference_masks``; its labels are
        not a real teacher's), a registered one or an installed plug-in's name.
    imported_dir : str or Path, optional
        The imported teacher masks (README layout); implies ``backend="imported"``.
    reference_masks : str or Path, optional
        Simulated backend only: masks named like the images, read by the SIMULATOR.
    params : str or Path, optional
        A params file (default: the ``paper`` profile's values).
    overrides : mapping or iterable of str, optional
        ``--set`` items, as ``["teacher.score_threshold=0.3"]`` or ``{"teacher.score_threshold": 0.3}``.
    device : str, optional
        ``auto`` (default), ``cpu`` or ``cuda``: where the teacher runs.
    skip_bad : bool, optional
        True: leave unreadable images out and list them with the reason; None (default) or False: the params'
        ``data.skip_bad`` (the profile's: stop at the first, naming it).
    overwrite : bool, optional
        Write into an existing output folder this command did not make; a file of yours where an output goes
        is refused by name either way.
    max_pixels : int, optional
        Refuse images above this many pixels, read from the file header (None: ``data.max_pixels``).
    bit_depth : str or int, optional
        Bits a 16-bit frame's sensor fills: ``auto``, 10, 12, 14 or 16 (None: ``data.bit_depth``).

    Returns
    -------
    pipeline.labeling.LabelResult
        ``.table`` (c, v, a, g per image), ``.masks`` (image id -> voted mask image file, of the first format
        written that has one, e.g. png; empty when none does), ``.skipped``, ``.out``.

    Raises
    ------
    InputError
        One line naming the keyword or file: no teacher chosen, an invalid option, format or params value, an
        unreadable image (without ``skip_bad``), or an output that belongs to the user.
    """
    fmts = parse_formats(formats)
    p = choose_teacher(effective_params(params, overrides, LABEL_PROFILE), backend,
                       {"checkpoint": checkpoint, "imported_dir": imported_dir})
    p = with_data_options(p, skip_bad, max_pixels, bit_depth)
    return label_folder(input, out, p, device=device, formats=fmts, reference_masks=reference_masks,
                        overwrite=overwrite)


def distill(input: str | Path, *, out: str | Path, val_masks: str | Path | None = None,
            checkpoint: str | Path | None = None, backend: str | None = None,
            imported_dir: str | Path | None = None, params: str | Path | None = None,
            overrides: Mapping | Iterable[str] | None = None, device: str = "auto", run: bool = True,
            skip_bad: bool | None = None, overwrite: bool = False, max_pixels: int | None = None,
            labels: str | Path | None = None, bit_depth: str | int | None = None, benchmark: bool = True,
            time: str | None = None) -> dict:
    """Train a deployable student on the images under ``input`` (``geodistill distill``).

    ``out`` becomes a DVC project running the pipeline's DAG, from the teacher to the deploy bundle and the
    report; rerun to resume.

    Parameters
    ----------
    input : str or Path
        A folder of images, searched recursively.
    out : str or Path
        The project folder (created).
    val_masks : str or Path, optional
        Masks named like some of the images: those become validation/test images (threshold calibration,
        checkpoint choice, report scores).  Without: tau = ``calibrate.fixed_tau`` and the last epoch.
    checkpoint : str or Path, optional
        A SAM 3 folder; implies ``backend="sam3"``.
    backend : str, optional
        ``sam3`` or ``imported``; ``simulated`` is refused (it needs masks of every training image).
    imported_dir : str or Path, optional
        The imported teacher masks; implies ``backend="imported"``.
    params : str or Path, optional
        A params file (default: the ``distill`` profile's values).
    overrides : mapping or iterable of str, optional
        ``--set`` items, as for :func:`label`.
    device : str, optional
        ``auto`` (default), ``cpu`` or ``cuda``.
    run : bool, optional
        False: only write the project (run it later with ``dvc repro`` in ``out``).
    skip_bad : bool, optional
        As for :func:`label`.
    overwrite : bool, optional
        As for :func:`label`.
    max_pixels : int, optional
        As for :func:`label`.
    labels : str or Path, optional
        An unmodified :func:`label` output folder of the same images: its teacher, resolution, vote and gate are
        used and its teacher cache read, so the teacher computes nothing again (no ``checkpoint`` needed).
    bit_depth : str or int, optional
        As for :func:`label`.
    benchmark : bool, optional
        False: no efficiency benchmark stage (``--no-benchmark``).
    time : str, optional
        Stage I's budget, e.g. ``"20m"`` or ``"1h30m"`` (``--time``), converted once on this host into
        ``train.step_budget``; a time that allows the whole run at more epochs raises ``train.epochs_stage1``
        (:func:`pipeline.training.budget.raised_cap`).

    Returns
    -------
    dict of str to Path
        ``deploy``, ``report``, ``thresholds`` and ``checkpoints`` paths inside ``out``.

    Raises
    ------
    InputError
        One line naming the keyword or file: no teacher chosen, an invalid option, a label folder that does not
        match, a failed stage's own error.
    """
    p = distill_params(effective_params(params, overrides, DISTILL_PROFILE), input, labels, backend,
                       {"checkpoint": checkpoint, "imported_dir": imported_dir}, skip_bad, max_pixels, bit_depth)
    p = time_budget_params(p, time, out, device, input, val_masks)
    project = write_project(input, out, p, val_masks=val_masks, overwrite=overwrite, labels=labels,
                            benchmark=benchmark)
    if run:
        run_project(project, device)
    return project_outputs(project)
