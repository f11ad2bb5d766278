"""Distillation efficiency: student Image IoU / teacher-vote Image IoU per test group, with a per-seed
ratio t interval (pipeline/report/dvc_results.py), in the report's reference-points table and as metrics."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from pipeline.report.dvc_results import distillation_efficiency, efficiency_metric_files


def test_efficiency_is_the_ratio_of_the_seed_mean_with_a_per_seed_ratio_t_interval():
    per_seed = [0.50, 0.52, 0.55, 0.49, 0.54]
    vote = 0.62
    s = pd.Series(per_seed)
    e, lo, hi = distillation_efficiency(s.mean(), s.std(ddof=1), len(s), vote)
    ratios = pd.Series([x / vote for x in per_seed])
    t = 2.7764451051977987  # t_{4, 0.975}
    half = t * ratios.std(ddof=1) / math.sqrt(5)
    assert e == pytest.approx(ratios.mean()) and e == pytest.approx(s.mean() / vote)
    assert (lo, hi) == (pytest.approx(e - half), pytest.approx(e + half))
    e1, lo1, hi1 = distillation_efficiency(0.5, float("nan"), 1, 0.6)  # one seed: no interval
    assert e1 == pytest.approx(0.5 / 0.6) and math.isnan(lo1) and math.isnan(hi1)
    assert all(math.isnan(x) for x in distillation_efficiency(0.5, 0.01, 3, float("nan")))
    assert all(math.isnan(x) for x in distillation_efficiency(0.5, 0.01, 3, 0.0))


def _summary():
    rows = []
    for g, vals in (("KCP", (0.51, 0.02, 0.57, 0.01)), ("HJM", (0.49, 0.03, 0.54, 0.02))):
        for m, (mean, std) in (("plain", vals[:2]), ("supervised_ceiling", vals[2:])):
            for mode in ("calibrated", "fixed"):
                rows.append({"dataset": "synthetic", "group": g, "method": m, "threshold_mode": mode,
                             "iou_mean": mean - (0.05 if mode == "fixed" else 0), "iou_std": std, "bf1_mean": 0.5,
                             "bf1_std": 0.01, "precision_mean": 0.6, "precision_std": 0.01, "recall_mean": 0.7,
                             "recall_std": 0.01, "n_seeds": 5})
    return pd.DataFrame(rows)


def _vote():
    return pd.DataFrame({"iou": [0.6, 0.7], "bf1": [0.5, 0.5], "precision": [0.6, 0.6], "recall": [0.7, 0.7]},
                        index=["KCP", "HJM"])


def _column(header: str):
    """The calibrated reference-points table of :func:`_summary`, its ``header`` column as {(group, name): cell}."""
    from pipeline.report.tables import reference_points_table

    tab = reference_points_table(_summary(), _vote(), "calibrated", ["KCP", "HJM"])
    col = tab.header.index(header)
    return tab, {(r[0], r[1]): r[col] for r in tab.rows}


def test_metric_files_hold_every_method_and_group_with_a_vote():
    files = efficiency_metric_files(_summary(), {"KCP": 0.6})
    assert sorted(files) == ["KCP/plain.json", "KCP/supervised_ceiling.json"]  # HJM has no vote here
    assert files["KCP/plain.json"]["efficiency"] == round(0.51 / 0.6, 4)
    # the ratio only: the interval is the report's, so `dvc metrics show` stays narrow (pipeline.report.dvc_results)
    assert files["KCP/supervised_ceiling.json"] == {"efficiency": round(0.57 / 0.6, 4)}


def test_reference_points_table_shows_the_efficiency_of_students_and_ceiling():
    _, cells = _column("IoU ÷ vote")
    plain = next(v for (g, name), v in cells.items() if g == "HJM" and "Plain" in name)
    e, lo, hi = distillation_efficiency(0.49, 0.03, 5, 0.7)
    assert plain == f"{e:.2f} [{lo:.2f}, {hi:.2f}]"
    assert sum(v.startswith(f"{0.57 / 0.6:.2f}") for v in cells.values()) == 1  # the ceiling on KCP
    assert any("vote" in name.lower() and v == "1" for (_, name), v in cells.items())


def test_targets_judge_the_ratio_or_the_interval_and_the_table_says_how_many_groups_meet_them():
    from pipeline.report.dvc_results import EFFICIENCY_TARGETS, efficiency_target_met
    from pipeline.report.tables import reference_points_table

    assert efficiency_target_met("plain", 0.96, 0.80) is True        # on the ratio
    assert efficiency_target_met("plain", 0.94, 0.90) is False
    assert efficiency_target_met("supervised_ceiling", 1.05, 0.99) is False  # "clearly above": the interval
    assert efficiency_target_met("supervised_ceiling", 1.05, 1.01) is True
    assert efficiency_target_met("supervised_ceiling", 1.05, float("nan")) is None  # one seed: not judged
    assert efficiency_target_met("continuation", 2.0, 2.0) is None
    assert set(EFFICIENCY_TARGETS) == {"plain", "geodistill", "supervised_ceiling"}

    summary = _summary()
    geo = summary[summary["method"] == "plain"].assign(method="geodistill", iou_mean=0.65)
    vote = _vote()
    tab = reference_points_table(pd.concat([summary, geo]), vote, "calibrated", ["KCP", "HJM"])
    assert sum("GeoDistill" in r[1] for r in tab.rows) == 2           # the proposed student has its ratio too
    note = next(n for n in tab.notes if n.startswith("Targets"))
    # plain 0.51/0.6 = 0.85 and 0.49/0.7 = 0.70: below 0.95 on both; geodistill 0.65/0.6 >= 1 on KCP only;
    # the ceiling's intervals (0.57 +- 0.01, 0.54 +- 0.02 over 5 seeds) are below 1 x the vote on both
    assert "≥ 0.95 × the vote: met on 0 of 2 groups" in note
    assert "≥ 1.00 × the vote: met on 1 of 2 groups" in note
    assert "interval above 1.00 × the vote: met on 0 of 2 groups" in note


def test_seed_ratio_against_a_seedless_reference_is_the_efficiency_and_reference_noise_widens_it():
    from pipeline.report.dvc_results import seed_ratio

    assert seed_ratio(0.5, 0.02, 5, 0.62) == pytest.approx(distillation_efficiency(0.5, 0.02, 5, 0.62))
    r, lo, hi = seed_ratio(0.5, 0.02, 5, 0.6, 0.03, 4)
    _, lo0, hi0 = seed_ratio(0.5, 0.02, 5, 0.6)
    assert r == pytest.approx(0.5 / 0.6) and hi - lo > hi0 - lo0  # both runs' seed noise, t with 3 dof
    t3 = 3.182446305284263  # t_{3, 0.975}
    half = t3 * math.sqrt(0.02 ** 2 / 5 + r ** 2 * 0.03 ** 2 / 4) / 0.6
    assert (lo, hi) == (pytest.approx(r - half), pytest.approx(r + half))
    assert math.isnan(seed_ratio(0.5, 0.02, 5, 0.6, 0.03, 1)[1])  # a one-seed ceiling: no interval


def test_seed_ratio_interval_covers_the_true_ratio_at_about_its_level():
    from pipeline.report.dvc_results import seed_ratio

    rng = np.random.default_rng(0)
    a = rng.normal(0.5, 0.03, (2000, 5))
    b = rng.normal(0.6, 0.03, (2000, 5))
    hits = [lo <= 0.5 / 0.6 <= hi for lo, hi in (seed_ratio(x.mean(), x.std(ddof=1), 5, y.mean(), y.std(ddof=1), 5)[1:]
                                              for x, y in zip(a, b))]
    assert 0.93 <= np.mean(hits) <= 0.995


def test_reference_points_table_splits_the_gap_into_label_cost_and_generalization():
    from pipeline.report.dvc_results import seed_ratio

    tab, cells = _column("Label cost")
    plain = next(v for (g, name), v in cells.items() if g == "KCP" and "Plain" in name)
    r, lo, hi = seed_ratio(0.51, 0.02, 5, 0.57, 0.01, 5)
    assert plain == f"{r:.2f} [{lo:.2f}, {hi:.2f}]"
    assert all(v == "--" for (_, name), v in cells.items() if "Plain" not in name)  # ceiling and vote rows
    assert any("label cost = Plain ÷ ceiling" in n and "generalization = ceiling ÷ vote" in n for n in tab.notes)
