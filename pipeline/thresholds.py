"""Thresholds: eq:inference-mask, M = [P >= tau] <=> [Z >= logit(tau)], how tau is calibrated, and
where tau comes from.

One module owns the three rules; calibrate, evaluate, export, segment, benchmark and the report
import it:

* the inference mask (eq:inference-mask): :func:`mask_from_probs`, :func:`logit_threshold`;
* calibration (paper, Training Details: "The binarization threshold is selected by Image IoU on the
  corresponding validation set and then applied unchanged to the test set"): :func:`threshold_grid`,
  :func:`select_tau` (the tie rule), :func:`calibrate_threshold`;
* resolution of the tau a deployed model runs with: :func:`resolve_tau` (precedence
  option > bundle > checkpoint > thresholds file > fixed tau), and beside it the working resolution
  it runs at: :func:`resolve_resolution` (option > benchmark size > recorded with the model > params).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Mapping

import numpy as np

from pipeline.artifacts import open_artifact
from pipeline.runtime.errors import InputError
from pipeline.metrics import iou_curve
from pipeline.params import PAPER, require

log = logging.getLogger(__name__)

TIE_TOLERANCE = 1e-12  # mean IoUs closer than this are a tie (select_tau)


# --------------------------------------------------------------------------------------------------
# eq:inference-mask
# --------------------------------------------------------------------------------------------------
def logit_threshold(tau: float) -> float:
    """logit(tau) = log(tau / (1 - tau)): [sigmoid(Z) >= tau] == [Z >= logit(tau)] (eq:inference-mask).

    tau = 0 -> -inf (everything foreground), tau = 1 -> +inf (nothing).
    """
    tau = float(tau)
    if not 0.0 <= tau <= 1.0:
        raise InputError(f"tau={tau}: must lie in [0, 1]")
    if tau == 0.0:
        return -math.inf
    if tau == 1.0:
        return math.inf
    return math.log(tau / (1.0 - tau))


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


# --------------------------------------------------------------------------------------------------
# Calibration on the validation split
# --------------------------------------------------------------------------------------------------
def threshold_grid(cfg: dict) -> np.ndarray:
    """tau grid from calibrate.grid_start .. grid_stop (inclusive) in steps of grid_step, rounded to
    1e-9 so that 0.5 is exactly on the default grid.  InputError names the param."""
    start = require(cfg, "grid_start", "calibrate", kind=(int, float), lo=0.0, hi=1.0)
    stop = require(cfg, "grid_stop", "calibrate", kind=(int, float), lo=0.0, hi=1.0)
    step = require(cfg, "grid_step", "calibrate", kind=(int, float), lo=1e-6, hi=1.0)
    if stop < start:
        raise InputError(f"params: calibrate.grid_stop={stop} < calibrate.grid_start={start}")
    n = int(np.floor((stop - start) / step + 1e-9)) + 1
    return np.round(start + step * np.arange(n), 9)


def _default_grid() -> np.ndarray:
    return threshold_grid(PAPER.calibrate.model_dump())


#: The grid of the training log's per-epoch calibrated tau (``val_tau_cal``): the schema's default
#: calibration grid (0.05..0.95 by 0.01).  Fixed rather than read from ``calibrate.*``: the training
#: log is part of a checkpoint, and editing the calibrate stage's grid must not retrain every student.
EPOCH_TAU_GRID = _default_grid()


def select_tau(grid, curve) -> float:
    """The calibrated tau: argmax over ``grid`` of ``curve`` (mean validation Image IoU per tau).

    Ties (mean IoUs within :data:`TIE_TOLERANCE` of the maximum) go to the tau closest to 0.5, then to
    the smaller tau.  ``grid`` and ``curve`` are 1-D of equal, non-zero length.
    """
    grid = np.asarray(grid, dtype=np.float64)
    curve = np.asarray(curve, dtype=np.float64)
    if grid.ndim != 1 or grid.shape != curve.shape or grid.size == 0:
        raise InputError(f"select_tau: grid {grid.shape} and curve {curve.shape} must be equal non-empty 1-D")
    best = np.flatnonzero(curve >= curve.max() - TIE_TOLERANCE)
    order = np.lexsort((grid[best], np.abs(grid[best] - 0.5)))  # closest to 0.5, then smaller tau
    return float(grid[best[order[0]]])


#: calibration rules (``calibrate.tau_rule``): ``argmax`` (the paper), ``plateau``, ``smooth``
TAU_RULES = ("argmax", "plateau", "smooth")


def plateau_tau(grid, curve, tolerance: float) -> float:
    """Centre of the near-optimal plateau: the contiguous run of grid points around the argmax
    (:func:`select_tau`) whose curve is >= max - ``tolerance``; tau = its middle grid point
    (lower middle for an even count).

    Why: on a flat curve (mean validation IoU over few images) the argmax wanders over the whole
    plateau with tiny numeric changes; its centre does not.  ``tolerance`` 0 -> the argmax's run of
    exact ties (normally the argmax itself)."""
    grid = np.asarray(grid, dtype=np.float64)
    curve = np.asarray(curve, dtype=np.float64)
    best = int(np.flatnonzero(grid == select_tau(grid, curve))[0])
    near = curve >= curve.max() - float(tolerance) - TIE_TOLERANCE
    lo = best
    while lo > 0 and near[lo - 1]:
        lo -= 1
    hi = best
    while hi < len(grid) - 1 and near[hi + 1]:
        hi += 1
    return float(grid[lo + (hi - lo) // 2])


def smooth_curve(curve, halfwidth: int) -> np.ndarray:
    """Centred moving average of ``curve`` over 2 * ``halfwidth`` + 1 grid points; near the ends the
    window is cut to the points that exist (no padding).  ``halfwidth`` 0 -> the curve itself."""
    c = np.asarray(curve, dtype=np.float64)
    h = int(halfwidth)
    if h <= 0:
        return c.copy()
    s = np.concatenate([[0.0], np.cumsum(c)])
    i = np.arange(len(c))
    lo, hi = np.maximum(i - h, 0), np.minimum(i + h + 1, len(c))
    return (s[hi] - s[lo]) / (hi - lo)


def tau_by_rule(grid, curve, rule: str = "argmax", *, tolerance: float = 0.005, halfwidth: int = 5) -> float:
    """The calibrated tau of ``curve`` (mean validation Image IoU over ``grid``) by ``rule``:
    ``argmax`` (:func:`select_tau`, the paper), ``plateau`` (:func:`plateau_tau` with ``tolerance``)
    or ``smooth`` (argmax of :func:`smooth_curve` with ``halfwidth``).  InputError for another rule."""
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
    """Choose tau on validation images by mean Image IoU over ``grid`` (eq:inference-mask).

    probs float [N,H,W] in [0,1]; gts bool [N,H,W]; grid strictly increasing taus.  Returns
    (best_tau, curve) with curve float64 [G] = mean Image IoU of [P >= tau] at each grid point
    (pipeline.metrics.iou_curve); best_tau by :func:`tau_by_rule` (``argmax``, the paper's rule, by
    default: :func:`select_tau`, ties -> closest to 0.5, then smaller).
    """
    grid = np.asarray(grid, dtype=np.float64)
    if np.ndim(probs) != 3 or np.shape(probs)[0] == 0:
        raise InputError(f"calibrate_threshold: expected probs [N,H,W] with N >= 1, got shape {np.shape(probs)}")
    curve = iou_curve(probs, gts, grid).mean(axis=0)
    return tau_by_rule(grid, curve, rule, tolerance=tolerance, halfwidth=halfwidth), curve


#: thresholds.parquet ``tau_source`` of a run that could not be calibrated (no validation image has a
#: mask): its tau is ``calibrate.fixed_tau``.  Calibrated rows have no ``tau_source`` (or a null one).
NO_VALIDATION_MASKS = "fixed tau: no validation masks"


def _run_row(thresholds_df, method: str, seed: int):
    """The (method, seed) row of a thresholds table (a pandas Series), or None when it is absent."""
    df = thresholds_df
    rows = df[(df["method"].astype(str) == str(method)) & (df["seed"].astype(int) == int(seed))]
    return None if rows.empty else rows.iloc[0]


def _note(row) -> str | None:
    value = row.get("tau_source") if row is not None else None
    return value if isinstance(value, str) and value else None


# --------------------------------------------------------------------------------------------------
# Which tau a deployed model runs with
# --------------------------------------------------------------------------------------------------
TAU_SOURCES = ("option", "bundle", "checkpoint", "thresholds", "fixed")
TAU_LABELS = {"option": "--tau", "bundle": "deploy bundle", "checkpoint": "checkpoint payload",
              "thresholds": "thresholds table", "fixed": "calibrate.fixed_tau"}


def resolve_tau(option=None, bundle=None, checkpoint=None, thresholds=None, fixed=None) -> tuple[float, str]:
    """The tau to binarise with (eq:inference-mask) and where it came from: ``(tau, source)``.

    Rule: the first candidate that is given, in the order
    ``option`` (--tau) > ``bundle`` (deploy.json) > ``checkpoint`` (its payload's tau) >
    ``thresholds`` (the run's row of a thresholds.parquet, calibrated on the validation split) >
    ``fixed`` (calibrate.fixed_tau: uncalibrated, logged as a warning).  Each candidate is None
    (absent), a number, or ``(number, source text)``; a bare number's source is its
    :data:`TAU_LABELS` entry.  The chosen value must lie in [0, 1] (InputError naming its source);
    InputError when none is given.
    """
    given = dict(zip(TAU_SOURCES, (option, bundle, checkpoint, thresholds, fixed)))
    for name in TAU_SOURCES:
        cand = given[name]
        if cand is None or (isinstance(cand, tuple) and cand[0] is None):
            continue
        value, source = cand if isinstance(cand, tuple) else (cand, TAU_LABELS[name])
        tau = check_tau(value, TAU_LABELS[name])
        if name == "fixed":
            log.warning("tau = %s from %s (no calibrated tau)", tau, source)
        return tau, source
    raise InputError("tau: no calibrated tau found; pass --tau or a thresholds table (--thresholds)")


#: the text of a thresholds row's calibrated tau when the row has no ``tau_source`` note
CALIBRATED = "calibrated on the validation split"


def tau_candidates(*, bundle: Mapping | None = None, payload: Mapping | None = None, thresholds=None,
                   params: Mapping | None = None) -> dict[str, tuple[float, str]]:
    """The tau candidates of one model, calibrated and fixed: ``{source: (tau, text)}``, the keyword
    arguments of :func:`resolve_tau` (eq:inference-mask binarises with the one it picks).

    * a deploy bundle (``bundle``: its deploy.json): ``bundle`` = the tau it was exported with;
    * a checkpoint (``payload``: its model.json fields, at least method and seed): ``checkpoint`` = the
      payload's tau when it records one, else ``thresholds`` = the run's row of ``thresholds`` (a
      thresholds.parquet: a path, read only when it exists, an opened artifact or a DataFrame), text
      :data:`CALIBRATED` or the row's ``tau_source`` note (:data:`NO_VALIDATION_MASKS`);
    * ``fixed``: ``calibrate.fixed_tau``, the one fixed tau: as calibrate recorded it in the run's
      thresholds row, else of ``params`` (validated params; None: no fixed candidate).

    Export, segment, benchmark, evaluation (both taus) and :class:`pipeline.Segmenter` take their tau
    from here.
    """
    found: dict[str, tuple[float, str]] = {}
    if bundle is not None and bundle.get("tau") is not None:
        found["bundle"] = (float(bundle["tau"]), f"deploy bundle ({bundle.get('tau_source', '?')})")
    row, method, seed = None, None, None
    if payload is not None:
        method, seed = payload.get("method"), payload.get("seed")
        if payload.get("tau") is not None:
            found["checkpoint"] = (float(payload["tau"]), TAU_LABELS["checkpoint"])
        elif (table := _thresholds_table(thresholds)) is not None:
            row = _run_row(table, method, seed)
    where = _thresholds_name(thresholds)
    if row is not None:
        found["thresholds"] = (float(row["tau"]), f"{_note(row) or CALIBRATED} ({where}: {method}, seed {seed})")
    label = TAU_LABELS["fixed"]
    if row is not None and row.get("fixed_tau") is not None:
        found["fixed"] = (float(row["fixed_tau"]), f"{label} (recorded by calibrate in {where})")
    elif params is not None and (fixed := (params.get("calibrate") or {}).get("fixed_tau")) is not None:
        why = "" if payload is None else \
            f" (no calibrated row for {method} seed {seed} in {where})" if thresholds is not None else \
            " (no --thresholds given)"
        found["fixed"] = (fixed, label + why)
    return found


def _thresholds_name(thresholds) -> str | None:
    """How messages name ``thresholds`` (a path, an opened artifact or a DataFrame)."""
    if thresholds is None:
        return None
    return "thresholds table" if hasattr(thresholds, "columns") else str(getattr(thresholds, "path", thresholds))


def _thresholds_table(thresholds):
    """The DataFrame of ``thresholds`` (a path, read only when it exists; an opened artifact; a DataFrame)."""
    if thresholds is None or hasattr(thresholds, "columns"):
        return thresholds
    if hasattr(thresholds, "df"):
        return thresholds.df
    return open_artifact(thresholds, "thresholds").df if Path(thresholds).exists() else None


# --------------------------------------------------------------------------------------------------
# Which working resolution a deployed model runs at
# --------------------------------------------------------------------------------------------------
RESOLUTION_SOURCES = ("option", "benchmark", "recorded", "params")
RESOLUTION_LABELS = {"option": "--resolution", "benchmark": "deploy.benchmark_resolution",
                     "recorded": "the model's recorded resolution", "params": "data.resolution"}
#: the smallest working resolution a model runs at (the student's four 2x poolings need 8 pixels)
MIN_RESOLUTION = 8


def resolve_resolution(option=None, benchmark=None, recorded=None, params=None,
                       missing: str = "resolution: none given or recorded; pass --resolution N") -> tuple[int, str]:
    """The working resolution (square, pixels) and where it came from: ``(resolution, source)``.

    Rule: the first candidate that is given, in the order ``option`` (--resolution, or the notebook
    API's ``resolution=``) > ``benchmark`` (deploy.benchmark_resolution: the benchmark stage times at
    that size) > ``recorded`` (the size the model was trained at: the bundle's deploy.json, the
    checkpoint's payload or meta.json) > ``params`` (data.resolution).  Callers pass only the
    candidates their command knows (segment and the notebook API never guess from params; export has no
    option).  Each candidate is None (absent), a number, or ``(number, source text)``; a bare number's
    source is its :data:`RESOLUTION_LABELS` entry.  The chosen value must be an int >= 8 (InputError
    naming its source); InputError ``missing`` when none is given.
    """
    given = dict(zip(RESOLUTION_SOURCES, (option, benchmark, recorded, params)))
    for name in RESOLUTION_SOURCES:
        cand = given[name]
        if cand is None or (isinstance(cand, tuple) and cand[0] is None):
            continue
        value, source = cand if isinstance(cand, tuple) else (cand, RESOLUTION_LABELS[name])
        if not isinstance(value, int) or isinstance(value, bool) or value < MIN_RESOLUTION:
            raise InputError(f"{source}: invalid resolution {value!r} (an integer >= {MIN_RESOLUTION})")
        return int(value), source
    raise InputError(missing)
