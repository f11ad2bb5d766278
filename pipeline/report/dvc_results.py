"""Results where DVC users look for them: short numeric metrics files (a few shared keys each, so ``dvc metrics
show`` stays narrow), per-method plot tables and DVCLive training logs (docs/pipeline.md).
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
    """A group or method name as one safe path component (``"a/b c"`` -> ``"a_b_c"``)."""
    s = re.sub(r"[^A-Za-z0-9._-]", "_", str(name)).strip(".")
    return s or "_"


def _group_dirs(df: pd.DataFrame) -> dict[tuple, str]:
    """(dataset, group) -> the group's folder: ``<dataset>.<group>`` when a run evaluates several datasets."""
    keys = sorted(set(zip(_dataset_col(df), df["group"].astype(str))))
    several = len({d for d, _ in keys}) > 1
    return {(d, g): path_component(f"{d}.{g}" if several else g) for d, g in keys}


def _dataset_col(df: pd.DataFrame) -> pd.Series:
    return df["dataset"].astype(str) if "dataset" in df else pd.Series([""] * len(df), index=df.index)


def _calibrated_files(summary: pd.DataFrame, values) -> dict[str, dict[str, float]]:
    """``{"<group>/<method>.json": values(row)}`` of the calibrated rows (the deployed rule); None skips a row."""
    cal = summary[summary["threshold_mode"] == "calibrated"]
    dirs = _group_dirs(cal)
    out: dict[str, dict[str, float]] = {}
    for ds, (_, r) in zip(_dataset_col(cal), cal.iterrows()):
        if (v := values(r)) is not None:
            out[f"{dirs[(ds, str(r['group']))]}/{path_component(r['method'])}.json"] = numeric(v)
    return out


def student_metric_files(summary: pd.DataFrame) -> dict[str, dict[str, float]]:
    """``{"<group>/<method>.json": {"iou", "bf1"}}``: the seed means at the calibrated tau."""
    return _calibrated_files(summary, lambda r: {"iou": r.get("iou_mean"), "bf1": r.get("bf1_mean")})


def teacher_metric_files(teacher_table: pd.DataFrame, gates: pd.DataFrame,
                         split: str = "test") -> dict[str, dict[str, float]]:
    """``{"<group>.json": {"iou", "bf1", "gate_share"}}`` per group of ``split``: the voted pseudo-masks'
    (eq:majority-vote) mean scores and the share of the group's images with g > 0 (eq:reliability-gate).
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
    """(ratio, low, high) of two seed means, r = mean / ref_mean, with the delta-method t interval
    r -+ t_{d, (1+ci)/2} sqrt(std^2 / n + r^2 ref_std^2 / ref_n) / ref_mean, d = min(n, ref_n) - 1;
    a reference without seeds (``ref_n`` None, e.g. the teacher vote) adds no variance.  nan interval below 2 seeds.
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
    """Distillation efficiency = student Image IoU / teacher-vote Image IoU, as (ratio, low, high):
    :func:`seed_ratio` against the vote, which has no seed.
    """
    return seed_ratio(student_mean, student_std, n_seeds, vote_iou, ci=ci)


#: method -> (the distillation efficiency it should reach, whether its whole interval must): docs/decisions.md
EFFICIENCY_TARGETS: dict[str, tuple[float, bool]] = {BASELINE: (0.95, False), PROPOSED: (1.0, False),
                                                      SUPERVISED_CEILING: (1.0, True)}


def efficiency_target_met(method: str, ratio: float, low: float) -> bool | None:
    """Whether (ratio, interval low end) meets the method's target; None without a target or a finite number."""
    if method not in EFFICIENCY_TARGETS:
        return None
    target, on_interval = EFFICIENCY_TARGETS[method]
    x = low if on_interval else ratio
    return bool(x >= target) if math.isfinite(x) else None


def efficiency_metric_files(summary: pd.DataFrame, vote: Mapping[str, float]) -> dict[str, dict[str, float]]:
    """``{"<group>/<method>.json": {"efficiency"}}``: every method's :func:`distillation_efficiency` ratio at
    the calibrated tau on the groups in ``vote`` (group -> the vote's Image IoU); the interval stays in the report.
    """
    def efficiency(r):
        if str(r["group"]) not in vote:
            return None
        return {"efficiency": distillation_efficiency(r["iou_mean"], r.get("iou_std"), r.get("n_seeds", 1),
                                                      vote[str(r["group"])])[0]}

    return _calibrated_files(summary, efficiency)


def deploy_metrics(fast_path: Mapping[str, Any] | None, rows: Iterable[Mapping[str, Any]],
                   baseline: str) -> dict[str, float]:
    """``{"latency_ms"}`` of the fast path, else of the ``baseline`` variant's row; ``{}`` when neither was measured."""
    if fast_path is not None:
        return numeric({"latency_ms": fast_path.get("latency_ms")})
    base = next((r for r in rows if r.get("variant") == baseline), None)
    return numeric({"latency_ms": base.get("latency_ms")}) if base is not None else {}


def training_curves(logs: Iterable[tuple[str, int, pd.DataFrame]]) -> pd.DataFrame:
    """Long table (method, seed, epoch, :data:`CURVE_COLUMNS` present) of ``(method, seed, log)`` triples."""
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
    """Long table (method, seed, tau, val_iou) of calibrate's curves of [P >= tau] (eq:inference-mask)."""
    rows = [{"method": str(r["method"]), "seed": int(r["seed"]), "tau": float(t), "val_iou": float(v)}
            for _, r in thresholds.iterrows() for t, v in zip(r["grid"], r["curve"])]
    df = pd.DataFrame(rows, columns=["method", "seed", "tau", "val_iou"])
    return df.sort_values(["method", "seed", "tau"], kind="stable").round(PLOT_DECIMALS).reset_index(drop=True)


def write_metrics_dir(directory: str | Path, files: Mapping[str, Mapping[str, float]]) -> Path:
    """Replace ``directory`` atomically by the JSON files ``{relative path: metrics}`` (no stale file survives)."""
    with atomic_path(directory, is_dir=True) as tmp:
        for rel, metrics in sorted(files.items()):
            write_json(tmp / rel, dict(metrics))
    return Path(directory)


def write_csv(path: str | Path, table: pd.DataFrame) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(table.to_csv(index=False, lineterminator="\n"))
    return Path(path)


LIVE_SKIP = ("epoch", "stage")


def write_live_log(log, directory: str | Path, selected_epoch: int | None = None) -> Path:
    """Log the run's epoch rows with DVCLive into ``directory`` (replaced atomically): step = ``epoch``, every
    other finite numeric column a metric, no experiment and no dvc.yaml (the DVC stage is the experiment).
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
