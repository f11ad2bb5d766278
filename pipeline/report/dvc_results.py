"""Results where DVC users look for them: short numeric metrics files and per-method plot tables.

``dvc metrics show`` prints one row per metrics file and one column per key found in any file, so
every file here has at most three of the same few keys (``iou``, ``bf1``, ``gate_share``,
``latency_ms``, ``efficiency``) and the table stays six columns wide (under 120 characters) however many
groups and methods a run has:

=====================================================  =============================================
``reports/metrics/students/<group>/<method>.json`` (evaluate)  ``iou``, ``bf1``: mean over seeds of the
                                                       per-seed mean test Image IoU / Boundary F1 at
                                                       the validation-calibrated tau
``reports/metrics/teacher/<group>.json`` (analyze_teacher)     ``iou``, ``bf1``: the teacher's voted
                                                       pseudo-mask (eq:majority-vote) against the
                                                       reference on the group's test images;
                                                       ``gate_share``: share of those images whose
                                                       reliability gate g > 0 (eq:reliability-gate:
                                                       geometry refinement enabled)
``reports/metrics/deploy.json`` (benchmark)                    ``latency_ms``: batch-1 median latency of the
                                                       deployed fast path (the baseline's when no
                                                       variant qualifies), at the benchmark size
``reports/metrics/efficiency/<group>/<method>.json`` (report)  ``efficiency``: the distillation efficiency,
                                                       the students' ``iou`` over the teacher vote's
                                                       on the same test images
                                                       (:func:`distillation_efficiency`)
=====================================================  =============================================

The files are stage outputs with ``cache: false`` outside ``artifacts/``: git tracks them, so
``dvc metrics diff <commit>`` compares against any commit.  Values are rounded to 4 decimals; a
non-finite value is left out (DVC shows ``-``).  Group and method names become path components
(:func:`path_component`).  The detailed numbers (seed std, gains with bootstrap CIs, Spearman rho,
every benchmark variant) stay in summary.parquet, teacher_metrics.parquet and efficiency.parquet; the
efficiency's per-seed interval is the report's (reference-points table: two more keys per file would
widen ``dvc metrics show`` to 145 characters with every method of the catalogue).

Plot tables (evaluate; git-tracked CSVs drawn by the ``method_lines`` template, one line per
method, see :mod:`pipeline.report.offline_plots`): :func:`training_curves` (epoch rows of every run's
training log) and :func:`threshold_curves` (calibrate's validation IoU over the tau grid).

Training logs for DVCLive viewers (train): :func:`write_live_log` writes a run's epoch rows as DVCLive
files (``reports/dvclive/<method>/<seed>``).

The builders are pure functions of tables; :func:`write_metrics_dir`, :func:`write_csv` and
:func:`write_live_log` write.
"""

from __future__ import annotations

import logging
import math
import re
from pathlib import Path
from typing import Any, Iterable, Mapping

import pandas as pd

from pipeline.artifacts.atomic import atomic_path, write_json
from pipeline.methods import BASELINE, PROPOSED, SUPERVISED_CEILING

#: decimals of every metric value (4: a 1e-4 change of a mean IoU is below any effect we report)
DECIMALS = 4
#: decimals of plot table values (curves: finer than a pixel at any plot size)
PLOT_DECIMALS = 6
#: training-log columns copied into the training-curves table (those present)
CURVE_COLUMNS = ("val_iou", "val_bf1", "val_iou_cal", "loss")


def number(value: Any) -> float | None:
    """``value`` rounded to :data:`DECIMALS`, or None when it is missing or not finite."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return round(v, DECIMALS) if math.isfinite(v) else None


def numeric(d: Mapping[str, Any]) -> dict[str, float]:
    """The finite entries of ``d``, rounded (a metrics file holds numbers only)."""
    return {k: n for k, v in d.items() if (n := number(v)) is not None}


def path_component(name: Any) -> str:
    """A group or method name as one safe path component: characters other than letters, digits,
    ``.``, ``_`` and ``-`` become ``_`` (``"KCP"`` -> ``"KCP"``, ``"a/b c"`` -> ``"a_b_c"``)."""
    s = re.sub(r"[^A-Za-z0-9._-]", "_", str(name)).strip(".")
    return s or "_"


def _group_dirs(df: pd.DataFrame) -> dict[tuple, str]:
    """(dataset, group) -> the directory name: the group, or ``<dataset>.<group>`` when a run
    evaluates several datasets (group names need not be unique across datasets)."""
    keys = sorted({(str(d), str(g)) for d, g in zip(df["dataset"], df["group"])}) if "dataset" in df else \
        sorted({("", str(g)) for g in df["group"]})
    several = len({d for d, _ in keys}) > 1
    return {(d, g): path_component(f"{d}.{g}" if several else g) for d, g in keys}


def _dataset_col(df: pd.DataFrame) -> pd.Series:
    return df["dataset"].astype(str) if "dataset" in df else pd.Series([""] * len(df), index=df.index)


# --------------------------------------------------------------------------------------------------
# Metrics
# --------------------------------------------------------------------------------------------------
def student_metric_files(summary: pd.DataFrame) -> dict[str, dict[str, float]]:
    """``{"<group>/<method>.json": {"iou", "bf1"}}`` from evaluate's summary table.

    ``summary``: one row per (dataset, group, method, threshold_mode) with ``iou_mean`` and
    ``bf1_mean`` (mean over seeds of the per-seed test means); only ``threshold_mode ==
    "calibrated"`` rows are used (the deployed rule).  No calibrated row: an empty dict.
    """
    cal = summary[summary["threshold_mode"] == "calibrated"]
    dirs = _group_dirs(cal)
    out: dict[str, dict[str, float]] = {}
    for ds, (_, r) in zip(_dataset_col(cal), cal.iterrows()):
        rel = f"{dirs[(ds, str(r['group']))]}/{path_component(r['method'])}.json"
        out[rel] = numeric({"iou": r.get("iou_mean"), "bf1": r.get("bf1_mean")})
    return out


def teacher_metric_files(teacher_table: pd.DataFrame, gates: pd.DataFrame,
                         split: str = "test") -> dict[str, dict[str, float]]:
    """``{"<group>.json": {"iou", "bf1", "gate_share"}}`` per group of ``split``.

    ``teacher_table``: analyze_teacher's per-image table (columns image_id, dataset, split, group,
    source, iou, bf1); the rows with ``source == "vote"`` are the voted pseudo-masks
    (eq:majority-vote).  ``iou``/``bf1``: their mean over the group's images.  ``gates``: one row per
    image with the reliability gate ``g`` (eq:reliability-gate); ``gate_share`` = share of the
    group's scored images with g > 0 (images without a gate row are left out of the share).
    """
    vote = teacher_table[(teacher_table["source"] == "vote") & (teacher_table["split"] == split)]
    dirs = _group_dirs(vote)
    g = gates.drop_duplicates("image_id").set_index("image_id")["g"]
    out: dict[str, dict] = {}
    for (ds, group), part in vote.groupby([_dataset_col(vote), vote["group"].astype(str)], sort=True):
        gv = part["image_id"].map(g).dropna().to_numpy(float)
        share = float((gv > 0).mean()) if gv.size else None
        out[f"{dirs[(ds, group)]}.json"] = numeric({"iou": part["iou"].mean(), "bf1": part["bf1"].mean(),
                                                    "gate_share": share})
    return out


def distillation_efficiency(student_mean: float, student_std: float, n_seeds: int, vote_iou: float,
                            ci: float = 0.95) -> tuple[float, float, float]:
    """Distillation efficiency = student Image IoU / teacher-vote Image IoU on the same test images:
    (ratio, low, high).

    ``student_mean``/``student_std``: the mean and sample std (ddof 1) over ``n_seeds`` seeds of the
    per-seed mean test Image IoU (evaluate's summary: ``iou_mean``, ``iou_std``); ``vote_iou``: the
    teacher vote's mean Image IoU on the group's test images (analyze_teacher).  The ratio is the
    ratio of the seed mean to the vote.  The vote has no seed (the same pseudo-masks in every run), so
    the per-seed ratios r_s = IoU_s / vote have mean = that ratio and std = student_std / vote, and the
    interval is the per-seed ratio t interval: ratio -+ t_{S-1, (1+ci)/2} std / (vote sqrt(S)).  It
    covers the seeds' training noise on these test images, not the sampling of the images (student and
    vote are scored on the same ones).  One seed, or a vote IoU of 0: the interval is (nan, nan); no
    vote: everything is nan.
    """
    nan = float("nan")
    vote, mean = float(vote_iou), float(student_mean)
    if not (math.isfinite(vote) and math.isfinite(mean)) or vote <= 0:
        return nan, nan, nan
    ratio = mean / vote
    std = float(student_std)
    if int(n_seeds) < 2 or not math.isfinite(std):
        return ratio, nan, nan
    from scipy.special import stdtrit

    half = float(stdtrit(int(n_seeds) - 1, (1.0 + ci) / 2.0)) * std / (vote * math.sqrt(int(n_seeds)))
    return ratio, ratio - half, ratio + half


#: the student's distillation-efficiency targets (docs/student.md): method -> (the ratio it should reach,
#: whether its whole interval must lie above it).  Plain should learn almost all its labels hold, the
#: proposed student should reach its labels, and the ceiling -- trained on reference masks -- should be
#: clearly above them, i.e. its interval's low end above 1.  Printed beside the table, never asserted.
EFFICIENCY_TARGETS: dict[str, tuple[float, bool]] = {BASELINE: (0.95, False), PROPOSED: (1.0, False),
                                                      SUPERVISED_CEILING: (1.0, True)}


def efficiency_target_met(method: str, ratio: float, low: float) -> bool | None:
    """Whether a (method's ratio, interval low end) meets :data:`EFFICIENCY_TARGETS`; None when the method
    has no target or the number it is judged on is not finite (one seed for a target on the interval)."""
    if method not in EFFICIENCY_TARGETS:
        return None
    target, on_interval = EFFICIENCY_TARGETS[method]
    x = low if on_interval else ratio
    return bool(x >= target) if math.isfinite(x) else None


def efficiency_metric_files(summary: pd.DataFrame, vote: Mapping[str, float]) -> dict[str, dict[str, float]]:
    """``{"<group>/<method>.json": {"efficiency"}}``: the :func:`distillation_efficiency` ratio of every
    method (students and the supervised ceiling) at the calibrated tau, for the groups with a vote IoU in
    ``vote`` (group -> teacher-vote Image IoU).  For its own folder (``reports/metrics/efficiency/``,
    written by the report stage): the students' files keep their keys.  The interval is left to the
    report, as the seed std is (module docstring)."""
    cal = summary[summary["threshold_mode"] == "calibrated"]
    dirs = _group_dirs(cal)
    out: dict[str, dict[str, float]] = {}
    for ds, (_, r) in zip(_dataset_col(cal), cal.iterrows()):
        if str(r["group"]) not in vote:
            continue
        e, _, _ = distillation_efficiency(r["iou_mean"], r.get("iou_std"), r.get("n_seeds", 1), vote[str(r["group"])])
        rel = f"{dirs[(ds, str(r['group']))]}/{path_component(r['method'])}.json"
        out[rel] = numeric({"efficiency": e})
    return out


def deploy_metrics(fast_path: Mapping[str, Any] | None, rows: Iterable[Mapping[str, Any]],
                   baseline: str) -> dict[str, float]:
    """``{"latency_ms"}``: the fast path's batch-1 latency (``fast_path`` from
    pipeline.deploy.benchmark.fast_path_summary), else the ``baseline`` variant's row; ``{}`` when
    neither was measured."""
    if fast_path is not None:
        return numeric({"latency_ms": fast_path.get("latency_ms")})
    base = next((r for r in rows if r.get("variant") == baseline), None)
    return numeric({"latency_ms": base.get("latency_ms")}) if base is not None else {}


# --------------------------------------------------------------------------------------------------
# Plot tables
# --------------------------------------------------------------------------------------------------
def training_curves(logs: Iterable[tuple[str, int, pd.DataFrame]]) -> pd.DataFrame:
    """Long table (method, seed, epoch, val_iou, val_bf1, val_iou_cal, loss) of every run's training
    log (``(method, seed, log)`` triples; columns of :data:`CURVE_COLUMNS` that no log has are left
    out), sorted by method, seed and epoch, rounded to :data:`PLOT_DECIMALS`."""
    frames = []
    for method, seed, log in logs:
        cols = [c for c in CURVE_COLUMNS if c in log.columns]
        part = log[["epoch", *cols]].copy()
        part.insert(0, "seed", int(seed))
        part.insert(0, "method", str(method))
        frames.append(part)
    if not frames:
        return pd.DataFrame(columns=["method", "seed", "epoch", *CURVE_COLUMNS])
    df = pd.concat(frames, ignore_index=True)
    df["epoch"] = df["epoch"].astype(int)
    return df.sort_values(["method", "seed", "epoch"], kind="stable").round(PLOT_DECIMALS).reset_index(drop=True)


def threshold_curves(thresholds: pd.DataFrame) -> pd.DataFrame:
    """Long table (method, seed, tau, val_iou) of calibrate's curves: the validation mean Image IoU
    of [P >= tau] (eq:inference-mask) at every ``tau`` of the run's grid (list columns ``grid`` and
    ``curve`` of thresholds.parquet), sorted by method, seed and tau."""
    rows = [{"method": str(r["method"]), "seed": int(r["seed"]), "tau": float(t), "val_iou": float(v)}
            for _, r in thresholds.iterrows() for t, v in zip(r["grid"], r["curve"])]
    df = pd.DataFrame(rows, columns=["method", "seed", "tau", "val_iou"])
    return df.sort_values(["method", "seed", "tau"], kind="stable").round(PLOT_DECIMALS).reset_index(drop=True)


# --------------------------------------------------------------------------------------------------
# Writers
# --------------------------------------------------------------------------------------------------
def write_metrics_dir(directory: str | Path, files: Mapping[str, Mapping[str, float]]) -> Path:
    """Replace ``directory`` atomically by the JSON files ``{relative path: metrics}`` (a stale file of
    a group or method no longer run cannot survive)."""
    with atomic_path(directory, is_dir=True) as tmp:
        for rel, metrics in sorted(files.items()):
            write_json(tmp / rel, dict(metrics))
    return Path(directory)


def write_csv(path: str | Path, table: pd.DataFrame) -> Path:
    """``table`` as CSV (header, no index), atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(table.to_csv(index=False, lineterminator="\n"))
    return Path(path)


#: training-log columns that are not DVCLive metrics (the step, and the schedule's stage number)
LIVE_SKIP = ("epoch", "stage")


def write_live_log(log, directory: str | Path, selected_epoch: int | None = None) -> Path:
    """Log the run's epoch rows with DVCLive into ``directory`` (replaced atomically).

    Step = ``epoch``; every other numeric column of the training log (pipeline.training.loop.LOG_COLUMNS
    minus :data:`LIVE_SKIP`) is a metric, a non-finite value (a loss term the method does not use)
    is left out.  DVCLive writes ``plots/metrics/<column>.tsv`` (step, value) and ``metrics.json``
    (the last epoch's values, plus ``selected_epoch``), without timestamps: the files are
    byte-identical on a rerun.  No DVC experiment is saved and no dvc.yaml written (the DVC stage is
    the experiment; dvc.yaml comes from pipeline/orchestration/dag.py).  DVCLive is imported here only: an optional
    dependency of the train stage.
    """
    from dvclive import Live

    logging.getLogger("dvclive").setLevel(logging.WARNING)  # its INFO line names a random experiment
    columns = [c for c in log.columns if c not in LIVE_SKIP]

    class _StageLive(Live):
        """DVCLive's files without its repository hooks: the DVC stage is the experiment, and
        DVCLive's own git/DVC probing fails in a repository without commits and would ``dvc init``
        a plain git checkout."""

        def _init_dvc(self):
            self._dvc_file = self._init_dvc_file()

    with atomic_path(directory, is_dir=True) as tmp:
        live = _StageLive(str(tmp), save_dvc_exp=False, dvcyaml=False, report=None)
        for row in log.to_dict("records"):
            live.step = int(row["epoch"])
            for name in columns:
                v = row[name]
                if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
                    live.log_metric(name, float(v))
        if selected_epoch is not None:
            live.summary["selected_epoch"] = int(selected_epoch)
        live.make_summary()
    return Path(directory)
