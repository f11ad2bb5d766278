"""The inference mask M = [P >= tau] <=> [Z >= logit(tau)] (eq:inference-mask), tau's calibration on the
validation split, and which tau and working resolution a deployed model runs with."""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Mapping

import numpy as np

from pipeline.artifacts.store import open_artifact
from pipeline.runtime.errors import InputError
from pipeline.metrics import iou_curve
from pipeline.params import PAPER, require

log = logging.getLogger(__name__)

TIE_TOLERANCE = 1e-12  # mean IoUs closer than this are a tie (select_tau)


def logit_threshold(tau: float) -> float:
    """logit(tau): [sigmoid(Z) >= tau] == [Z >= logit(tau)] (eq:inference-mask); -inf at 0, +inf at 1."""
    tau = float(tau)
    if not 0.0 <= tau <= 1.0:
        raise InputError(f"tau={tau}: must lie in [0, 1]")
    return math.log(tau / (1.0 - tau)) if 0.0 < tau < 1.0 else (math.inf if tau == 1.0 else -math.inf)


def mask_from_probs(probs: np.ndarray, tau: float) -> np.ndarray:
    """M = [P >= tau] (eq:inference-mask), bool with the shape of ``probs``."""
    return np.asarray(probs) >= float(tau)


def check_tau(tau, where: str) -> float:
    """``tau`` as a float in [0, 1]; InputError naming ``where`` (an option or param) otherwise."""
    try:
        t = float(tau)
    except (TypeError, ValueError):
        raise InputError(f"{where}={tau!r}: not a number") from None
    if not 0.0 <= t <= 1.0 or math.isnan(t):
        raise InputError(f"{where}={tau!r}: must lie in [0, 1]")
    return t


def threshold_grid(cfg: dict) -> np.ndarray:
    """calibrate.grid_start .. grid_stop (inclusive) by grid_step, rounded to 1e-9 (0.5 exactly on the grid)."""
    start = require(cfg, "grid_start", "calibrate", kind=(int, float), lo=0.0, hi=1.0)
    stop = require(cfg, "grid_stop", "calibrate", kind=(int, float), lo=0.0, hi=1.0)
    step = require(cfg, "grid_step", "calibrate", kind=(int, float), lo=1e-6, hi=1.0)
    if stop < start:
        raise InputError(f"params: calibrate.grid_stop={stop} < calibrate.grid_start={start}")
    n = int(np.floor((stop - start) / step + 1e-9)) + 1
    return np.round(start + step * np.arange(n), 9)


#: the training log's per-epoch tau grid: the default one, so that editing ``calibrate.*`` retrains nothing
EPOCH_TAU_GRID = threshold_grid(PAPER.calibrate.model_dump())


def select_tau(grid, curve) -> float:
    """argmax over ``grid`` of ``curve`` (mean validation Image IoU); ties within :data:`TIE_TOLERANCE` go to
    the tau closest to 0.5, then to the smaller."""
    grid = np.asarray(grid, dtype=np.float64)
    curve = np.asarray(curve, dtype=np.float64)
    if grid.ndim != 1 or grid.shape != curve.shape or grid.size == 0:
        raise InputError(f"select_tau: grid {grid.shape} and curve {curve.shape} must be equal non-empty 1-D")
    best = np.flatnonzero(curve >= curve.max() - TIE_TOLERANCE)
    order = np.lexsort((grid[best], np.abs(grid[best] - 0.5)))
    return float(grid[best[order[0]]])


#: calibration rules (``calibrate.tau_rule``): ``argmax`` (the paper), ``plateau``, ``smooth``
TAU_RULES = ("argmax", "plateau", "smooth")


def plateau_tau(grid, curve, tolerance: float) -> float:
    """The middle grid point (lower middle) of the contiguous run around the argmax whose curve is within
    ``tolerance`` of the maximum: it does not wander over a flat curve as the argmax does."""
    grid = np.asarray(grid, dtype=np.float64)
    curve = np.asarray(curve, dtype=np.float64)
    best = int(np.flatnonzero(grid == select_tau(grid, curve))[0])
    far = np.flatnonzero(~(curve >= curve.max() - float(tolerance) - TIE_TOLERANCE))
    lo = int(far[far < best].max(initial=-1)) + 1
    hi = int(far[far > best].min(initial=len(grid))) - 1
    return float(grid[lo + (hi - lo) // 2])


def smooth_curve(curve, halfwidth: int) -> np.ndarray:
    """Centred moving average over 2 * ``halfwidth`` + 1 points, the window cut at the ends."""
    c = np.asarray(curve, dtype=np.float64)
    h = int(halfwidth)
    if h <= 0:
        return c.copy()
    s = np.concatenate([[0.0], np.cumsum(c)])
    i = np.arange(len(c))
    lo, hi = np.maximum(i - h, 0), np.minimum(i + h + 1, len(c))
    return (s[hi] - s[lo]) / (hi - lo)


def tau_by_rule(grid, curve, rule: str = "argmax", *, tolerance: float = 0.005, halfwidth: int = 5) -> float:
    """The calibrated tau of ``curve`` by ``rule`` (:data:`TAU_RULES`; argmax is the paper's)."""
    if rule == "argmax":
        return select_tau(grid, curve)
    if rule == "plateau":
        return plateau_tau(grid, curve, tolerance)
    if rule == "smooth":
        return select_tau(grid, smooth_curve(curve, halfwidth))
    raise InputError(f"calibrate.tau_rule={rule!r}: expected one of {', '.join(TAU_RULES)}")


def rule_options(cfg) -> dict:
    """Keyword arguments of :func:`tau_by_rule` from the calibrate params section."""
    return {"rule": cfg["tau_rule"], "tolerance": cfg["plateau_tolerance"], "halfwidth": cfg["smooth_halfwidth"]}


def calibrate_threshold(probs, gts, grid, rule: str = "argmax", *, tolerance: float = 0.005,
                        halfwidth: int = 5) -> tuple[float, np.ndarray]:
    """(tau by :func:`tau_by_rule`, curve float64 [G] = mean Image IoU of [P >= tau] at each grid point) on
    validation probs [N,H,W] and masks (eq:inference-mask)."""
    grid = np.asarray(grid, dtype=np.float64)
    if np.ndim(probs) != 3 or np.shape(probs)[0] == 0:
        raise InputError(f"calibrate_threshold: expected probs [N,H,W] with N >= 1, got shape {np.shape(probs)}")
    curve = iou_curve(probs, gts, grid).mean(axis=0)
    return tau_by_rule(grid, curve, rule, tolerance=tolerance, halfwidth=halfwidth), curve


#: thresholds.parquet ``tau_source`` of a run without validation masks (its tau is ``calibrate.fixed_tau``)
NO_VALIDATION_MASKS = "fixed tau: no validation masks"


TAU_LABELS = {"option": "--tau", "bundle": "deploy bundle", "checkpoint": "checkpoint payload",
              "thresholds": "thresholds table", "fixed": "calibrate.fixed_tau"}
TAU_SOURCES = tuple(TAU_LABELS)


def resolve_tau(option=None, bundle=None, checkpoint=None, thresholds=None, fixed=None) -> tuple[float, str]:
    """``(tau, source)``: the first candidate given, in :data:`TAU_LABELS` order (eq:inference-mask); each None,
    a number or ``(number, text)``; a fixed tau is logged as a warning."""
    for name, value, source in _given(TAU_LABELS, option, bundle, checkpoint, thresholds, fixed):
        tau = check_tau(value, TAU_LABELS[name])
        if name == "fixed":
            log.warning("tau = %s from %s (no calibrated tau)", tau, source)
        return tau, source
    raise InputError("tau: no calibrated tau found; pass --tau or a thresholds table (--thresholds)")


def _given(labels: Mapping[str, str], *candidates):
    """(name, value, source text) of each candidate given (None, a number or ``(number, text)``), in order."""
    for name, cand in zip(labels, candidates):
        if cand is not None and not (isinstance(cand, tuple) and cand[0] is None):
            yield (name, *cand) if isinstance(cand, tuple) else (name, cand, labels[name])


#: the text of a calibrated thresholds row without a ``tau_source`` note
CALIBRATED = "calibrated on the validation split"


def tau_candidates(*, bundle: Mapping | None = None, payload: Mapping | None = None, thresholds=None,
                   params: Mapping | None = None) -> dict[str, tuple[float, str]]:
    """One model's tau candidates ``{source: (tau, text)}`` for :func:`resolve_tau`: the bundle's (its deploy.json);
    a checkpoint's payload tau, else its row of ``thresholds`` (a path, artifact or DataFrame); the fixed
    tau calibrate recorded there, else ``calibrate.fixed_tau`` of the validated ``params``."""
    found: dict[str, tuple[float, str]] = {}
    if bundle is not None and bundle.get("tau") is not None:
        found["bundle"] = (float(bundle["tau"]), f"deploy bundle ({bundle.get('tau_source', '?')})")
    row, method, seed = None, None, None
    if payload is not None:
        method, seed = payload.get("method"), payload.get("seed")
        if payload.get("tau") is not None:
            found["checkpoint"] = (float(payload["tau"]), TAU_LABELS["checkpoint"])
        elif (df := _thresholds_table(thresholds)) is not None:
            rows = df[(df["method"].astype(str) == str(method)) & (df["seed"].astype(int) == int(seed))]
            row = None if rows.empty else rows.iloc[0]
    where = None if thresholds is None else \
        "thresholds table" if hasattr(thresholds, "columns") else str(getattr(thresholds, "path", thresholds))
    if row is not None:
        note = row.get("tau_source")
        note = note if isinstance(note, str) and note else CALIBRATED
        found["thresholds"] = (float(row["tau"]), f"{note} ({where}: {method}, seed {seed})")
    label = TAU_LABELS["fixed"]
    if row is not None and row.get("fixed_tau") is not None:
        found["fixed"] = (float(row["fixed_tau"]), f"{label} (recorded by calibrate in {where})")
    elif params is not None:
        why = "" if payload is None else \
            f" (no calibrated row for {method} seed {seed} in {where})" if thresholds is not None else \
            " (no --thresholds given)"
        found["fixed"] = (params["calibrate"]["fixed_tau"], label + why)
    return found


def _thresholds_table(thresholds):
    """The DataFrame of ``thresholds`` (a path is read only when it exists)."""
    if thresholds is None or hasattr(thresholds, "columns"):
        return thresholds
    if hasattr(thresholds, "df"):
        return thresholds.df
    return open_artifact(thresholds, "thresholds").df if Path(thresholds).exists() else None


RESOLUTION_LABELS = {"option": "--resolution", "benchmark": "deploy.benchmark_resolution",
                     "recorded": "the model's recorded resolution", "params": "data.resolution"}
#: the smallest working resolution a model runs at (the student's four 2x poolings need 8 pixels)
MIN_RESOLUTION = 8


def resolve_resolution(option=None, benchmark=None, recorded=None, params=None,
                       missing: str = "resolution: none given or recorded; pass --resolution N") -> tuple[int, str]:
    """``(resolution, source)``: the first candidate given, in :data:`RESOLUTION_LABELS` order;
    an int >= :data:`MIN_RESOLUTION`, InputError ``missing`` when none is given."""
    for _, value, source in _given(RESOLUTION_LABELS, option, benchmark, recorded, params):
        if not isinstance(value, int) or isinstance(value, bool) or value < MIN_RESOLUTION:
            raise InputError(f"{source}: invalid resolution {value!r} (an integer >= {MIN_RESOLUTION})")
        return int(value), source
    raise InputError(missing)
