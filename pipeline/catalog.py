"""The catalogue: every artifact, output file and stage, written once; dvc.yaml is rendered from it.

An artifact has its file name, schema and producing stage; a stage its script, what it reads and writes and its
params keys.  Paths are relative to ``ARTIFACTS_DIR``; those starting ``../`` lie outside it and are git-tracked
DVC outs (``cache: false``).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Mapping

from pipeline.params import DEFAULT_PARAMS as PARAMS_FILE
from pipeline.params import Params, get_path

__all__ = ["PARAMS_FILE", "ARTIFACTS_DIR", "WEIGHTS_FILE", "WEIGHTS_CONFIG_FILE", "LEGACY_WEIGHTS_FILE",
           "TRAINING_LOG_FILE", "META_FILE", "RESUME_STATE_FILE", "DVC_FILE", "path", "dvc_path", "OutputFile",
           "bundle_file", "OUTPUT_FILES", "output_file", "output_names", "Schema", "ARTIFACTS", "StageSpec", "STAGES",
           "EXTRA_PATHS", "PLOT_TEMPLATE", "PLOTS", "stage_params"]

ARTIFACTS_DIR = "artifacts"

#: a model's tensors as safetensors (nothing in it can execute on load), and its config as JSON
WEIGHTS_FILE = "model.safetensors"
WEIGHTS_CONFIG_FILE = "model.json"
#: the torch-pickle weights file older runs wrote; still read, never written
LEGACY_WEIGHTS_FILE = "model.pt"
TRAINING_LOG_FILE = "log.parquet"
META_FILE = "meta.json"
RESUME_STATE_FILE = "state.pt"
DVC_FILE = "dvc.yaml"


def path(name: str, root: str | Path = ARTIFACTS_DIR, **fmt) -> Path:
    """Locate artifact ``name`` under ``root``.

    Parameters
    ----------
    name : str
        An :data:`ARTIFACTS` key.
    root : str or Path, optional
        The artifacts folder (default :data:`ARTIFACTS_DIR`); a path starting ``../`` resolves beside it.
    **fmt
        Values of the path's placeholders (``method``, ``seed``, ``profile``); none: the path keeps them.

    Returns
    -------
    Path
        The artifact's path.

    Raises
    ------
    KeyError
        ``name`` is not in :data:`ARTIFACTS`, or ``fmt`` lacks one of the path's placeholders.
    """
    rel = ARTIFACTS[name].path.format(**fmt) if fmt else ARTIFACTS[name].path
    return Path(root) / rel if not rel.startswith("../") else Path(root).parent / rel[3:]


def dvc_path(name: str, **fmt) -> str:
    """Spell artifact ``name``'s path as dvc.yaml does: under :data:`ARTIFACTS_DIR`, posix.

    Parameters
    ----------
    name : str
        An :data:`ARTIFACTS` key.
    **fmt
        Values of the path's placeholders, as for :func:`path`; DVC templates (``${...}``) stay templates.

    Returns
    -------
    str
        The posix path.
    """
    return path(name, ARTIFACTS_DIR, **fmt).as_posix()


@dataclasses.dataclass(frozen=True)
class OutputFile:
    """One file or folder in an output folder or in the deploy bundle.

    Attributes
    ----------
    key : str
        Its key in its folder's table.
    name : str
        Its file name; ``{...}`` in it is filled by the writer.
    written_by : str
        The dotted name of the module or function that writes it.
    description : str
        What it holds ("": nothing to add to the name).
    required : bool
        Bundle files: every bundle has it; False: only when the export could write it.
    """

    key: str
    name: str
    written_by: str
    description: str = ""
    required: bool = True


DEPLOY_BUNDLE: dict[str, OutputFile] = {f.key: f for f in [
    OutputFile("weights", WEIGHTS_FILE, "pipeline.artifacts.weights.write_weights",
               "mask-path tensors (a checkpoint's format: pipeline.evaluation.inference.load_student opens a "
               f"bundle too; bundles of older versions hold {LEGACY_WEIGHTS_FILE} instead, still read)"),
    OutputFile("weights_config", WEIGHTS_CONFIG_FILE, "pipeline.artifacts.weights.write_weights",
               "model config, method, seed, tau, resolution"),
    OutputFile("torchscript", "model.ts", "pipeline.deploy.mask_path.export_torchscript",
               "TorchScript (traced) mask path; shape-generic (any batch and size)"),
    OutputFile("onnx", "model.onnx", "pipeline.deploy.mask_path.export_onnx",
               "ONNX mask path, dynamic batch/height/width (only when onnx + onnxruntime import)", required=False),
    OutputFile("int8", "model.int8.onnx", "pipeline.deploy.quantize.quantize_onnx_int8",
               "static int8 (QDQ) quantisation of the ONNX model, calibrated on training-split images (only "
               "when the ONNX model exists and training images are given)", required=False),
    OutputFile("deploy_json", "deploy.json", "pipeline.deploy.bundle.write_bundle",
               "tau and its source, working resolution, config, parity, file sha256s, source checkpoint "
               "(pipeline.deploy.bundle.read_deploy_info: every reader)"),
    # bundles of older versions have no contract: not required
    OutputFile("contract", "contract.json", "pipeline.deploy.bundle.write_contract",
               "the written input/output contract for software that runs the ONNX model without this project: "
               "frame reading, size, channel order, normalisation, dtype, tau, output meaning, confidence, "
               "the golden pair and its tolerance", required=False),
    OutputFile("golden_input", "golden_input.npy", "pipeline.deploy.bundle.write_contract",
               "a golden model input: one RGB uint8 frame [R,R,3] at the working resolution", required=False),
    OutputFile("golden_probs", "golden_probs.npy", "pipeline.deploy.bundle.write_contract",
               "the golden output: P = sigmoid(Z) float32 [R,R] of the golden input (PyTorch fp32, CPU)",
               required=False),
    OutputFile("golden_mask", "golden_mask.npy", "pipeline.deploy.bundle.write_contract",
               "the golden mask [P >= tau], bool [R,R]", required=False),
]}


def bundle_file(key: str) -> str:
    """Return the file name of deploy bundle file ``key``.

    Parameters
    ----------
    key : str
        A :data:`DEPLOY_BUNDLE` key (``"weights"``, ``"onnx"``, ...).

    Returns
    -------
    str
        Its file name.

    Raises
    ------
    KeyError
        ``key`` is not in the bundle table.
    """
    return DEPLOY_BUNDLE[key].name


def _files(written_by: str, *rows: tuple[str, ...]) -> dict[str, OutputFile]:
    """Build the table of one output folder, all written by ``written_by``: rows of (key, name[, description])."""
    return {key: OutputFile(key, name, written_by, *desc) for key, name, *desc in rows}


#: one row per input left out, with the reason (label and segment)
SKIPPED_FILE = "skipped.csv"

#: the files and folders of each output folder, keyed by an artifact's name or a command's
OUTPUT_FILES: dict[str, dict[str, OutputFile]] = {
    "synthetic_files": _files(
        "pipeline.datasets.build", ("readme", "README.txt", "why no synthetic files were generated")),
    "report": _files(
        "stages.report", ("markdown", "report.md"), ("html", "report.html", "self-contained (figures inlined)"),
        ("environment", "environment.json", "host, libraries and the runs' records"),
        ("figures", "figures", "the figures below, PNG and SVG"),
        ("plots", "plots", "the figures' data as CSV: <name>.csv")),
    "report_figures": _files("pipeline.report.build", *((k, f"{k}.png") for k in (
        "threshold_curves", "reliability", "area_vs_tau", "training_curves_calibrated", "training_curves",
        "qualitative", "student_vs_pseudo_labels", "gate_distribution", "training_loss", "pseudo_targets"))),
    "run_logs": _files(
        "pipeline.cluster.driver", ("timeline", "timeline.json", "each stage's start, end and status"),
        ("stage_log", "{stage}.log", "a stage's stdout and stderr")),
    "project": _files(  # a standalone project (geodistill distill)
        "pipeline.orchestration.standalone.write_project", ("params", PARAMS_FILE), ("dvc", DVC_FILE),
        ("protocol", "folder_protocol.yaml", "the input folder's split"),
        ("record", "distill.json", "distill's record (pipeline.artifacts.ownership)")),
    "label": _files(
        "pipeline.labeling.writing", ("masks", "masks", "masks/<image_id>.png"), ("coco", "coco.json"),
        ("yolo", "yolo", "the YOLO dataset (label_yolo)"),
        ("table", "labels.parquet", "one row per image: the gate inputs and the gate"),
        ("csv", "labels.csv", "the table as CSV"), ("sheet", "contact_sheet.png"),
        ("record", "label.json", "label's record (pipeline.artifacts.ownership)"), ("skipped", SKIPPED_FILE)),
    "label_yolo": _files(
        "pipeline.labeling.writing", ("train", "train.txt", "training image list"),
        ("val", "val.txt", "validation image list (2 images or more)"), ("data", "data.yaml"),
        ("readme", "README.txt")),
    "review": _files(
        "pipeline.review.export", ("record", "review.json", "review export's record (pipeline.artifacts.ownership)"),
        ("csv", "ranked.csv"), ("labelstudio", "labelstudio"), ("cvat", "cvat"),
        ("ls_tasks", "tasks.json", "in labelstudio/"), ("ls_config", "label_config.xml", "in labelstudio/"),
        ("cvat_coco", "instances_default.json", "in cvat/")),
    "segment": _files(  # <out>/<the input's relative path without its suffix><suffix> per image
        "pipeline.deploy.image_files", ("mask", ".mask.png", "suffix of each input's mask"),
        ("prob", ".prob.png", "suffix of each input's probability map (--save-prob)"),
        ("overlay", ".overlay.png", "suffix of each input's overlay (--overlay)"), ("skipped", SKIPPED_FILE),
        ("confidence", "confidence.csv", "one row per mask: its path and the frame's confidence"),
        ("record", "segment.json", "segment's record (pipeline.artifacts.ownership)")),
}


def output_file(folder: str, key: str) -> str:
    """Return the name of file ``key`` in output folder ``folder``.

    Parameters
    ----------
    folder : str
        An :data:`OUTPUT_FILES` key (an artifact's name or a command's).
    key : str
        The file's key in that folder.

    Returns
    -------
    str
        Its file name (a suffix, for segment's per-image files).

    Raises
    ------
    KeyError
        ``folder`` or ``key`` is not in the table.
    """
    return OUTPUT_FILES[folder][key].name


def output_names(folder: str, *keys: str) -> dict[str, str]:
    """Map the keys of output folder ``folder`` to their file names.

    Parameters
    ----------
    folder : str
        An :data:`OUTPUT_FILES` key.
    *keys : str
        The keys wanted; none: all of the folder's.

    Returns
    -------
    dict[str, str]
        ``{key: name}`` in the table's order; a key not in the folder is left out.

    Raises
    ------
    KeyError
        ``folder`` is not in the table.
    """
    return {k: f.name for k, f in OUTPUT_FILES[folder].items() if not keys or k in keys}


@dataclasses.dataclass(frozen=True)
class Schema:
    """What an artifact must hold: Zarr arrays, Parquet columns or a folder's files.

    Attributes
    ----------
    kind : str
        The storage: ``"zarr"``, ``"parquet"`` or ``"dir"``.
    version : int
        The schema's version, recorded in each artifact's :class:`pipeline.artifacts.lineage.Meta`.
    arrays : Mapping[str, tuple[str, int]]
        Zarr: array name -> (numpy dtype kind, ndim), each required.
    optional : Mapping[str, tuple[str, int]]
        Zarr: the arrays that may be absent, likewise.
    columns : tuple[str, ...]
        Parquet: the required columns.
    files : tuple[str, ...]
        Folder: the required files (``"a|b"``: either).
    """

    kind: str  # "zarr" | "parquet" | "dir"
    version: int = 1
    arrays: Mapping[str, tuple[str, int]] = dataclasses.field(default_factory=dict)
    optional: Mapping[str, tuple[str, int]] = dataclasses.field(default_factory=dict)
    columns: tuple[str, ...] = ()
    files: tuple[str, ...] = ()


def _table(*columns: str, version: int = 1) -> Schema:
    return Schema("parquet", version, columns=columns)


def _zarr(optional: Mapping[str, tuple[str, int]] | None = None, **arrays: tuple[str, int]) -> Schema:
    return Schema("zarr", arrays=arrays, optional=optional or {})


def _folder(*files: str) -> Schema:
    return Schema("dir", files=files)


@dataclasses.dataclass(frozen=True)
class ArtifactSpec:
    """One artifact of the catalogue: where it lives, its schema and the stage that writes it."""

    name: str
    path: str              # relative to the artifacts directory ("../" for outside it)
    schema: Schema | None  # the schema named like the artifact (None: a plain file or folder)
    stage: str             # the producing stage
    description: str = ""


_a = ArtifactSpec
#: a model's weights: safetensors, or the torch pickle of older runs (pipeline.artifacts.weights)
_WEIGHTS = f"{WEIGHTS_FILE}|{LEGACY_WEIGHTS_FILE}"

ARTIFACTS: dict[str, ArtifactSpec] = {a.name: a for a in [
    _a("manifest", "manifest.parquet", _table(
        "image_id", "dataset", "domain", "split", "group", "spacecraft", "image_path", "mask_path", "part_path",
        "width", "height", "sha256"), "prepare", "one row per image: split, group, paths, sha256"),
    _a("images", "images.zarr", _zarr(image=("u", 4)), "prepare", "uint8 [N,H,W,3] at the working resolution"),
    _a("reference", "reference.zarr", _zarr({"parts": ("u", 3)}, mask=("b", 3), has_mask=("b", 1)), "prepare",
       "manual masks: selection, calibration and evaluation ONLY (never a loss of an annotation-free method)"),
    _a("skipped_files", "skipped_files.parquet", _table("path", "reason"), "prepare",
       "files left out, with the reason"),
    _a("contact_sheet", "figures/contact_sheet.png", None, "prepare"),
    _a("synthetic_files", "synthetic", None, "prepare", "synthetic benchmark PNGs the manifest points at"),
    _a("teacher", "teacher.zarr", _zarr({"vflip_masks": ("b", 3), "vflip_scores": ("f", 1)}, masks=("b", 4),
                                       scores=("f", 2)), "teacher", "masks [N,K,H,W], scores [N,K]"),
    _a("teacher_scores", "teacher_scores.parquet", _table(
        "image_id", "prompt_index", "prompt", "score", "valid", "mask_area"), "teacher"),
    _a("consensus", "consensus.zarr", _zarr({"h": ("f", 1)}, agreement=("f", 3), voted=("b", 3), n_valid=("i", 1)),
       "consensus", "agreement, voted, n_valid, h (prompt disagreement)"),
    _a("geometry", "geometry.zarr", _zarr(sdf=("f", 3), skeleton=("b", 3)), "geometry", "sdf, skeleton"),
    _a("gates", "gates.parquet", _table(
        "image_id", "split", "c", "v", "a", "a0", "g_conf", "g_valid", "g_area", "g", "n_valid"), "geometry",
       "c, v, a, a0, g_conf, g_valid, g_area, g"),
    _a("checkpoints", "checkpoints", None, "train", "all runs: checkpoints/<method>/<seed>/"),
    _a("checkpoint", "checkpoints/{method}/{seed}", _folder(_WEIGHTS, TRAINING_LOG_FILE), "train",
       "one (method, seed) run"),
    _a("training_log", f"checkpoints/{{method}}/{{seed}}/{TRAINING_LOG_FILE}",
       _table("epoch", "stage", "loss", "val_iou", "val_bf1", "lr", version=2), "train", "the run's per-epoch log"),
    _a("train_live", "../reports/dvclive/{method}/{seed}", None, "train",
       "DVCLive log of the run's epoch rows (metrics.json, plots/metrics/*.tsv): a git-tracked DVC out"),
    _a("train_timings", "timings/train/{method}/{seed}.json", None, "train",
       "per-epoch wall-clock seconds: NOT a DVC out and not fingerprinted (checkpoints stay byte-identical)"),
    _a("noise_floor", "../reports/noise_floor.json", None, "stability benchmark",
       "perturbation and seed spreads of the published numbers, one record per configuration "
       "({recipes: {key: record}}; python -m benchmarks.stability --noise-floor adds or replaces "
       "its own); the report applies the record measured in its own configuration when there is one: a "
       "DVC dep of report in this repository's DAG (not a DVC out: the benchmark writes it)"),
    _a("run_logs", "logs/run", None, "run",
       "`geodistill run`: <stage>.log (stdout+stderr) per stage and timeline.json; NOT a DVC out"),
    _a("thresholds", "thresholds.parquet", _table("method", "seed", "tau", "val_iou"), "calibrate"),
    _a("metrics", "metrics.parquet", _table(
        "dataset", "group", "method", "seed", "image_id", "threshold_mode", "tau", "iou", "bf1", "precision", "recall",
        "area_ratio"), "evaluate", "per image, calibrated and fixed tau"),
    _a("summary", "summary.parquet", _table(
        "dataset", "group", "method", "threshold_mode", "n_seeds", "n_images", "iou_mean", "iou_std", "bf1_mean",
        "bf1_std"), "evaluate"),
    _a("metrics_students", "../reports/metrics/students", None, "evaluate",
       "DVC metrics (git-tracked): <group>/<method>.json = iou, bf1 at the calibrated tau "
       "(pipeline.report.dvc_results)"),
    _a("plot_training_curves", "../reports/plots/training_curves.csv", None, "evaluate",
       "DVC plot (git-tracked): method, seed, epoch, val_iou, ... of every run's training log"),
    _a("plot_threshold_curves", "../reports/plots/threshold_curves.csv", None, "evaluate",
       "DVC plot (git-tracked): method, seed, tau, val_iou of calibrate's curves"),
    _a("teacher_metrics", "teacher_metrics.parquet", _table(
        "image_id", "group", "source", "iou", "bf1", "precision", "recall"), "analyze_teacher"),
    _a("metrics_teacher", "../reports/metrics/teacher", None, "analyze_teacher",
       "DVC metrics (git-tracked): <group>.json = the vote's iou, bf1 and the gate_share g > 0"),
    _a("deploy", "deploy", _folder(_WEIGHTS, *(f.name for k, f in DEPLOY_BUNDLE.items()
                                           if f.required and k not in ("weights", "weights_config"))),
       "export", "exported mask path (TorchScript, ONNX, int8, tau)"),
    _a("efficiency", "efficiency.parquet", _table(
        "variant", "params", "gflops", "latency_ms", "throughput", "peak_mb"), "benchmark"),
    _a("metrics_deploy", "../reports/metrics/deploy.json", None, "benchmark",
       "DVC metrics (git-tracked): latency_ms of the deployed fast path"),
    _a("report", "../reports/{profile}", _folder(output_file("report", "markdown"), output_file("report", "html")),
       "report", "report.md, report.html, figures, plots"),
    _a("metrics_efficiency", "../reports/metrics/efficiency", None, "report",
       "DVC metrics (git-tracked): <group>/<method>.json = distillation efficiency (test Image IoU / the "
       "teacher vote's) and its interval at the calibrated tau (pipeline.report.dvc_results.efficiency_metric_files)"),
    _a("corrections", "corrections.parquet", _table(
        "image_id", "file", "width", "height", "rle", "pixels", "source"), "review import",
       "masks a person corrected (geodistill review import; compressed COCO RLE at each image's own size): "
       "manual masks, never a loss of an annotation-free method; the corrections stage's dep when params "
       "review.corrections names it"),
    _a("corrected", "corrected.zarr", _zarr(mask=("b", 3), row=("i", 1)), "corrections",
       "the corrections checked against this run and at the working resolution, for review.mode (validate: "
       "validation masks; replace: training targets, NOT annotation-free); only when review.corrections is set"),
    _a("review", "review", None, "review_export",
       "the training images a person should check first (review.top, ranked by review.ranking): ranked.csv, "
       "labelstudio/, cvat/ and review.json, as geodistill review export writes them"),
]}


@dataclasses.dataclass(frozen=True)
class StageSpec:
    """One DVC stage: the command ``python -m <module> <args>``, what it reads and writes and its params.

    Attributes
    ----------
    name : str
        The stage's name in dvc.yaml.
    module : str
        The stage script's module (``stages.<name>``).
    args : str
        Its arguments, with ``{artifact}`` placeholders (:data:`ARTIFACTS` keys or :data:`EXTRA_PATHS`).
    deps : tuple[str, ...]
        The artifacts it reads.
    outs : tuple[str, ...]
        The artifacts it writes.
    params : tuple[str, ...]
        The dotted params keys DVC tracks and the artifacts' fingerprint holds.
    data_deps : tuple[str, ...]
        Deps that are no artifact: paths or params templates.
    metrics : tuple[str, ...]
        The artifacts it writes as DVC metrics (git-tracked, uncached).
    exclusive : bool
        It measures wall time: ``geodistill run`` runs it with nothing beside it.
    """

    name: str
    module: str
    args: str
    deps: tuple[str, ...]
    outs: tuple[str, ...]
    params: tuple[str, ...]
    data_deps: tuple[str, ...] = ()
    metrics: tuple[str, ...] = ()
    exclusive: bool = False  # it measures wall time: `geodistill run` runs it with nothing beside it


def _keys(section: str, *names: str, but: tuple[str, ...] = ()) -> tuple[str, ...]:
    """List the dotted keys of ``names`` in params ``section``; none named: of all its fields but ``but``."""
    names = names or tuple(k for k in Params.model_fields[section].annotation.model_fields if k not in but)
    return tuple(f"{section}.{n}" for n in names)


STAGES: dict[str, StageSpec] = {s.name: s for s in [
    StageSpec("prepare", "stages.prepare", "--out-dir {artifacts_dir}", (),
              ("manifest", "images", "reference", "skipped_files", "contact_sheet", "synthetic_files"),
              _keys("data", but=("cache_dir",)), data_deps=("data_manifests",)),
    StageSpec("teacher", "stages.teacher",
              "--manifest {manifest} --images {images} --reference {reference} --out {teacher} "
              "--scores {teacher_scores}",
              ("manifest", "images", "reference"), ("teacher", "teacher_scores"),
              _keys("teacher", but=("batch_size", "compile", "cache_dir", "options"))),  # speed, cache; options: when set
    StageSpec("consensus", "stages.consensus", "--teacher {teacher} --out {consensus}",
              ("teacher",), ("consensus",), _keys("consensus", "vote_threshold")),
    StageSpec("geometry", "stages.geometry",
              "--consensus {consensus} --manifest {manifest} --out {geometry} --gates {gates}",
              ("consensus", "manifest"), ("geometry", "gates"), _keys("geometry")),
    # train_<method>: rendered per method (pipeline.orchestration.dag.train_stage)
    StageSpec("calibrate", "stages.calibrate",
              "--artifacts {artifacts_dir} --checkpoints {checkpoints} --out {thresholds}",
              ("manifest", "images", "reference", "checkpoints"), ("thresholds",),
              _keys("calibrate") + ("train.recipe",)),
    StageSpec("evaluate", "stages.evaluate",
              "--artifacts {artifacts_dir} --checkpoints {checkpoints} --thresholds {thresholds} "
              "--out {metrics} --summary {summary} --metrics-dir {metrics_students} "
              "--training-curves {plot_training_curves} --threshold-curves {plot_threshold_curves}",
              ("manifest", "images", "reference", "checkpoints", "thresholds"),
              ("metrics", "summary", "plot_training_curves", "plot_threshold_curves"),
              _keys("evaluate"), metrics=("metrics_students",)),
    StageSpec("analyze_teacher", "stages.analyze_teacher",
              "--artifacts {artifacts_dir} --out {teacher_metrics} --metrics-dir {metrics_teacher}",
              ("manifest", "reference", "teacher", "consensus", "gates"), ("teacher_metrics",),
              _keys("evaluate", "bf1_tolerance", "small_region_max_fraction"), metrics=("metrics_teacher",)),
    StageSpec("export", "stages.export",
              "--checkpoint {export_checkpoint} --thresholds {thresholds} --artifacts {artifacts_dir} --out {deploy}",
              ("export_checkpoint", "thresholds", "manifest", "images"), ("deploy",),
              _keys("deploy", "export_method", "export_seed", "opset", "parity_atol", "int8_calibration_images",
                    "int8_calibration", "int8_percentile", "int8_weight_bits", "int8_min_mask_iou")
              + ("calibrate.fixed_tau", "data.resolution", "data.bit_depth", "data.letterbox")),
    StageSpec("benchmark", "stages.benchmark",
              "--deploy {deploy} --artifacts {artifacts_dir} --out {efficiency} --metrics-json {metrics_deploy}",
              ("deploy", "manifest", "images", "reference"), ("efficiency",),
              _keys("deploy", "opset", "benchmark_warmup", "benchmark_iters", "benchmark_batches",
                    "benchmark_resolution", "benchmark_variants", "int8_calibration_images", "target_latency_ms",
                    "target_resolution", "target_iou_drop") + ("calibrate.fixed_tau", "data.resolution"),
              metrics=("metrics_deploy",), exclusive=True),
    StageSpec("report", "stages.report",
              "--artifacts {artifacts_dir} --out {report} --metrics-dir {metrics_efficiency}",
              ("manifest", "images", "reference", "teacher", "consensus", "geometry", "gates", "checkpoints",
               "thresholds", "metrics", "summary", "teacher_metrics", "efficiency"), ("report",),
              ("profile",) + _keys("report"),
              # a new floor changes the report's verdicts
              data_deps=(dvc_path("noise_floor"),), metrics=("metrics_efficiency",)),
    # in dvc.yaml only when params review.corrections is set (pipeline.orchestration.dag.OPTIONAL_STAGES)
    StageSpec("corrections", "stages.corrections",
              "--corrections ${review.corrections} --artifacts {artifacts_dir} --out {corrected}",
              ("manifest", "images"), ("corrected",), _keys("review", "corrections", "mode") + ("data.source",),
              data_deps=("${review.corrections}",)),
    StageSpec("review_export", "stages.review_export", "--artifacts {artifacts_dir} --out {review}",
              ("manifest", "consensus", "gates"), ("review",),
              _keys("review", "top", "ranking") + ("data.letterbox", "teacher.backend")),
]}

#: the path placeholders of stage commands that are not single artifacts
EXTRA_PATHS = {
    "artifacts_dir": ARTIFACTS_DIR,
    "export_checkpoint": f"{ARTIFACTS_DIR}/checkpoints/${{deploy.export_method}}/${{deploy.export_seed}}",
}


#: the Vega-Lite template of every plot below (pipeline.report.offline_plots): one line per method
PLOT_TEMPLATE = "method_lines"


@dataclasses.dataclass(frozen=True)
class PlotSpec:
    """One top-level plot of dvc.yaml: ``y`` of artifact ``data`` (a CSV with a ``method`` column) against ``x``."""

    name: str
    data: str
    x: str
    y: str
    title: str
    x_label: str
    y_label: str


PLOTS: tuple[PlotSpec, ...] = (
    PlotSpec("training_curves", "plot_training_curves", "epoch", "val_iou",
             "Validation Image IoU during training (tau 0.5, mean over seeds)", "epoch of the run's own schedule",
             "val Image IoU"),
    PlotSpec("threshold_curves", "plot_threshold_curves", "tau", "val_iou",
             "Validation Image IoU of [P >= tau] (calibration curve, mean over seeds)", "tau", "val Image IoU"),
)


def stage_params(params: dict, keys) -> dict:
    """Pick the values of ``keys`` from validated params: what a stage fingerprints.

    Parameters
    ----------
    params : dict
        Validated params, as nested mappings.
    keys : Iterable[str]
        Dotted keys (a :class:`StageSpec`'s ``params``).

    Returns
    -------
    dict
        ``{dotted key: value}`` in ``keys``' order.

    Raises
    ------
    KeyError
        A key is not in ``params``.
    """
    return {k: get_path(params, k) for k in keys}
