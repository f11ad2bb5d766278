"""Seed aggregation, paired hierarchical bootstrap and Spearman (pipeline.stats)."""

import numpy as np
import pandas as pd
import pytest
from scipy import stats as sps

from pipeline.stats import (SEED_BOOTSTRAP, SEED_IMAGE_T, average_ranks, hierarchical_resample_means, method_gains,
                            paired_hierarchical_bootstrap, paired_seed_image_t, seed_summary, spearman)


# ---------------------------------------------------------------------------------------- seeds
def test_seed_summary_mean_and_sample_std_of_per_seed_means():
    # seed 1 images: 0.2, 0.4 (mean 0.3); seed 2: 0.5, 0.7, 0.9 (mean 0.7) -> mean 0.5, std sqrt(0.08)
    df = pd.DataFrame({
        "group": ["A"] * 5, "method": ["m"] * 5, "seed": [1, 1, 2, 2, 2],
        "iou": [0.2, 0.4, 0.5, 0.7, 0.9], "bf1": [1.0, np.nan, 0.0, 0.0, 0.0],
    })
    out = seed_summary(df, ["group", "method"], ["iou", "bf1"])
    assert len(out) == 1
    r = out.iloc[0]
    assert r.n_seeds == 2 and r.n_images == 3
    assert r.iou_mean == pytest.approx(0.5)
    assert r.iou_std == pytest.approx(np.std([0.3, 0.7], ddof=1))
    # NaN is skipped inside a seed: seed 1 bf1 mean is 1.0, seed 2 is 0.0
    assert r.bf1_mean == pytest.approx(0.5)


def test_seed_summary_single_seed_std_is_nan_not_zero():
    df = pd.DataFrame({"group": ["A", "A"], "seed": [42, 42], "iou": [0.1, 0.3]})
    r = seed_summary(df, ["group"], ["iou"]).iloc[0]
    assert r.iou_mean == pytest.approx(0.2)
    assert np.isnan(r.iou_std)


# ------------------------------------------------------------------------------------ bootstrap
def test_resample_means_respect_clusters():
    # two clusters with constant values 0 and 1: every resample mean is a mix of whole clusters'
    # weight, so with equal sizes the only possible means are 0, 0.5 and 1
    values = np.array([0.0] * 4 + [1.0] * 4)
    clusters = np.array([0] * 4 + [1] * 4)
    boot = hierarchical_resample_means(values, clusters, 500, np.random.default_rng(0))[:, 0]
    assert set(np.round(boot, 6)) <= {0.0, 0.5, 1.0}
    assert {0.0, 0.5, 1.0} <= set(np.round(boot, 6))
    # unequal cluster sizes: the mean is weighted by the drawn images, values stay within [0, 1]
    clusters = np.array([0] * 2 + [1] * 6)
    boot = hierarchical_resample_means(values, clusters, 500, np.random.default_rng(1))[:, 0]
    assert boot.min() >= 0.0 and boot.max() <= 1.0


def test_bootstrap_is_seeded_and_paired():
    rng = np.random.default_rng(3)
    ctrl = rng.random(30)
    treat = ctrl + 0.1           # a perfectly constant paired difference: zero-width interval
    clusters = np.repeat(np.arange(5), 6)
    res = paired_hierarchical_bootstrap(treat, ctrl, clusters, n_resamples=300, seed=1)
    assert res.estimate == pytest.approx(0.1)
    assert res.low == pytest.approx(0.1) and res.high == pytest.approx(0.1)
    # same seed, same data -> identical interval; other seed -> (almost surely) different
    t = ctrl + rng.normal(0, 0.1, 30)
    r1 = paired_hierarchical_bootstrap(t, ctrl, clusters, n_resamples=300, seed=5)
    r2 = paired_hierarchical_bootstrap(t, ctrl, clusters, n_resamples=300, seed=5)
    r3 = paired_hierarchical_bootstrap(t, ctrl, clusters, n_resamples=300, seed=6)
    assert (r1.low, r1.high) == (r2.low, r2.high)
    assert (r1.low, r1.high) != (r3.low, r3.high)


def _simulate(rng, n_clusters, true_diff, cluster_sd, image_sd):
    sizes = rng.integers(5, 16, size=n_clusters)
    clusters = np.repeat(np.arange(n_clusters), sizes)
    base = rng.random(len(clusters))                              # cancels in the paired difference
    effect = true_diff + rng.normal(0, cluster_sd, n_clusters)[clusters] + rng.normal(0, image_sd, len(clusters))
    return base + effect, base, clusters


def test_bootstrap_interval_covers_true_difference_at_nominal_rate():
    """200 simulated datasets (spacecraft-level and image-level noise); the 95 % interval should
    contain the true mean difference in about 95 % of them.  Twenty clusters: the percentile cluster
    bootstrap is slightly liberal with few clusters, so the accepted band is [0.88, 0.99]
    (binomial sd at 0.95 and n = 200 is 0.015)."""
    rng = np.random.default_rng(2026)
    true_diff = 0.05
    hits = 0
    n_sims = 200
    for i in range(n_sims):
        t, c, cl = _simulate(rng, 20, true_diff, cluster_sd=0.04, image_sd=0.08)
        res = paired_hierarchical_bootstrap(t, c, cl, n_resamples=1000, ci=0.95, seed=i)
        hits += res.low <= true_diff <= res.high
    rate = hits / n_sims
    assert 0.88 <= rate <= 0.99, rate


def test_ignoring_the_hierarchy_would_undercover():
    """The spacecraft level matters: with strong spacecraft effects, treating the images as
    independent (every image its own cluster) gives intervals that are far too narrow."""
    rng = np.random.default_rng(11)
    hits_h = hits_iid = 0
    for i in range(100):
        t, c, cl = _simulate(rng, 8, 0.0, cluster_sd=0.1, image_sd=0.02)
        h = paired_hierarchical_bootstrap(t, c, cl, n_resamples=500, seed=i)
        iid = paired_hierarchical_bootstrap(t, c, np.arange(len(cl)), n_resamples=500, seed=i)
        hits_h += h.low <= 0 <= h.high
        hits_iid += iid.low <= 0 <= iid.high
        assert h.high - h.low > iid.high - iid.low
    assert hits_iid < 60 < hits_h


def test_bootstrap_multi_column_and_errors():
    rng = np.random.default_rng(0)
    c = rng.random((20, 2))
    t = c + np.array([0.1, -0.2])
    res = paired_hierarchical_bootstrap(t, c, np.repeat(np.arange(4), 5), n_resamples=100)
    np.testing.assert_allclose(res.estimate, [0.1, -0.2])
    with pytest.raises(ValueError):
        paired_hierarchical_bootstrap(t[:5], c, np.arange(20))
    with pytest.raises(ValueError):
        paired_hierarchical_bootstrap(np.full(3, np.nan), np.zeros(3), np.arange(3))


def test_method_gains_pairs_shared_seeds_and_images():
    rows = []
    for seed in (1, 2):
        for i in range(12):
            sc = i // 4
            rows.append(dict(dataset="d", group="G", threshold_mode="calibrated", method="plain", seed=seed,
                             image_id=f"im{i}", spacecraft=f"s{sc}", iou=0.5, bf1=0.4))
            rows.append(dict(dataset="d", group="G", threshold_mode="calibrated", method="geo", seed=seed,
                             image_id=f"im{i}", spacecraft=f"s{sc}", iou=0.5 + 0.1 * seed, bf1=0.4))
    # an ablation with only seed 1 is compared with the seed-1 control
    for i in range(12):
        rows.append(dict(dataset="d", group="G", threshold_mode="calibrated", method="abl", seed=1,
                         image_id=f"im{i}", spacecraft=f"s{i // 4}", iou=0.45, bf1=np.nan if i < 6 else 0.5))
    df = pd.DataFrame(rows)
    g = method_gains(df, ["iou", "bf1"], n_resamples=200, interval="seed_bootstrap").set_index("method")
    assert set(g.index) == {"geo", "abl"}
    assert g["gain_iou_p"].isna().all()   # the bootstrap has no p-value
    assert g.loc["geo", "gain_iou"] == pytest.approx(0.15)          # mean over seeds of (0.1, 0.2)
    assert g.loc["geo", "gain_seeds"] == 2 and g.loc["geo", "gain_images"] == 12
    assert g.loc["abl", "gain_iou"] == pytest.approx(-0.05)
    assert g.loc["abl", "gain_seeds"] == 1
    assert g.loc["abl", "gain_bf1"] == pytest.approx(0.1)          # NaN images left out
    # every image gains 0.1 at seed 1 and 0.2 at seed 2: no image-level spread, but the seeds disagree,
    # so the seed level spans them (the seed-averaged interval of the old bootstrap collapsed to 0.15)
    assert g.loc["geo", "gain_iou_lo"] == pytest.approx(0.1)
    assert g.loc["geo", "gain_iou_hi"] == pytest.approx(0.2)
    assert g.loc["geo", "gain_iou_seed_sd"] == pytest.approx(np.std([0.1, 0.2], ddof=1))
    assert np.isnan(g.loc["abl", "gain_iou_seed_sd"])
    # the default interval (the t interval for these spacecraft) also gives the p-value Holm needs
    from pipeline.stats import DEFAULT_INTERVAL, SEED_IMAGE_T

    t = method_gains(df, ["iou", "bf1"]).set_index("method")
    assert DEFAULT_INTERVAL == SEED_IMAGE_T and t.loc["geo", "gain_iou"] == pytest.approx(0.15)
    assert 0.0 <= t.loc["geo", "gain_iou_p"] <= 1.0 and t.loc["geo", "gain_iou_lo"] < 0.15 < t.loc["geo", "gain_iou_hi"]



def test_method_gains_interval_choice_keeps_the_columns_and_the_gains():
    rng = np.random.default_rng(5)
    rows = []
    for seed in (1, 2, 3):
        for i in range(12):
            base = dict(dataset="d", group="G", threshold_mode="calibrated", seed=seed, image_id=f"im{i}",
                        spacecraft=f"s{i // 4}")
            rows.append(dict(base, method="plain", iou=0.5, bf1=0.4))
            rows.append(dict(base, method="geo", iou=0.5 + 0.1 * (seed == 2) + rng.normal(0, 0.05), bf1=0.4))
    df = pd.DataFrame(rows)
    boot = method_gains(df, ["iou", "bf1"], n_resamples=200, interval="seed_bootstrap")
    tt = method_gains(df, ["iou", "bf1"], n_resamples=200, interval=SEED_IMAGE_T)
    assert list(tt.columns) == list(boot.columns)
    for col in ("gain_iou", "gain_iou_seed_sd", "gain_seeds", "gain_images"):
        assert tt[col].tolist() == pytest.approx(boot[col].tolist())
    # the bounds are paired_seed_image_t's on the [S, n] differences
    wide = df.pivot_table(index=["seed", "image_id", "spacecraft"], columns="method", values="iou").reset_index()
    d = (wide["geo"] - wide["plain"]).to_numpy().reshape(3, 12)
    want = paired_seed_image_t(d, np.zeros_like(d), wide["spacecraft"].to_numpy()[:12])
    assert tt.loc[0, "gain_iou_lo"] == pytest.approx(want.low) and tt.loc[0, "gain_iou_hi"] == pytest.approx(want.high)
    # a constant difference (bf1): the zero-width interval under both
    assert tt.loc[0, "gain_bf1_lo"] == tt.loc[0, "gain_bf1_hi"] == pytest.approx(0.0)
    with pytest.raises(ValueError, match="interval"):
        method_gains(df, ["iou"], interval="wald")


# ------------------------------------------------------------------------------------- Spearman
def test_average_ranks_match_scipy():
    x = np.array([3.0, 1.0, 2.0, 2.0, 5.0, 1.0, 2.0])
    np.testing.assert_allclose(average_ranks(x), sps.rankdata(x))


@pytest.mark.parametrize("case", range(6))
def test_spearman_agrees_with_scipy(case):
    rng = np.random.default_rng(case)
    n = [5, 12, 60, 60, 200, 33][case]
    x = rng.random(n)
    y = 0.5 * x + rng.normal(0, 0.3, n)
    if case == 3:                      # heavy ties (e.g. many g = 0 images)
        x = np.where(x < 0.3, 0.0, np.round(x, 1))
    if case == 5:
        y = -y
    ours = spearman(x, y)
    ref = sps.spearmanr(x, y)
    assert ours.rho == pytest.approx(ref.statistic, abs=1e-12)
    assert ours.pvalue == pytest.approx(ref.pvalue, rel=1e-9, abs=1e-15)
    assert ours.n == n


def test_spearman_edge_cases():
    assert np.isnan(spearman([1, 2], [2, 1]).rho)
    assert np.isnan(spearman([1, 1, 1, 1], [1, 2, 3, 4]).rho)
    r = spearman([1, 2, 3, 4], [10, 20, 30, 40])
    assert r.rho == pytest.approx(1.0) and r.pvalue == 0.0
    r = spearman([1, 2, np.nan, 4, 5], [1, 3, 2, 5, 4])   # NaN pair dropped
    assert r.n == 4


def test_counts_matrix_bootstrap_equals_the_gather_baseline():
    from benchmarks.bench_evaluate import baseline_method_gains, baseline_resample_means

    rng = np.random.default_rng(0)
    values = rng.normal(size=(40, 3))
    clusters = np.repeat(["b", "a", "c", "d"], [5, 15, 12, 8])[rng.permutation(40)]   # unequal, unsorted
    new = hierarchical_resample_means(values, clusters, 700, np.random.default_rng(3))
    old = baseline_resample_means(values, clusters, 700, np.random.default_rng(3))
    np.testing.assert_allclose(new, old, rtol=1e-12)
    # the per-group matrix bootstrap of method_gains == one bootstrap per (method, metric)
    rows = []
    for method in ("plain", "a", "b"):
        for seed in (1,):  # one seed: the seed-aware bootstrap is the old one (several: test_seed_level_*)
            for i in range(30):
                rows.append(dict(dataset="d", group="g", threshold_mode="calibrated", method=method, seed=seed,
                                 image_id=f"i{i}", spacecraft=f"s{i % 4}", iou=rng.random(),
                                 bf1=np.nan if (method == "b" and i == 3) else rng.random()))
    df = pd.DataFrame(rows)
    got = method_gains(df, ["iou", "bf1"], n_resamples=400, seed=9, interval=SEED_BOOTSTRAP)
    want = baseline_method_gains(df, ["iou", "bf1"], n_resamples=400, seed=9)
    assert [c for c in got.columns if not c.endswith(("_seed_sd", "_p"))] == want.columns.tolist()
    num = [c for c in want.columns if c.startswith("gain_")]
    np.testing.assert_allclose(got[num].to_numpy(float), want[num].to_numpy(float), rtol=1e-12, atol=1e-15)


# ------------------------------------------------------------------------------ seed-aware bootstrap
def test_seed_bootstrap_with_one_seed_is_the_image_bootstrap():
    from pipeline.stats import paired_seed_bootstrap

    rng = np.random.default_rng(4)
    c = rng.random((30, 2))
    t = c + rng.normal(0.05, 0.1, (30, 2))
    clusters = np.repeat(np.arange(5), 6)
    old = paired_hierarchical_bootstrap(t, c, clusters, n_resamples=500, seed=3)
    new = paired_seed_bootstrap(t[None], c[None], clusters, n_resamples=500, seed=3)
    for k in ("estimate", "low", "high"):
        np.testing.assert_array_equal(getattr(new, k), getattr(old, k))


def test_seed_level_widens_the_interval_when_seeds_disagree_and_not_when_they_agree():
    from pipeline.stats import paired_seed_bootstrap

    rng = np.random.default_rng(5)
    clusters = np.repeat(np.arange(6), 5)
    c = rng.random((1, 30)).repeat(5, axis=0)
    noise = rng.normal(0, 0.02, (1, 30))
    agree = c + 0.03 + noise                                     # five seeds, identical differences
    shifts = np.array([-0.06, -0.02, 0.03, 0.07, 0.13])[:, None]   # seeds that disagree, same mean +0.03
    disagree = c + shifts + noise
    seed_avg = paired_hierarchical_bootstrap(agree.mean(0), c.mean(0), clusters, n_resamples=2000, seed=1)
    a = paired_seed_bootstrap(agree, c, clusters, n_resamples=2000, seed=1)
    d = paired_seed_bootstrap(disagree, c, clusters, n_resamples=2000, seed=1)
    assert a.low == pytest.approx(seed_avg.low) and a.high == pytest.approx(seed_avg.high)
    assert d.estimate == pytest.approx(a.estimate)               # same mean gain ...
    assert d.high - d.low > 3 * (a.high - a.low)                 # ... far less certain
    assert a.low > 0 and d.low < 0                               # the old interval would call it supported


def test_claim_status_is_signed_and_puts_the_floor_on_the_bound():
    """Issue 33: each of the five verdicts, a direction on every supported one, the floor compared with
    the CI bound nearest 0 (not the point estimate), one seed deciding nothing, Holm's p last."""
    from pipeline.stats import (GAIN_SUPPORTED, LOSS_SUPPORTED, NO_DIFFERENCE, NOT_ESTIMATED, ONE_SEED, VERDICTS,
                                claim_status)

    assert len(set(VERDICTS)) == 5
    assert claim_status(0.03, 0.01, 0.05) == GAIN_SUPPORTED              # no floor measured: the CI decides
    assert claim_status(-0.03, -0.05, -0.01, 0.005) == LOSS_SUPPORTED    # a loss is a loss, not "supported"
    assert claim_status(0.03, -0.01, 0.07, 0.0) == NO_DIFFERENCE
    assert claim_status(-0.03, -0.07, 0.01, 0.0) == NO_DIFFERENCE        # no direction when the CI covers 0
    # the floor on the bound: the point estimate 0.03 clears 0.014, the lower bound 0.009 does not
    assert claim_status(0.03, 0.009, 0.05, 0.014) == NO_DIFFERENCE
    assert claim_status(0.03, 0.015, 0.05, 0.014) == GAIN_SUPPORTED
    assert claim_status(-0.03, -0.05, -0.009, 0.014) == NO_DIFFERENCE    # the bound nearest 0 of a loss: high
    assert claim_status(0.015, 0.005, 0.03, float("nan")) == GAIN_SUPPORTED
    assert claim_status(float("nan"), 0.0, 0.1) == NOT_ESTIMATED
    # one seed: its CI holds no training noise, so it decides nothing, whatever the CI; two seeds may
    assert claim_status(0.03, 0.01, 0.05, 0.0, n_seeds=1) == ONE_SEED
    assert claim_status(0.03, -0.01, 0.05, 0.0, n_seeds=1) == ONE_SEED
    assert claim_status(0.03, 0.01, 0.05, 0.0, n_seeds=2) == GAIN_SUPPORTED
    assert claim_status(0.03, 0.01, 0.05, 0.0, n_seeds=float("nan")) == GAIN_SUPPORTED
    # multiplicity: a Holm-adjusted p at or above alpha leaves no difference detected
    assert claim_status(0.03, 0.01, 0.05, 0.0, 5, p_adjusted=0.06) == NO_DIFFERENCE
    assert claim_status(0.03, 0.01, 0.05, 0.0, 5, p_adjusted=0.01) == GAIN_SUPPORTED


def test_holm_adjust_matches_the_step_down_definition():
    from pipeline.stats import holm_adjust

    p = [0.01, 0.04, 0.03, float("nan"), 0.005]
    adj = holm_adjust(p)
    # sorted finite: 0.005 (x4), 0.01 (x3), 0.03 (x2), 0.04 (x1), running maximum, capped at 1
    assert np.allclose(adj[[4, 0, 2, 1]], [0.02, 0.03, 0.06, 0.06]) and np.isnan(adj[3])
    assert np.allclose(holm_adjust([0.5, 0.9]), [1.0, 1.0]) and holm_adjust([]).shape == (0,)
    # Holm never adjusts below the raw p, and with one p it is the raw p
    assert holm_adjust([0.02])[0] == 0.02 and np.all(adj[np.isfinite(adj)] >= np.asarray(p)[np.isfinite(adj)])


def test_paired_seed_t_interval():
    from scipy import stats as sps

    from pipeline.stats import paired_seed_t_interval

    d = [0.01, 0.03, -0.02, 0.04]
    m, lo, hi = paired_seed_t_interval(d)
    ref = sps.t.interval(0.95, 3, loc=np.mean(d), scale=np.std(d, ddof=1) / 2)
    assert np.isclose(m, np.mean(d)) and np.allclose([lo, hi], ref)
    assert np.isnan(paired_seed_t_interval([0.1])[1]) and np.isnan(paired_seed_t_interval([])[0])
