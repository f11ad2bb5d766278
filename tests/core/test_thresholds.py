"""pipeline.thresholds: eq:inference-mask, the calibration tie rule and the tau precedence rule."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from pipeline import thresholds as T
from pipeline.metrics import image_ious, iou_curve
from pipeline.runtime.errors import InputError


# ---- eq:inference-mask ----------------------------------------------------------------------------
def test_logit_threshold_matches_sigmoid_threshold():
    z = np.linspace(-6, 6, 1001)
    p = 1 / (1 + np.exp(-z))
    for tau in (0.05, 0.3, 0.5, 0.77, 0.95):
        # [Z >= logit(tau)] == [sigmoid(Z) >= tau], up to round-off exactly at tau
        assert np.array_equal(z >= T.logit_threshold(tau), T.mask_from_probs(p, tau) | np.isclose(p, tau))
    assert T.logit_threshold(0.5) == 0.0
    assert T.logit_threshold(0.0) == -np.inf and T.logit_threshold(1.0) == np.inf
    with pytest.raises(InputError):
        T.logit_threshold(1.5)


def test_mask_from_probs_is_inclusive_and_keeps_the_shape():
    p = np.array([[0.2, 0.5], [0.5000001, 0.4999999]], np.float32)
    m = T.mask_from_probs(p, 0.5)
    assert m.dtype == bool and m.shape == p.shape
    assert m.tolist() == [[False, True], [True, False]]  # P = tau is foreground (>=)
    assert T.mask_from_probs(p, 0.0).all() and not T.mask_from_probs(p, 1.0).any()


def test_check_tau_names_the_source():
    assert T.check_tau("0.25", "--tau") == 0.25
    for bad in (-0.1, 1.1, float("nan"), "x", None):
        with pytest.raises(InputError, match="--tau"):
            T.check_tau(bad, "--tau")


# ---- calibration ----------------------------------------------------------------------------------
def test_select_tau_takes_the_argmax_and_breaks_ties_towards_one_half():
    grid = [0.1, 0.3, 0.4, 0.6, 0.7, 0.9]
    assert T.select_tau(grid, [0.1, 0.2, 0.9, 0.3, 0.2, 0.1]) == 0.4        # plain argmax
    assert T.select_tau(grid, [0.9, 0.2, 0.3, 0.3, 0.9, 0.1]) == 0.7        # tie: 0.7 is closer to 0.5
    assert T.select_tau(grid, [0.1, 0.2, 0.8, 0.8, 0.2, 0.1]) == 0.4        # equidistant tie: the smaller tau
    assert T.select_tau(grid, [0.8, 0.8 - 1e-13, 0, 0, 0, 0]) == 0.3        # within TIE_TOLERANCE: a tie
    assert T.select_tau(grid, [0.8, 0.8 - 1e-9, 0, 0, 0, 0]) == 0.1         # beyond it: no tie
    with pytest.raises(InputError):
        T.select_tau([0.5], [0.1, 0.2])


def test_calibrate_threshold_uses_the_tie_rule_on_real_masks():
    # one image whose probabilities separate the mask perfectly for any tau in (0.2, 0.8]
    gts = np.zeros((1, 4, 4), bool)
    gts[0, :2] = True
    probs = np.where(gts, 0.8, 0.2).astype(np.float32)
    tau, curve = T.calibrate_threshold(probs, gts, [0.1, 0.3, 0.45, 0.7, 0.85])
    assert tau == 0.45 and curve.tolist() == [0.5, 1.0, 1.0, 1.0, 0.0]
    # the same as the brute force mean Image IoU of [P >= tau]
    from pipeline.metrics import image_iou

    assert curve[3] == image_iou(T.mask_from_probs(probs[0], 0.7), gts[0])
    with pytest.raises(InputError):
        T.calibrate_threshold(probs[:0], gts[:0], [0.5])


def test_threshold_grid_contains_one_half_and_checks_the_params():
    grid = T.threshold_grid({"grid_start": 0.05, "grid_stop": 0.95, "grid_step": 0.05})
    assert len(grid) == 19 and 0.5 in grid.tolist() and grid[0] == 0.05 and grid[-1] == 0.95
    with pytest.raises(InputError, match="grid_stop"):
        T.threshold_grid({"grid_start": 0.6, "grid_stop": 0.4, "grid_step": 0.05})


# ---- which tau ------------------------------------------------------------------------------------
ALL = {"option": 0.1, "bundle": 0.2, "checkpoint": 0.3, "thresholds": 0.4, "fixed": 0.5}


@pytest.mark.parametrize("drop", range(len(T.TAU_SOURCES)))
def test_resolve_tau_takes_the_first_given_source_in_precedence_order(drop):
    """option > bundle > checkpoint > thresholds > fixed: with the first ``drop`` sources absent, the
    next one wins, whatever the sources after it say."""
    given = {k: (None if i < drop else v) for i, (k, v) in enumerate(ALL.items())}
    tau, source = T.resolve_tau(**given)
    winner = T.TAU_SOURCES[drop]
    assert tau == ALL[winner] and source == T.TAU_LABELS[winner]


def test_resolve_tau_source_texts_and_absent_tuples():
    assert T.resolve_tau(thresholds=(0.42, "calibrated (t.parquet: plain, seed 1)"), fixed=(0.5, "fixed")) == \
        (0.42, "calibrated (t.parquet: plain, seed 1)")
    # a candidate (None, text) is absent: the next one wins
    assert T.resolve_tau(bundle=(None, "bundle"), thresholds=(None, "no row"), fixed=(0.5, "fallback")) == \
        (0.5, "fallback")
    assert T.resolve_tau(option=0.0, bundle=0.9) == (0.0, "--tau")  # 0 is a value, not absent


def test_resolve_tau_warns_on_the_fixed_fallback_and_refuses_nothing_or_bad_values(caplog):
    with caplog.at_level(logging.WARNING, logger="pipeline.thresholds"):
        assert T.resolve_tau(fixed=0.5) == (0.5, "calibrate.fixed_tau")
    assert "no calibrated tau" in caplog.text
    with pytest.raises(InputError, match="no calibrated tau"):
        T.resolve_tau()
    with pytest.raises(InputError, match="--tau"):
        T.resolve_tau(option=1.5, bundle=0.5)  # an invalid higher-precedence value is an error, not skipped


# ---- a threshold per image (a departure, screened: docs/student.md, "A threshold per image") ----------------
def _halo_images(peaks, side=16):
    """Each image: a spacecraft square at probability f_i, a halo ring around it at f_i - 0.2, background at 0.
    The reference is the square, so image i is segmented exactly by any tau in (f_i - 0.2, f_i]."""
    probs, gts = [], []
    for f in peaks:
        p = np.zeros((side, side))
        p[2:14, 2:14] = f - 0.2
        p[5:11, 5:11] = f
        probs.append(p)
        gts.append(p == f)
    return np.stack(probs), np.stack(gts)


def test_relative_taus_follow_the_formula_and_stay_on_the_grid():
    rule = {"a": 0.5, "b": 0.2, "lo": 0.8, "span": 0.1}
    peaks = np.array([0.8, 0.85, 0.9, 5.0, -5.0])
    tau = T.relative_taus(peaks, rule)
    assert tau[:3] == pytest.approx([0.5, 0.6, 0.7])
    # clipped to the search grid's range, so that no image is thresholded where calibration never looked
    assert tau[3] == T.RELATIVE_TAU_GRID[-1] and tau[4] == T.RELATIVE_TAU_GRID[0]
    probs = np.stack([np.full((2, 2), 0.55), np.full((2, 2), 0.55)])
    masks = T.masks_from_relative(probs, {"a": 0.5, "b": 0.0, "lo": 0.0, "span": 1.0})
    assert masks.dtype == bool and masks.shape == probs.shape and masks.all()
    assert not T.masks_from_relative(probs, {"a": 0.6, "b": 0.0, "lo": 0.0, "span": 1.0}).any()


def test_the_relative_rule_segments_what_no_single_tau_can():
    peaks = np.linspace(0.55, 0.95, 9)  # image i is exact for tau in (f_i - 0.2, f_i]: no common tau
    probs, gts = _halo_images(peaks)
    rule = T.calibrate_relative_threshold(probs, gts)
    assert rule["b"] > 0 and rule["iou"] == pytest.approx(1.0)
    assert image_ious(T.masks_from_relative(probs, rule), gts).min() == pytest.approx(1.0)
    assert np.array_equal(T.image_peaks(probs), peaks)
    # b = 0 is a single tau: its fit is the single-tau curve's best on the same grid, and below the rule's
    single = T.calibrate_relative_threshold(probs, gts, slopes=[0.0])
    curve = iou_curve(probs, gts, T.RELATIVE_TAU_GRID).mean(axis=0)
    assert single["b"] == 0.0 and single["iou"] == pytest.approx(curve.max()) and single["iou"] < 0.99
    assert single["a"] == pytest.approx(T.RELATIVE_TAU_GRID[int(np.argmax(curve))])


def test_image_peaks_refuses_a_batch_that_is_not_n_h_w():
    with pytest.raises(InputError, match="image_peaks"):
        T.image_peaks(np.zeros((4, 4)))
