"""The evaluation on the test split: every run's per-image scores at its calibrated and the fixed tau,
the seed summaries, and the gains over the method table's reference points (the ``evaluate`` stage's logic).
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

from pipeline import catalog
from pipeline.artifacts.store import read_chunk_rows
from pipeline.evaluation.diagnostics import target_fractions, target_size_class
from pipeline.runtime.errors import ArtifactError
from pipeline.evaluation.inference import load_student, predict_probs
from pipeline.methods import BASELINE, GAIN_CONTROLS, gain_treatments
from pipeline.metrics import score_masks, scoring_reference
from pipeline.runtime.progress import progress
from pipeline.stats import DEFAULT_INTERVAL, method_gains, seed_summary, vs_column
from pipeline.thresholds import mask_from_probs, tau_candidates

__all__ = ["score_runs", "summarize"]

GAIN_METRICS = ("iou", "bf1", "precision", "recall")
SUMMARY_METRICS = ("iou", "bf1", "precision", "recall", "area_ratio", "small_iou", "area_vs_reference")
METRICS_KEY = ["dataset", "domain", "group", "spacecraft", "method", "seed", "image_id", "threshold_mode", "tau"]
SUMMARY_BY = ["dataset", "group", "method", "threshold_mode"]
INFO_COLUMNS = ["image_id", "dataset", "domain", "group", "spacecraft"]
CHUNK = 64  # test images per batch: bounded memory
#: the reference side (~5 bytes a pixel) is kept for every run up to this many test pixels, else rebuilt per run
REFERENCE_CACHE_PIXELS = 1 << 26


def run_thresholds(thresholds: pd.DataFrame, method: str, seed: int, path) -> tuple[float, float]:
    """(calibrated tau, fixed tau) of one run as calibrate recorded them."""
    taus = tau_candidates(payload={"method": method, "seed": seed}, thresholds=thresholds)
    if "thresholds" not in taus:
        raise ArtifactError(f"{path}: no calibrated threshold for {method}/{seed} in {catalog.ARTIFACTS['thresholds'].path}; "
                            f"rerun calibrate")
    return taus["thresholds"][0], taus["fixed"][0]


def _chunk_references(reference_masks, test: np.ndarray, tolerance: float, small_fraction: float):
    """``get(start, idx)``: a test chunk's target fractions and :class:`pipeline.metrics.ScoringReference`."""
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
    """One chunk of one run's rows, a frame per threshold mode (``taus``: mode -> tau)."""
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
    """metrics.parquet: every run ``(method, seed, checkpoint)`` on the ``test`` rows at both taus (``cfg``: evaluate.*)."""
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
    """Gains over ``control`` of the methods :func:`pipeline.methods.gain_treatments` compares with it."""
    keep = [*gain_treatments(control, metrics["method"].unique()), control]
    return method_gains(metrics[metrics["method"].isin(keep)], GAIN_METRICS, control=control,
                        by=[c for c in SUMMARY_BY if c != "method"], n_resamples=n_boot, ci=ci, seed=seed,
                        interval=interval)


def summarize(metrics: pd.DataFrame, n_boot: int, ci: float, seed: int, interval: str = DEFAULT_INTERVAL) -> pd.DataFrame:
    """summary.parquet: the seed summary with the gains over BASELINE (always) and over every other evaluated
    reference point (:func:`pipeline.stats.vs_column`).
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
