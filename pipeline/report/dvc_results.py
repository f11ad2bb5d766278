"""Results where DVC users look for them (docs/pipeline.md).

Short numeric metrics files (a few shared keys each, so ``dvc metrics show`` stays narrow), per-method plot
tables and DVCLive training logs.
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
from pipeline.params import PAPER

__all__ = ["path_component", "student_metric_files", "teacher_metric_files", "seed_ratio", "distillation_efficiency",
           "EFFICIENCY_TARGETS", "efficiency_target_met", "efficiency_metric_files", "deploy_metrics",
           "training_curves", "threshold_curves", "write_metrics_dir", "write_csv", "write_live_log"]

DECIMALS = 4  # a 1e-4 change of a mean IoU is below any effect we report
PLOT_DECIMALS = 6  # finer than a pixel at any plot size
CURVE_COLUMNS = ("val_iou", "val_bf1", "val_iou_cal", "loss")


def number(value: Any) -> float | None:
    """Round ``value`` to :data:`DECIMALS`; None when it is missing or not finite."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return round(v, DECIMALS) if math.isfinite(v) else None


def numeric(d: Mapping[str, Any]) -> dict[str, float]:
    """Keep the finite entries of ``d``, rounded (a metrics file holds numbers only)."""
    return {k: n for k, v in d.items() if (n := number(v)) is not None}


def path_component(name: Any) -> str:
    """Turn a group or method name into one safe path component (``"a/b c"`` -> ``"a_b_c"``).

    Parameters
    ----------
    name : object
        The name (its ``str``).

    Returns
    -------
    str
        Letters, digits, ``.``, ``_`` and ``-`` only, no leading or trailing dot; ``"_"`` when nothing is left.
    """
    s = re.sub(r"[^A-Za-z0-9._-]", "_", str(name)).strip(".")
    return s or "_"


def _group_dirs(df: pd.DataFrame) -> dict[tuple, str]:
    """Map (dataset, group) to the group's folder: ``<dataset>.<group>`` when a run evaluates several datasets."""
    keys = sorted(set(zip(_dataset_col(df), df["group"].astype(str))))
    several = len({d for d, _ in keys}) > 1
    return {(d, g): path_component(f"{d}.{g}" if several else g) for d, g in keys}


def _dataset_col(df: pd.DataFrame) -> pd.Series:
    """Return ``df``'s dataset column as strings ("" for every row when it has none)."""
    return df["dataset"].astype(str) if "dataset" in df else pd.Series([""] * len(df), index=df.index)


def _calibrated_files(summary: pd.DataFrame, values) -> dict[str, dict[str, float]]:
    """Map ``"<group>/<method>.json"`` to ``values(row)`` for the calibrated rows (the deployed rule); None skips."""
    cal = summary[summary["threshold_mode"] == "calibrated"]
    dirs = _group_dirs(cal)
    out: dict[str, dict[str, float]] = {}
    for ds, (_, r) in zip(_dataset_col(cal), cal.iterrows()):
        if (v := values(r)) is not None:
            out[f"{dirs[(ds, str(r['group']))]}/{path_component(r['method'])}.json"] = numeric(v)
    return out


def student_metric_files(summary: pd.DataFrame) -> dict[str, dict[str, float]]:
    """Make the students' metrics files: the seed means of Image IoU and Boundary F1 at the calibrated tau.

    Parameters
    ----------
    summary : pandas.DataFrame
        The seed summary (``summary.parquet``): ``group``, ``method``, ``threshold_mode``, ``iou_mean``,
        ``bf1_mean`` (and ``dataset`` where several).

    Returns
    -------
    dict
        ``{"<group>/<method>.json": {"iou": ..., "bf1": ...}}``, finite values only, rounded to :data:`DECIMALS`.
    """
    return _calibrated_files(summary, lambda r: {"iou": r.get("iou_mean"), "bf1": r.get("bf1_mean")})


def teacher_metric_files(teacher_table: pd.DataFrame, gates: pd.DataFrame,
                         split: str = "test") -> dict[str, dict[str, float]]:
    """Make the teacher's metrics files: per group of ``split``, the vote's mean scores and gate share.

    The voted pseudo-masks' (eq:majority-vote) mean Image IoU and Boundary F1, and the share of the group's
    images with g > 0 (eq:reliability-gate).

    Parameters
    ----------
    teacher_table : pandas.DataFrame
        The teacher table (``teacher_metrics.parquet``); its ``vote`` rows are used.
    gates : pandas.DataFrame
        The gates table (``gates.parquet``): ``image_id`` and ``g``.
    split : str
        The split scored.

    Returns
    -------
    dict
        ``{"<group>.json": {"iou", "bf1", "gate_share"}}``, finite values only (no gate share without gates).
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


def seed_ratio(mean: float, std: float, n: int, ref_mean: float, ref_std: float = 0.0, ref_n: int | None = None,
               ci: float = PAPER.evaluate.ci) -> tuple[float, float, float]:
    """Divide two seed means, with the delta-method t interval of the ratio.

    r = mean / ref_mean, and the interval
    r -+ t_{d, (1+ci)/2} sqrt(std^2 / n + r^2 ref_std^2 / ref_n) / ref_mean, with d = min(n, ref_n) - 1.
    A reference without seeds (``ref_n`` None, e.g. the teacher vote) adds no variance.

    Parameters
    ----------
    mean, std : float
        The numerator's seed mean and seed standard deviation (ddof 1).
    n : int
        Its number of seeds.
    ref_mean, ref_std : float
        The denominator's mean and seed standard deviation.
    ref_n : int, optional
        The denominator's number of seeds; None: a reference without seeds.
    ci : float
        The interval's coverage (default ``evaluate.ci``).

    Returns
    -------
    tuple of float
        (ratio, low, high); all NaN unless both means are finite and ``ref_mean`` > 0; NaN bounds below 2 seeds
        (d < 1) or with a non-finite std.
    """
    nan = float("nan")
    ref, mean = float(ref_mean), float(mean)
    if not (math.isfinite(ref) and math.isfinite(mean)) or ref <= 0:
        return nan, nan, nan
    ratio = mean / ref
    dof = min(int(n), int(ref_n) if ref_n is not None else int(n)) - 1
    if dof < 1 or not math.isfinite(float(std)) or (ref_n is not None and not math.isfinite(float(ref_std))):
        return ratio, nan, nan
    from scipy.special import stdtrit

    var = float(std) ** 2 / int(n) + (ratio ** 2 * float(ref_std) ** 2 / int(ref_n) if ref_n is not None else 0.0)
    half = float(stdtrit(dof, (1.0 + ci) / 2.0)) * math.sqrt(var) / ref
    return ratio, ratio - half, ratio + half


def distillation_efficiency(student_mean: float, student_std: float, n_seeds: int, vote_iou: float,
                            ci: float = PAPER.evaluate.ci) -> tuple[float, float, float]:
    """Compute the distillation efficiency: student Image IoU / teacher-vote Image IoU, with its interval.

    :func:`seed_ratio` against the vote, which has no seed.

    Parameters
    ----------
    student_mean, student_std : float
        The student's seed mean and seed standard deviation of Image IoU.
    n_seeds : int
        The student's number of seeds.
    vote_iou : float
        The teacher vote's Image IoU (eq:majority-vote) on the same images.
    ci : float
        The interval's coverage (default ``evaluate.ci``).

    Returns
    -------
    tuple of float
        (ratio, low, high), as :func:`seed_ratio`.
    """
    return seed_ratio(student_mean, student_std, n_seeds, vote_iou, ci=ci)


#: method -> (the distillation efficiency it should reach, whether its whole interval must): docs/decisions.md
EFFICIENCY_TARGETS: dict[str, tuple[float, bool]] = {BASELINE: (0.95, False), PROPOSED: (1.0, False),
                                                      SUPERVISED_CEILING: (1.0, True)}


def efficiency_target_met(method: str, ratio: float, low: float) -> bool | None:
    """Tell whether an efficiency meets the method's target in :data:`EFFICIENCY_TARGETS`.

    Parameters
    ----------
    method : str
        The method.
    ratio : float
        Its distillation efficiency.
    low : float
        The low end of its interval (compared where the target asks for the whole interval).

    Returns
    -------
    bool or None
        Whether the target is met; None for a method without a target or a non-finite number.
    """
    if method not in EFFICIENCY_TARGETS:
        return None
    target, on_interval = EFFICIENCY_TARGETS[method]
    x = low if on_interval else ratio
    return bool(x >= target) if math.isfinite(x) else None


def efficiency_metric_files(summary: pd.DataFrame, vote: Mapping[str, float]) -> dict[str, dict[str, float]]:
    """Make the efficiency metrics files: every method's distillation efficiency at the calibrated tau.

    The :func:`distillation_efficiency` ratio on each group in ``vote``; the interval stays in the report.

    Parameters
    ----------
    summary : pandas.DataFrame
        The seed summary (``summary.parquet``): ``iou_mean``, ``iou_std``, ``n_seeds`` per group and method.
    vote : Mapping
        Group -> the teacher vote's Image IoU; other groups are left out.

    Returns
    -------
    dict
        ``{"<group>/<method>.json": {"efficiency": ratio}}`` (a non-finite ratio leaves the file empty).
    """
    def efficiency(r):
        if str(r["group"]) not in vote:
            return None
        return {"efficiency": distillation_efficiency(r["iou_mean"], r.get("iou_std"), r.get("n_seeds", 1),
                                                      vote[str(r["group"])])[0]}

    return _calibrated_files(summary, efficiency)


def deploy_metrics(fast_path: Mapping[str, Any] | None, rows: Iterable[Mapping[str, Any]],
                   baseline: str) -> dict[str, float]:
    """Pick the deployed model's batch-1 latency for the DVC metrics.

    Parameters
    ----------
    fast_path : Mapping or None
        The fast path's measured record (with ``latency_ms``), None when there is none.
    rows : iterable of Mapping
        The benchmark rows, one per variant (``variant``, ``latency_ms``).
    baseline : str
        The variant whose row stands in without a fast path.

    Returns
    -------
    dict
        ``{"latency_ms": ...}``; ``{}`` when neither was measured (or the value is not finite).
    """
    if fast_path is not None:
        return numeric({"latency_ms": fast_path.get("latency_ms")})
    base = next((r for r in rows if r.get("variant") == baseline), None)
    return numeric({"latency_ms": base.get("latency_ms")}) if base is not None else {}


def training_curves(logs: Iterable[tuple[str, int, pd.DataFrame]]) -> pd.DataFrame:
    """Stack training logs into the long plot table DVC shows.

    Parameters
    ----------
    logs : iterable of (str, int, pandas.DataFrame)
        ``(method, seed, log)`` triples; each log has ``epoch`` and some of :data:`CURVE_COLUMNS`.

    Returns
    -------
    pandas.DataFrame
        Columns ``method``, ``seed``, ``epoch`` and the :data:`CURVE_COLUMNS` present, sorted, rounded to
        :data:`PLOT_DECIMALS`; empty (all columns) without logs.
    """
    frames = []
    for method, seed, log in logs:
        cols = ["epoch", *(c for c in CURVE_COLUMNS if c in log.columns)]
        frames.append(log[cols].assign(method=str(method), seed=int(seed))[["method", "seed", *cols]])
    if not frames:
        return pd.DataFrame(columns=["method", "seed", "epoch", *CURVE_COLUMNS])
    df = pd.concat(frames, ignore_index=True)
    df["epoch"] = df["epoch"].astype(int)
    return df.sort_values(["method", "seed", "epoch"], kind="stable").round(PLOT_DECIMALS).reset_index(drop=True)


def threshold_curves(thresholds: pd.DataFrame) -> pd.DataFrame:
    """Unroll calibrate's validation curves of [P >= tau] (eq:inference-mask) into a long plot table.

    Parameters
    ----------
    thresholds : pandas.DataFrame
        The calibrated thresholds (``thresholds.parquet``): per method and seed, the ``grid`` of taus and the
        ``curve`` of validation Image IoU on it.

    Returns
    -------
    pandas.DataFrame
        Columns ``method``, ``seed``, ``tau``, ``val_iou``, sorted, rounded to :data:`PLOT_DECIMALS`.
    """
    rows = [{"method": str(r["method"]), "seed": int(r["seed"]), "tau": float(t), "val_iou": float(v)}
            for _, r in thresholds.iterrows() for t, v in zip(r["grid"], r["curve"])]
    df = pd.DataFrame(rows, columns=["method", "seed", "tau", "val_iou"])
    return df.sort_values(["method", "seed", "tau"], kind="stable").round(PLOT_DECIMALS).reset_index(drop=True)


def write_metrics_dir(directory: str | Path, files: Mapping[str, Mapping[str, float]]) -> Path:
    """Replace ``directory`` atomically by the given JSON files (no stale file survives).

    Parameters
    ----------
    directory : str or Path
        The metrics folder, replaced whole.
    files : Mapping
        Relative path -> its metrics (name -> number).

    Returns
    -------
    Path
        ``directory``.
    """
    with atomic_path(directory, is_dir=True) as tmp:
        for rel, metrics in sorted(files.items()):
            write_json(tmp / rel, dict(metrics))
    return Path(directory)


def write_csv(path: str | Path, table: pd.DataFrame) -> Path:
    """Write ``table`` as CSV atomically (no index, Unix line ends).

    Parameters
    ----------
    path : str or Path
        The file, replaced.
    table : pandas.DataFrame
        The table.

    Returns
    -------
    Path
        ``path``.
    """
    with atomic_path(path) as tmp:
        tmp.write_text(table.to_csv(index=False, lineterminator="\n"))
    return Path(path)


LIVE_SKIP = ("epoch", "stage")


def write_live_log(log, directory: str | Path, selected_epoch: int | None = None) -> Path:
    """Log the run's epoch rows with DVCLive into ``directory``, replaced atomically.

    Step = ``epoch``; every other finite numeric column but ``stage`` is a metric; no experiment and no
    dvc.yaml (the DVC stage is the experiment).

    Parameters
    ----------
    log : pandas.DataFrame
        The run's training log, a row per epoch.
    directory : str or Path
        The DVCLive folder, replaced whole.
    selected_epoch : int, optional
        The epoch whose weights were kept, written to the summary.

    Returns
    -------
    Path
        ``directory``.
    """
    from dvclive import Live

    logging.getLogger("dvclive").setLevel(logging.WARNING)  # its INFO line names a random experiment
    columns = [c for c in log.columns if c not in LIVE_SKIP]

    class _StageLive(Live):
        """DVCLive without its repository hooks (they fail without commits and ``dvc init`` a git checkout)."""

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
