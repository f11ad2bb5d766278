"""The inference mask and its threshold (eq:inference-mask).

M = [P >= tau] <=> [Z >= logit(tau)]; tau's calibration on the validation split (mean Image IoU over a grid,
:func:`calibrate_threshold`), and which tau and working resolution a deployed model runs with
(:func:`resolve_tau`, :func:`resolve_resolution`).
"""

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

__all__ = ["TIE_TOLERANCE", "logit_threshold", "mask_from_probs", "check_tau", "threshold_grid", "EPOCH_TAU_GRID",
           "select_tau", "TAU_RULES", "plateau_tau", "smooth_curve", "tau_by_rule", "rule_options",
           "calibrate_threshold", "RELATIVE_TAU_GRID", "RELATIVE_SLOPES", "image_peaks", "relative_taus",
           "calibrate_relative_threshold", "masks_from_relative", "NO_VALIDATION_MASKS", "TAU_LABELS", "TAU_SOURCES",
           "resolve_tau", "tau_candidates",
           "RESOLUTION_LABELS", "MIN_RESOLUTION", "resolve_resolution"]

log = logging.getLogger(__name__)

#: mean IoUs closer than this are a tie (:func:`select_tau`)
TIE_TOLERANCE = 1e-12


def logit_threshold(tau: float) -> float:
    """Return the logit threshold logit(tau) = log(tau / (1 - tau)).

    [sigmoid(Z) >= tau] == [Z >= logit(tau)] (eq:inference-mask), so engines that output logits binarise
    without a sigmoid.

    Parameters
    ----------
    tau : float
        Probability threshold in [0, 1].

    Returns
    -------
    float
        logit(tau); -inf at tau = 0 (every pixel foreground), +inf at tau = 1.

    Raises
    ------
    InputError
        ``tau`` is outside [0, 1].
    """
    tau = float(tau)
    if not 0.0 <= tau <= 1.0:
        raise InputError(f"tau={tau}: must lie in [0, 1]")
    return math.log(tau / (1.0 - tau)) if 0.0 < tau < 1.0 else (math.inf if tau == 1.0 else -math.inf)


def mask_from_probs(probs: np.ndarray, tau: float) -> np.ndarray:
    """Binarise probabilities: M = [P >= tau] (eq:inference-mask).

    Parameters
    ----------
    probs : array_like
        Probabilities P, any shape.
    tau : float
        The threshold; a pixel equal to tau is foreground.

    Returns
    -------
    numpy.ndarray
        bool, the shape of ``probs``.
    """
    return np.asarray(probs) >= float(tau)


def check_tau(tau, where: str) -> float:
    """Check a threshold given by a user.

    Parameters
    ----------
    tau : object
        The value given.
    where : str
        The option or param that gave it, named in the error.

    Returns
    -------
    float
        ``tau`` as a float in [0, 1].

    Raises
    ------
    InputError
        ``tau`` is not a number, is NaN or lies outside [0, 1].
    """
    try:
        t = float(tau)
    except (TypeError, ValueError):
        raise InputError(f"{where}={tau!r}: not a number") from None
    if not 0.0 <= t <= 1.0 or math.isnan(t):
        raise InputError(f"{where}={tau!r}: must lie in [0, 1]")
    return t


def threshold_grid(cfg: dict) -> np.ndarray:
    """Build the calibration grid: grid_start .. grid_stop (inclusive) by grid_step.

    Values are rounded to 1e-9, so 0.5 lies exactly on the paper's grid.

    Parameters
    ----------
    cfg : dict
        The params ``calibrate`` section (``grid_start``, ``grid_stop``, ``grid_step``).

    Returns
    -------
    numpy.ndarray
        float64, increasing.

    Raises
    ------
    InputError
        ``grid_stop`` < ``grid_start``, or a key is missing or out of range (:func:`pipeline.params.require`).
    """
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
    """Select tau = argmax over ``grid`` of ``curve`` (the paper's rule).

    Tie-break: values within :data:`TIE_TOLERANCE` (1e-12) of the maximum tie; among them the tau closest to 0.5
    wins, then the smaller tau.

    Parameters
    ----------
    grid : array_like
        Thresholds, 1-D.
    curve : array_like
        Mean validation Image IoU at each grid point, the grid's shape.

    Returns
    -------
    float
        The selected tau.

    Raises
    ------
    InputError
        ``grid`` and ``curve`` are not equal-shaped, non-empty 1-D arrays.
    """
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
    """Select the middle of the plateau around the argmax.

    The contiguous run of grid points around :func:`select_tau`'s tau whose curve lies within ``tolerance`` of the
    maximum; its middle point (the lower middle for an even run).  It does not wander over a flat curve as the
    argmax does.

    Parameters
    ----------
    grid : array_like
        Thresholds, 1-D.
    curve : array_like
        Mean validation Image IoU at each grid point.
    tolerance : float
        Width of the plateau below the maximum (``calibrate.plateau_tolerance``).

    Returns
    -------
    float
        The selected tau.

    Raises
    ------
    InputError
        As :func:`select_tau`.
    """
    grid = np.asarray(grid, dtype=np.float64)
    curve = np.asarray(curve, dtype=np.float64)
    best = int(np.flatnonzero(grid == select_tau(grid, curve))[0])
    far = np.flatnonzero(~(curve >= curve.max() - float(tolerance) - TIE_TOLERANCE))
    lo = int(far[far < best].max(initial=-1)) + 1
    hi = int(far[far > best].min(initial=len(grid))) - 1
    return float(grid[lo + (hi - lo) // 2])


def smooth_curve(curve, halfwidth: int) -> np.ndarray:
    """Centred moving average over 2 * ``halfwidth`` + 1 points, the window cut at the ends.

    Parameters
    ----------
    curve : array_like
        Values, 1-D.
    halfwidth : int
        Points on each side; <= 0 returns a copy.

    Returns
    -------
    numpy.ndarray
        float64, the curve's length.
    """
    c = np.asarray(curve, dtype=np.float64)
    h = int(halfwidth)
    if h <= 0:
        return c.copy()
    s = np.concatenate([[0.0], np.cumsum(c)])
    i = np.arange(len(c))
    lo, hi = np.maximum(i - h, 0), np.minimum(i + h + 1, len(c))
    return (s[hi] - s[lo]) / (hi - lo)


def tau_by_rule(grid, curve, rule: str = PAPER.calibrate.tau_rule, *,
                tolerance: float = PAPER.calibrate.plateau_tolerance,
                halfwidth: int = PAPER.calibrate.smooth_halfwidth) -> float:
    """Calibrate tau from a curve by a named rule.

    Parameters
    ----------
    grid : array_like
        Thresholds, 1-D.
    curve : array_like
        Mean validation Image IoU at each grid point.
    rule : {"argmax", "plateau", "smooth"}, optional
        :func:`select_tau` (argmax, the paper's), :func:`plateau_tau`, or :func:`select_tau` of
        :func:`smooth_curve`; ``calibrate.tau_rule`` unless given.
    tolerance : float, optional
        The plateau rule's tolerance (``calibrate.plateau_tolerance`` unless given).
    halfwidth : int, optional
        The smooth rule's half window (``calibrate.smooth_halfwidth`` unless given).

    Returns
    -------
    float
        The calibrated tau.

    Raises
    ------
    InputError
        ``rule`` is not one of :data:`TAU_RULES`, or as :func:`select_tau`.
    """
    if rule == "argmax":
        return select_tau(grid, curve)
    if rule == "plateau":
        return plateau_tau(grid, curve, tolerance)
    if rule == "smooth":
        return select_tau(grid, smooth_curve(curve, halfwidth))
    raise InputError(f"calibrate.tau_rule={rule!r}: expected one of {', '.join(TAU_RULES)}")


def rule_options(cfg) -> dict:
    """Return the keyword arguments of :func:`tau_by_rule` from the params ``calibrate`` section.

    Parameters
    ----------
    cfg : mapping
        The ``calibrate`` section (``tau_rule``, ``plateau_tolerance``, ``smooth_halfwidth``).

    Returns
    -------
    dict
        ``rule``, ``tolerance`` and ``halfwidth``.
    """
    return {"rule": cfg["tau_rule"], "tolerance": cfg["plateau_tolerance"], "halfwidth": cfg["smooth_halfwidth"]}


def _check_batch(probs, where: str) -> None:
    if np.ndim(probs) != 3 or np.shape(probs)[0] == 0:
        raise InputError(f"{where}: expected probs [N,H,W] with N >= 1, got shape {np.shape(probs)}")


def calibrate_threshold(probs, gts, grid, rule: str = PAPER.calibrate.tau_rule, *,
                        tolerance: float = PAPER.calibrate.plateau_tolerance,
                        halfwidth: int = PAPER.calibrate.smooth_halfwidth) -> tuple[float, np.ndarray]:
    """Calibrate tau on the validation split (eq:inference-mask).

    curve[g] = mean over images of the Image IoU of [P >= grid[g]]; tau = :func:`tau_by_rule` of the curve
    (argmax: ties within :data:`TIE_TOLERANCE` go to the tau closest to 0.5, then to the smaller).

    Parameters
    ----------
    probs : array_like
        Validation probabilities, float [N,H,W], N >= 1.
    gts : array_like
        Validation reference masks, bool or 0/1 [N,H,W].
    grid : array_like
        Strictly increasing thresholds (:func:`threshold_grid`).
    rule : str, optional
        A rule of :data:`TAU_RULES` (``calibrate.tau_rule`` unless given: argmax, the paper's).
    tolerance : float, optional
        The plateau rule's tolerance (``calibrate.plateau_tolerance`` unless given).
    halfwidth : int, optional
        The smooth rule's half window (``calibrate.smooth_halfwidth`` unless given).

    Returns
    -------
    tuple
        (tau, curve float64 [G]).

    Raises
    ------
    InputError
        ``probs`` is not [N,H,W] with N >= 1, or as :func:`pipeline.metrics.threshold_counts` and
        :func:`tau_by_rule`.
    """
    grid = np.asarray(grid, dtype=np.float64)
    _check_batch(probs, "calibrate_threshold")
    curve = iou_curve(probs, gts, grid).mean(axis=0)
    return tau_by_rule(grid, curve, rule, tolerance=tolerance, halfwidth=halfwidth), curve


#: the per-image threshold's search (docs/student.md, "A threshold per image"): taus on a 0.01 grid over
#: [0.30, 0.98], which also bounds every tau_i, and slopes b in [-0.6, 0.6] by 0.05 -- fixed before its screens
RELATIVE_TAU_GRID = np.round(np.arange(30, 99) / 100, 9)
RELATIVE_SLOPES = np.round(np.arange(-12, 13) * 0.05, 9)


def image_peaks(probs) -> np.ndarray:
    """Compute the per-image threshold's feature: each image's largest probability, f_i = max_x P_i(x).

    Parameters
    ----------
    probs : array_like
        Probabilities P, float [N,H,W].

    Returns
    -------
    numpy.ndarray
        float64 [N].

    Raises
    ------
    InputError
        ``probs`` is not [N,H,W] with N >= 1.
    """
    _check_batch(probs, "image_peaks")
    return np.asarray(probs, dtype=np.float64).reshape(np.shape(probs)[0], -1).max(axis=1)


def relative_taus(peaks, rule: Mapping[str, float]) -> np.ndarray:
    """Per-image thresholds: tau_i = clip(a + b (f_i - lo) / span, tau_min, tau_max).

    A DEPARTURE from eq:inference-mask's single tau, screened only (docs/student.md, "A threshold per image"):
    with b > 0 an image whose largest probability is lower gets a lower threshold.  ``lo`` and ``span`` are the
    calibration images' 5th percentile of f and its 5th-95th percentile range, so that a and b do not depend on
    the scale of f; [tau_min, tau_max] is :data:`RELATIVE_TAU_GRID`'s range.

    Parameters
    ----------
    peaks : array_like
        f_i, the images' :func:`image_peaks`.
    rule : Mapping
        ``a``, ``b``, ``lo`` and ``span`` (> 0), as :func:`calibrate_relative_threshold` returns them.

    Returns
    -------
    numpy.ndarray
        float64, the shape of ``peaks``.
    """
    f = np.asarray(peaks, dtype=np.float64)
    tau = rule["a"] + rule["b"] * (f - rule["lo"]) / rule["span"]
    return np.clip(tau, RELATIVE_TAU_GRID[0], RELATIVE_TAU_GRID[-1])


def calibrate_relative_threshold(probs, gts, slopes=RELATIVE_SLOPES) -> dict[str, float]:
    """Calibrate :func:`relative_taus` on the validation split, as :func:`calibrate_threshold` calibrates tau.

    (a, b) = argmax over a in :data:`RELATIVE_TAU_GRID` and b in ``slopes`` of the mean Image IoU of
    [P_i >= tau_i], each image's IoU read at the grid tau nearest its tau_i; the first maximum within
    :data:`TIE_TOLERANCE` in (b, a) order.  b = 0 is a single tau, so the rule fits the validation images at least
    as well as a single tau on the same grid.

    Parameters
    ----------
    probs : array_like
        Validation probabilities, float [N,H,W], N >= 1.
    gts : array_like
        Validation reference masks, bool or 0/1 [N,H,W].
    slopes : array_like, optional
        The b values searched (:data:`RELATIVE_SLOPES` unless given).

    Returns
    -------
    dict
        ``a``, ``b``, ``lo``, ``span`` (the rule) and ``iou`` (its mean validation Image IoU).

    Raises
    ------
    InputError
        As :func:`image_peaks` and :func:`pipeline.metrics.iou_curve`.
    """
    grid = RELATIVE_TAU_GRID
    f = image_peaks(probs)
    curve = iou_curve(probs, gts, grid)  # [N, G]
    lo, hi = np.percentile(f, [5, 95])
    span = float(max(hi - lo, 1e-9))
    slopes = np.asarray(slopes, dtype=np.float64)
    rows = np.arange(len(f))
    means = np.empty((len(slopes), len(grid)))
    for j, b in enumerate(slopes):
        tau = np.clip(grid[:, None] + b * (f[None, :] - lo) / span, grid[0], grid[-1])  # [a, N]
        k = np.clip(np.rint((tau - grid[0]) / (grid[1] - grid[0])).astype(int), 0, len(grid) - 1)
        means[j] = curve[rows[None, :], k].mean(axis=1)
    best = int(np.flatnonzero(means.ravel() >= means.max() - TIE_TOLERANCE)[0])
    j, i = divmod(best, len(grid))
    return {"a": float(grid[i]), "b": float(slopes[j]), "lo": float(lo), "span": span, "iou": float(means[j, i])}


def masks_from_relative(probs, rule: Mapping[str, float]) -> np.ndarray:
    """Binarise each image at its own threshold: M_i = [P_i >= tau_i] (:func:`relative_taus`).

    Parameters
    ----------
    probs : array_like
        Probabilities P, float [N,H,W].
    rule : Mapping
        As :func:`relative_taus`.

    Returns
    -------
    numpy.ndarray
        bool [N,H,W].

    Raises
    ------
    InputError
        ``probs`` is not [N,H,W] with N >= 1 (:func:`image_peaks`).
    """
    tau = relative_taus(image_peaks(probs), rule)
    return np.asarray(probs) >= tau[:, None, None]


#: thresholds.parquet ``tau_source`` of a run without validation masks (its tau is ``calibrate.fixed_tau``)
NO_VALIDATION_MASKS = "fixed tau: no validation masks"


#: tau's candidate sources, in :func:`resolve_tau`'s order, with the text naming each
TAU_LABELS = {"option": "--tau", "bundle": "deploy bundle", "checkpoint": "checkpoint payload",
              "thresholds": "thresholds table", "fixed": "calibrate.fixed_tau"}
TAU_SOURCES = tuple(TAU_LABELS)


def resolve_tau(option=None, bundle=None, checkpoint=None, thresholds=None, fixed=None) -> tuple[float, str]:
    """Choose the tau a model runs with: the first candidate given, in :data:`TAU_LABELS` order.

    Order: the ``--tau`` option, the deploy bundle's, the checkpoint payload's, the thresholds table's, then
    ``calibrate.fixed_tau`` (logged as a warning: not calibrated).

    Parameters
    ----------
    option, bundle, checkpoint, thresholds, fixed : float or tuple, optional
        Each None (not given), a number, or ``(number, source text)``; ``(None, text)`` counts as not given.

    Returns
    -------
    tuple
        (tau float in [0, 1], source text).

    Raises
    ------
    InputError
        No candidate is given, or the chosen one is not a number in [0, 1] (:func:`check_tau`).
    """
    for name, value, source in _given(TAU_LABELS, option, bundle, checkpoint, thresholds, fixed):
        tau = check_tau(value, TAU_LABELS[name])
        if name == "fixed":
            log.warning("tau = %s from %s (no calibrated tau)", tau, source)
        return tau, source
    raise InputError("tau: no calibrated tau found; pass --tau or a thresholds table (--thresholds)")


def _given(labels: Mapping[str, str], *candidates):
    """Yield (name, value, source text) of each candidate given (None, a number or ``(number, text)``), in order."""
    for name, cand in zip(labels, candidates):
        if cand is not None and not (isinstance(cand, tuple) and cand[0] is None):
            yield (name, *cand) if isinstance(cand, tuple) else (name, cand, labels[name])


#: the text of a calibrated thresholds row without a ``tau_source`` note
CALIBRATED = "calibrated on the validation split"


def tau_candidates(*, bundle: Mapping | None = None, payload: Mapping | None = None, thresholds=None,
                   params: Mapping | None = None) -> dict[str, tuple[float, str]]:
    """Collect one model's tau candidates for :func:`resolve_tau`.

    The bundle's tau (its deploy.json); a checkpoint payload's tau, else its (method, seed) row of
    ``thresholds``; the fixed tau calibrate recorded in that row, else ``calibrate.fixed_tau`` of ``params``.

    Parameters
    ----------
    bundle : mapping, optional
        A deploy bundle's deploy.json content.
    payload : mapping, optional
        A checkpoint's payload (``method``, ``seed``, maybe ``tau``).
    thresholds : path, artifact or pandas.DataFrame, optional
        The thresholds table; a path that does not exist is ignored.
    params : mapping, optional
        Validated params whose ``calibrate.fixed_tau`` is the last resort.

    Returns
    -------
    dict
        ``{source: (tau, text)}`` with sources among :data:`TAU_SOURCES`.

    Raises
    ------
    ArtifactError
        ``thresholds`` is a path to an existing file that is not a valid thresholds table.
    """
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
    """Return the DataFrame of ``thresholds`` (a path is read only when it exists)."""
    if thresholds is None or hasattr(thresholds, "columns"):
        return thresholds
    if hasattr(thresholds, "df"):
        return thresholds.df
    return open_artifact(thresholds, "thresholds").df if Path(thresholds).exists() else None


#: the working resolution's candidate sources, in :func:`resolve_resolution`'s order, with the text naming each
RESOLUTION_LABELS = {"option": "--resolution", "benchmark": "deploy.benchmark_resolution",
                     "recorded": "the model's recorded resolution", "params": "data.resolution"}
#: the smallest working resolution a model runs at (the student's four 2x poolings need 8 pixels)
MIN_RESOLUTION = 8


def resolve_resolution(option=None, benchmark=None, recorded=None, params=None,
                       missing: str = "resolution: none given or recorded; pass --resolution N") -> tuple[int, str]:
    """Choose the working resolution: the first candidate given, in :data:`RESOLUTION_LABELS` order.

    Order: the ``--resolution`` option, ``deploy.benchmark_resolution``, the model's recorded resolution, then
    ``data.resolution``.

    Parameters
    ----------
    option, benchmark, recorded, params : int or tuple, optional
        Each None, an int, or ``(value, source text)``; ``(None, text)`` counts as not given.
    missing : str, optional
        The error message when none is given.

    Returns
    -------
    tuple
        (resolution int >= :data:`MIN_RESOLUTION`, source text).

    Raises
    ------
    InputError
        The chosen value is not an int >= :data:`MIN_RESOLUTION` (naming its source), or none is given
        (``missing``).
    """
    for _, value, source in _given(RESOLUTION_LABELS, option, benchmark, recorded, params):
        if not isinstance(value, int) or isinstance(value, bool) or value < MIN_RESOLUTION:
            raise InputError(f"{source}: invalid resolution {value!r} (an integer >= {MIN_RESOLUTION})")
        return int(value), source
    raise InputError(missing)
