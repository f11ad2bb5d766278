"""The evaluation of the students (the ``calibrate`` and ``evaluate`` stages' logic).

Each run's tau calibrated on the validation split; on the test split every run's per-image scores at its calibrated
and the fixed tau, the seed summaries, and the gains over the method table's reference points.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

from pipeline import catalog
from pipeline.artifacts.store import read_chunk_rows
from pipeline.evaluation.diagnostics import (area_ratio_curve, expected_calibration_error, median_area_ratio,
                                           reliability_bins, target_fractions, target_size_class)
from pipeline.runtime.errors import ArtifactError
from pipeline.evaluation.inference import load_student, predict_probs
from pipeline.methods import BASELINE, GAIN_CONTROLS, gain_treatments
from pipeline.metrics import iou_curve, score_masks, scoring_reference
from pipeline.runtime.progress import progress
from pipeline.stats import DEFAULT_INTERVAL, method_gains, seed_summary, vs_column
from pipeline.thresholds import (NO_VALIDATION_MASKS, calibrate_threshold, mask_from_probs, rule_options, tau_candidates,
                                 threshold_grid)

__all__ = ["score_runs", "summarize", "calibrate_runs", "fixed_thresholds"]

GAIN_METRICS = ("iou", "bf1", "precision", "recall")
SUMMARY_METRICS = ("iou", "bf1", "precision", "recall", "area_ratio", "small_iou", "area_vs_reference")
METRICS_KEY = ["dataset", "domain", "group", "spacecraft", "method", "seed", "image_id", "threshold_mode", "tau"]
SUMMARY_BY = ["dataset", "group", "method", "threshold_mode"]
INFO_COLUMNS = ["image_id", "dataset", "domain", "group", "spacecraft"]
CHUNK = 64  # test images per batch: bounded memory
#: the reference side (~5 bytes a pixel) is kept for every run up to this many test pixels, else rebuilt per run
REFERENCE_CACHE_PIXELS = 1 << 26


def fixed_thresholds(runs: Sequence[tuple[str, int, Path]], fixed_tau: float) -> pd.DataFrame:
    """thresholds.parquet when no validation image has a mask: every run gets the fixed tau.

    Export and segment then use it, and the report says that no masks were available.

    Parameters
    ----------
    runs : sequence of (str, int, Path)
        The runs (method, seed, checkpoint folder).
    fixed_tau : float
        ``calibrate.fixed_tau``.

    Returns
    -------
    pandas.DataFrame
        One row per run: ``tau`` = ``fixed_tau``, ``val_iou`` NaN, ``n_val`` 0, ``tau_source`` saying why.
    """
    return pd.DataFrame([{"method": method, "seed": int(seed), "tau": fixed_tau, "val_iou": float("nan"),
                          "fixed_tau": fixed_tau, "fixed_val_iou": float("nan"), "n_val": 0,
                          "tau_source": NO_VALIDATION_MASKS} for method, seed, _ in runs])


def calibrate_runs(runs: Sequence[tuple[str, int, Path]], val_images: np.ndarray, val_masks: np.ndarray,
                   cfg: Mapping, device) -> pd.DataFrame:
    """thresholds.parquet: each run's tau by mean validation Image IoU over the grid (eq:inference-mask).

    tau follows ``calibrate.tau_rule`` (:func:`pipeline.thresholds.calibrate_threshold`); each row also holds
    the whole curve, the Image IoU at the fixed tau, the reliability diagram and its ECE, and the median
    predicted over reference area ratio across the grid.  The reference masks only calibrate here.

    Parameters
    ----------
    runs : sequence of (str, int, Path)
        The runs (method, seed, checkpoint folder).
    val_images : numpy.ndarray
        The validation images [N,R,R,C], N >= 1.
    val_masks : numpy.ndarray
        Their reference masks, bool [N,R,R].
    cfg : Mapping
        The validated ``calibrate`` section.
    device : str or torch.device
        Where the students run.

    Returns
    -------
    pandas.DataFrame
        One row per run, in the order of ``runs``.

    Raises
    ------
    InputError
        As :func:`pipeline.thresholds.calibrate_threshold`.
    """
    grid, fixed_tau = threshold_grid(cfg), cfg["fixed_tau"]
    rows = []
    for method, seed, path in progress(runs, desc="calibrate"):
        model, _ = load_student(path, device)
        probs = predict_probs(model, val_images, device=device)
        tau, curve = calibrate_threshold(probs, val_masks, grid, **rule_options(cfg))
        rel = reliability_bins(probs, val_masks, cfg["reliability_bins"])
        area = median_area_ratio(area_ratio_curve(probs, val_masks, grid))
        rows.append({"method": method, "seed": int(seed), "tau": tau, "val_iou": float(curve.max()),
                     "fixed_tau": fixed_tau, "fixed_val_iou": float(iou_curve(probs, val_masks, [fixed_tau]).mean()),
                     "n_val": len(val_masks), "grid": grid.tolist(), "curve": curve.tolist(),
                     "ece": expected_calibration_error(rel.confidence, rel.frequency, rel.count),
                     "rel_confidence": rel.confidence.tolist(), "rel_frequency": rel.frequency.tolist(),
                     "rel_count": rel.count.tolist(), "area_curve": area.tolist(),
                     # tau is a grid point (select_tau): its area ratio is on the curve already
                     "area_ratio": float(area[int(np.flatnonzero(grid == tau)[0])]),
                     "fixed_area_ratio": float(median_area_ratio(area_ratio_curve(probs, val_masks, [fixed_tau]))[0])})
    return pd.DataFrame(rows)


def run_thresholds(thresholds: pd.DataFrame, method: str, seed: int, path) -> tuple[float, float]:
    """Read one run's (calibrated tau, fixed tau) as calibrate recorded them.

    Parameters
    ----------
    thresholds : pandas.DataFrame
        thresholds.parquet.
    method : str
        The run's method.
    seed : int
        The run's seed.
    path : str or Path
        The run's checkpoint, named by the error.

    Returns
    -------
    tuple of float
        ``(calibrated tau, fixed tau)``.

    Raises
    ------
    ArtifactError
        No calibrated threshold for the run: rerun calibrate.
    """
    taus = tau_candidates(payload={"method": method, "seed": seed}, thresholds=thresholds)
    if "thresholds" not in taus:
        raise ArtifactError(f"{path}: no calibrated threshold for {method}/{seed} in {catalog.ARTIFACTS['thresholds'].path}; "
                            f"rerun calibrate")
    return taus["thresholds"][0], taus["fixed"][0]


def _chunk_references(reference_masks, test: np.ndarray, tolerance: float, small_fraction: float):
    """Make ``get(start, idx)``: a test chunk's target fractions and :class:`pipeline.metrics.ScoringReference`."""
    cache: dict[int, tuple] = {}

    def get(start: int, idx: np.ndarray) -> tuple:
        if start in cache:
            return cache[start]
        gts = read_chunk_rows(reference_masks, idx).astype(bool)
        entry = target_fractions(gts), scoring_reference(gts, tolerance, max_fraction=small_fraction)
        if test.size * gts[0].size <= REFERENCE_CACHE_PIXELS:
            cache[start] = entry
        return entry
    return get


def _score_chunk(probs: np.ndarray, info: pd.DataFrame, target: np.ndarray, ref, method: str, seed: int,
                 taus: Mapping[str, float], tiny_fraction: float) -> list[pd.DataFrame]:
    """Score one chunk of one run: a frame per threshold mode (``taus``: mode -> tau)."""
    frames = []
    for mode, tau in taus.items():
        scores = score_masks(mask_from_probs(probs, tau), ref)  # eq:inference-mask
        part = info.assign(method=method, seed=int(seed), threshold_mode=mode, tau=tau, **scores)
        part["target_fraction"], part["target_size"] = target, target_size_class(target, tiny_fraction)
        with np.errstate(invalid="ignore", divide="ignore"):
            part["area_vs_reference"] = np.where(target > 0, scores["area_ratio"] / np.maximum(target, 1e-300),
                                                 np.nan)
        frames.append(part)
    return frames


def score_runs(runs: Sequence[tuple[str, int, Path]], manifest: pd.DataFrame, images, reference, test: np.ndarray,
               thresholds: pd.DataFrame, cfg: Mapping, device) -> pd.DataFrame:
    """Score every run on the test rows at its calibrated and the fixed tau: the rows of metrics.parquet.

    Each image's mask is eq:inference-mask, M(x) = [P(x) >= tau], scored against its reference.

    Parameters
    ----------
    runs : sequence of tuple
        ``(method, seed, checkpoint path)`` per run.
    manifest : pandas.DataFrame
        The manifest (its info columns are copied to each row).
    images : zarr group
        images.zarr (``image`` [N, R, R, 3]).
    reference : zarr group
        reference.zarr (``mask`` [N, R, R]).
    test : numpy.ndarray
        The test rows' manifest indices.
    thresholds : pandas.DataFrame
        thresholds.parquet: each run's calibrated and fixed tau.
    cfg : Mapping
        The validated ``evaluate:`` section (``bf1_tolerance``, ``small_region_max_fraction``,
        ``tiny_target_max_fraction``).
    device : str or torch.device
        Where the students run.

    Returns
    -------
    pandas.DataFrame
        One row per (run, image, threshold mode): the keys :data:`METRICS_KEY` first, then the scores, the
        target fraction and size class, and the area over the reference's.

    Raises
    ------
    ArtifactError
        A run without a calibrated threshold (from :func:`run_thresholds`).
    """
    info = manifest.iloc[test][INFO_COLUMNS].reset_index(drop=True)
    refs = _chunk_references(reference["mask"], test, cfg["bf1_tolerance"], cfg["small_region_max_fraction"])
    frames = []
    for method, seed, path in progress(runs, desc="evaluate"):
        tau_cal, tau_fixed = run_thresholds(thresholds, method, seed, path)
        model, _ = load_student(path, device)
        for s in range(0, test.size, CHUNK):
            idx = test[s:s + CHUNK]
            probs = predict_probs(model, read_chunk_rows(images["image"], idx), device=device)
            target, ref = refs(s, idx)
            frames += _score_chunk(probs, info.iloc[s:s + len(idx)], target, ref, method, seed,
                                   {"calibrated": tau_cal, "fixed": tau_fixed}, cfg["tiny_target_max_fraction"])
    metrics = pd.concat(frames, ignore_index=True)
    return metrics[METRICS_KEY + [c for c in metrics.columns if c not in METRICS_KEY]]


def control_gains(metrics: pd.DataFrame, control: str, n_boot: int, ci: float, seed: int,
                  interval: str = DEFAULT_INTERVAL) -> pd.DataFrame:
    """Compute the gains over ``control`` of the methods :func:`pipeline.methods.gain_treatments` compares with it."""
    keep = [*gain_treatments(control, metrics["method"].unique()), control]
    return method_gains(metrics[metrics["method"].isin(keep)], GAIN_METRICS, control=control,
                        by=[c for c in SUMMARY_BY if c != "method"], n_resamples=n_boot, ci=ci, seed=seed,
                        interval=interval)


def summarize(metrics: pd.DataFrame, n_boot: int, ci: float, seed: int, interval: str = DEFAULT_INTERVAL) -> pd.DataFrame:
    """Summarise the metrics over seeds, with the gains over the reference points: summary.parquet.

    The gains are over BASELINE (always) and over every other evaluated reference point, each in its
    :func:`pipeline.stats.vs_column` columns.

    Parameters
    ----------
    metrics : pandas.DataFrame
        metrics.parquet (:func:`score_runs`).
    n_boot : int
        Bootstrap resamples of a gain's interval (``evaluate.bootstrap_resamples``).
    ci : float
        The intervals' confidence level (``evaluate.ci``).
    seed : int
        The resampling's seed (``evaluate.bootstrap_seed``).
    interval : str
        How a gain's interval is computed (``evaluate.interval``; docs/intervals.md).

    Returns
    -------
    pandas.DataFrame
        One row per (dataset, group, method, threshold mode).
    """
    summary = seed_summary(metrics, SUMMARY_BY, SUMMARY_METRICS)
    present = set(metrics["method"])
    for control in GAIN_CONTROLS:
        if control != BASELINE and control not in present:
            continue
        gains = control_gains(metrics, control, n_boot, ci, seed, interval)
        gains = gains.rename(columns={c: vs_column(c, control) for c in gains.columns if c not in SUMMARY_BY})
        summary = summary.merge(gains, on=SUMMARY_BY, how="left")
    return summary
