"""Threshold and calibration diagnostics (issue 17 item 3): the pure functions of pipeline.evaluation.diagnostics
against hand-computed values, the per-epoch swing table, the findings stated in words (computed, not
fixed), and the figure conventions (one colour per method, legends never cut)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from pipeline.evaluation.diagnostics import (area_ratio_curve, expected_calibration_error, median_area_ratio, reliability_bins,
                                  target_fractions, target_size_class)
from pipeline.runtime.errors import InputError
from pipeline.report import figures as F
from pipeline.report.analysis import epoch_swings, fixed_tau_findings


# ---- reliability diagram and ECE ---------------------------------------------------------------
def test_reliability_bins_by_hand():
    # 8 pixels: probabilities and truth chosen so each bin's numbers are easy to state
    p = np.array([[[0.05, 0.15, 0.15, 0.55], [0.65, 0.95, 0.95, 1.0]]])
    g = np.array([[[0, 0, 1, 0], [1, 1, 0, 1]]], bool)
    r = reliability_bins(p, g, n_bins=4)          # bins [0,.25) [.25,.5) [.5,.75) [.75,1]
    np.testing.assert_allclose(r.edges, [0, 0.25, 0.5, 0.75, 1.0])
    assert r.count.tolist() == [3, 0, 2, 3]       # P = 1 falls in the last bin
    np.testing.assert_allclose(r.confidence[[0, 2, 3]], [(0.05 + 0.15 + 0.15) / 3, 0.6, (0.95 + 0.95 + 1.0) / 3])
    np.testing.assert_allclose(r.frequency[[0, 2, 3]], [1 / 3, 0.5, 2 / 3])
    assert np.isnan(r.confidence[1]) and np.isnan(r.frequency[1])
    # ECE = sum n_b/N |freq - conf| = 3/8*|1/3-0.35/3| + 2/8*|0.5-0.6| + 3/8*|2/3-2.9/3|
    want = 3 / 8 * abs(1 / 3 - 0.35 / 3) + 2 / 8 * 0.1 + 3 / 8 * abs(2 / 3 - 2.9 / 3)
    assert expected_calibration_error(r.confidence, r.frequency, r.count) == pytest.approx(want)
    # chunking does not change anything
    many = np.repeat(p, 5, axis=0), np.repeat(g, 5, axis=0)
    r5 = reliability_bins(*many, n_bins=4, chunk=2)
    assert r5.count.tolist() == [15, 0, 10, 15]
    np.testing.assert_allclose(r5.frequency[[0, 2, 3]], r.frequency[[0, 2, 3]])


def test_ece_edge_cases_and_errors():
    # a perfectly calibrated predictor: every bin's frequency equals its confidence
    assert expected_calibration_error([0.25, 0.75], [0.25, 0.75], [4, 4]) == 0.0
    assert np.isnan(expected_calibration_error([np.nan], [np.nan], [0]))
    with pytest.raises(InputError, match="in \\[0, 1\\]"):
        reliability_bins(np.full((1, 2, 2), 1.5), np.zeros((1, 2, 2), bool))
    with pytest.raises(InputError, match="shapes"):
        reliability_bins(np.zeros((1, 2, 2)), np.zeros((1, 2, 3), bool))


# ---- foreground area across tau ------------------------------------------------------------------
def test_area_ratio_curve_by_hand():
    p = np.array([[[0.2, 0.4, 0.6, 0.8]], [[0.9, 0.9, 0.1, 0.1]], [[0.7, 0.7, 0.7, 0.7]]])
    g = np.array([[[1, 1, 0, 0]], [[1, 0, 0, 0]], [[0, 0, 0, 0]]], bool)
    curve = area_ratio_curve(p, g, [0.3, 0.5, 0.85])
    # image 0: |P>=.3| = 3, |P>=.5| = 2, |P>=.85| = 0 over |G| = 2; image 1: 2, 2, 2 over 1; image 2: empty G
    np.testing.assert_allclose(curve[0], [1.5, 1.0, 0.0])
    np.testing.assert_allclose(curve[1], [2.0, 2.0, 2.0])
    assert np.isnan(curve[2]).all()
    # inclusive threshold (eq:inference-mask: P >= tau)
    assert area_ratio_curve(p[:1], g[:1], [0.6])[0, 0] == 1.0
    np.testing.assert_allclose(median_area_ratio(curve), [1.75, 1.5, 1.0])
    assert np.isnan(median_area_ratio(curve[2:])).all()
    with pytest.raises(InputError, match="increasing"):
        area_ratio_curve(p, g, [0.5, 0.3])


def test_target_size_classes():
    g = np.zeros((3, 10, 100), bool)
    g[0, 0, :1] = True          # 1 / 1000 = 0.1 % -> tiny
    g[1, :, :5] = True          # 5 % -> regular
    f = target_fractions(g)
    np.testing.assert_allclose(f, [0.001, 0.05, 0.0])
    assert target_size_class(f, 0.002).tolist() == ["tiny", "regular", "empty"]
    assert target_size_class([0.002], 0.002).tolist() == ["regular"]   # strictly under the limit


# ---- per-epoch swings ------------------------------------------------------------------------------
def test_epoch_swings_by_hand():
    logs = pd.DataFrame({
        "method": ["plain"] * 4 + ["plain"] * 3, "stage": [1] * 7, "seed": [1] * 4 + [2] * 3,
        "epoch": [1, 2, 3, 4, 1, 2, 3],
        "val_iou": [0.10, 0.40, 0.35, 0.45, 0.20, 0.25, 0.20],
        "val_iou_cal": [0.30, 0.42, 0.40, 0.46, 0.30, 0.31, 0.30],
        "val_tau_cal": [0.6, 0.7, 0.8, 0.7, 0.6, 0.6, 0.9]})
    r = epoch_swings(logs).iloc[0]
    assert r["max_swing"] == pytest.approx(0.30) and (r["max_seed"], r["max_epoch"]) == (1, 2)
    # |diffs| at 0.5: .30 .05 .10 (seed 1), .05 .05 (seed 2) -> median .05
    assert r["median_swing"] == pytest.approx(0.05)
    assert r["max_swing_cal"] == pytest.approx(0.12)
    assert (r["tau_min"], r["tau_max"]) == (0.6, 0.9)


# ---- findings in words ----------------------------------------------------------------------------
def _summary(bf1_cal, bf1_fix, groups=("KCP", "CVI"), half_width=0.02):
    """Gains with CIs of +-``half_width`` on five seeds (the verdicts come from the intervals)."""
    rows = []
    for mode, gains in (("calibrated", bf1_cal), ("fixed", bf1_fix)):
        for g, gain in zip(groups, gains):
            rows.append(dict(group=g, method="plain", threshold_mode=mode, iou_mean=0.45, iou_std=0.01))
            rows.append(dict(group=g, method="geodistill", threshold_mode=mode, iou_mean=0.47, iou_std=0.01,
                             gain_iou=0.02, gain_iou_lo=0.02 - half_width, gain_iou_hi=0.02 + half_width,
                             gain_bf1=gain, gain_bf1_lo=gain - half_width, gain_bf1_hi=gain + half_width,
                             gain_seeds=5))
    return pd.DataFrame(rows)


def _metrics(area_geo_fixed):
    rows = []
    for method, fixed, cal in (("plain", 1.4, 1.2), ("geodistill", area_geo_fixed, 1.15)):
        for mode, v in (("fixed", fixed), ("calibrated", cal)):
            rows += [dict(method=method, threshold_mode=mode, area_vs_reference=v)] * 3
    return pd.DataFrame(rows)


def test_findings_are_computed_from_the_numbers():
    thr = pd.DataFrame({"method": ["plain", "plain", "geodistill", "geodistill"], "seed": [1, 2, 1, 2],
                        "tau": [0.6, 0.64, 0.8, 0.84], "ece": [0.02, 0.03, 0.06, 0.07]})
    text = " ".join(fixed_tau_findings(_summary([0.04, 0.05], [-0.07, -0.12]), thr, _metrics(1.8), None, None,
                                       ["KCP", "CVI"], fixed_tau=0.5))
    assert "0.82 (mean over seeds), higher than plain's 0.62 (difference +0.20)" in text
    assert "fixed tau = 0.5 -0.070 (CI below 0), -0.120 (CI below 0)" in text
    assert "calibrated tau +0.040 (CI above 0), +0.050 (CI above 0)" in text
    # these intervals are unadjusted and floor-free: the verdict words belong to the claim tables alone
    assert "(gain supported)" not in text and "(loss supported)" not in text
    assert "geodistill 1.80 at 0.5 and 1.15 at its calibrated tau" in text
    assert "reversal is present and is a threshold effect" in text
    # the ECE sentence follows its t interval over the shared seeds: +0.04 at both seeds -> worse
    assert "geodistill is worse calibrated" in text
    noisy = thr.assign(ece=[0.02, 0.09, 0.06, 0.03])   # per-seed differences +0.04, -0.06: the CI covers 0
    text_ece = " ".join(fixed_tau_findings(None, noisy, None, None, None, ["KCP"], fixed_tau=0.5))
    assert "no difference in pixel-level calibration detected" in text_ece and "worse" not in text_ece
    # other numbers, other verdicts: no reversal when the fixed-tau gain stays positive
    text = " ".join(fixed_tau_findings(_summary([0.04, 0.05], [0.01, 0.02]), thr, _metrics(1.8), None, None,
                                       ["KCP", "CVI"], fixed_tau=0.5))
    assert "No fixed-tau reversal" in text and "threshold effect" not in text
    # negative point estimates whose CIs cover 0 are no reversal: a majority of signs decides nothing
    text = " ".join(fixed_tau_findings(_summary([0.04, 0.05], [-0.01, -0.015]), thr, _metrics(1.8), None, None,
                                       ["KCP", "CVI"], fixed_tau=0.5))
    assert "No fixed-tau reversal detected" in text and "threshold effect" not in text
    # a reversal without foreground inflation is not explained by the threshold
    text = " ".join(fixed_tau_findings(_summary([0.04, 0.05], [-0.07, -0.12]), thr, _metrics(1.0), None, None,
                                       ["KCP", "CVI"], fixed_tau=0.5))
    assert "without foreground inflation at 0.5" in text


def test_the_words_about_the_fixed_tau_quote_the_recorded_value():
    """The fixed tau in the findings and the tables is calibrate.fixed_tau as the run recorded it
    (thresholds.parquet, else the fixed-mode rows of metrics.parquet), never a number of the report's own."""
    from types import SimpleNamespace

    from pipeline.report import tables as T
    from pipeline.report.build import recorded_fixed_tau

    thr = pd.DataFrame({"method": ["plain", "geodistill"], "tau": [0.6, 0.8], "ece": [0.02, 0.06]})
    text = " ".join(fixed_tau_findings(_summary([0.04, 0.05], [-0.07, -0.12]), thr, _metrics(1.8), None, None,
                                       ["KCP", "CVI"], fixed_tau=0.35))
    assert "fixed tau = 0.35 -0.070" in text and "1.80 at 0.35 and" in text and "at tau = 0.35 it inflates" in text
    assert "0.5" not in text
    # unknown (no artifact recorded it): the param is named instead of a value
    text = " ".join(fixed_tau_findings(_summary([0.04, 0.05], [-0.07, -0.12]), thr, _metrics(1.8), None, None,
                                       ["KCP", "CVI"]))
    assert "fixed tau = `calibrate.fixed_tau` -0.070" in text
    assert T.mode_text("fixed", 0.35) == "fixed tau = 0.35" and T.mode_text("fixed", 0.5) == "fixed tau = 0.5"
    assert "Val IoU at 0.35" in T.calibration_table(thr, 0.35).header
    art = lambda df: SimpleNamespace(df=df)  # noqa: E731  (an opened artifact: its table)
    assert recorded_fixed_tau(art(thr.assign(fixed_tau=0.35)), None) == 0.35
    metrics = pd.DataFrame({"threshold_mode": ["fixed", "calibrated"], "tau": [0.4, 0.7]})
    assert recorded_fixed_tau(None, art(metrics)) == 0.4 and recorded_fixed_tau(art(thr), None) is None


# ---- figures --------------------------------------------------------------------------------------
def test_one_distinct_style_per_method():
    """Series styles are fields of the method table: no two methods share a colour or a symbol, the
    colours are far apart, ablations are dashed, and the figures read exactly these fields."""
    from matplotlib.colors import to_rgb
    from matplotlib.lines import Line2D

    from pipeline.methods import METHODS

    colours = [np.array(to_rgb(m.color)) * 255 for m in METHODS.values()]
    d = min(np.linalg.norm(a - b) for i, a in enumerate(colours) for b in colours[i + 1:])
    assert d > 50  # no two methods alike (ablations are additionally dashed)
    assert len({m.symbol for m in METHODS.values()}) == len(METHODS)
    assert all(m.dash in Line2D.lineStyles or m.dash in ("solid", "dashed", "dashdot", "dotted")
               for m in METHODS.values())
    for name, m in METHODS.items():
        assert F.method_style(name) == {"color": m.color, "style": m.dash, "symbol": m.symbol, "key": name}
    assert F.method_style("no_gate")["style"] == "dashed" and F.method_style("geodistill")["style"] == "solid"
    # the budget-matched control is told apart from GeoDistill-Refine by more than its colour
    assert F.method_style("continuation")["style"] != F.method_style("geodistill")["style"]
    assert F.method_style("teacher_vote")["color"] == F.UNKNOWN_METHOD["color"]


def test_legend_labels_are_never_cut():
    """16 long legend labels: every label's text lies inside the saved image (the PNG grows to hold it)."""
    import cv2

    from pipeline.methods import METHODS

    long = "Supervised ceiling (uses reference masks; not annotation-free)"
    series = [{"x": [0, 1], "y": [0.1 * i, 0.2], "label": f"{long} {i}", **F.method_style(m)}
              for i, m in enumerate(METHODS)]
    fig = F.line_plot(series, "t", "x", "y")
    fig.canvas.draw()
    legend = fig.axes[0].get_legend()
    texts = legend.get_texts()
    assert [t.get_text() for t in texts] == [s["label"] for s in series]   # every entry is there
    tight = fig.get_tightbbox()                                             # inches: what savefig keeps
    right = max(t.get_window_extent().x1 for t in texts) / fig.dpi
    bottom = min(t.get_window_extent().y0 for t in texts) / fig.dpi
    assert right <= tight.x1 + 1e-6 and bottom >= tight.y0 - 1e-6
    png = cv2.imdecode(np.frombuffer(F.png_bytes(fig), np.uint8), cv2.IMREAD_COLOR)
    assert png.shape[1] >= (tight.x1 - tight.x0) * F.PNG_DPI - 2             # the file is that wide
    # legible text: ticks and legend at 8.5 pt or more
    assert min(F.CHART_FONT.values()) >= 8.5
