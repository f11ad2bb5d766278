"""Intervals that cover: the known-truth coverage benchmark and the seed-aware t interval
(benchmarks.coverage, pipeline.stats.paired_seed_image_t; docs/intervals.md)."""

import numpy as np
import pytest
from scipy import stats as sps

from benchmarks import coverage
from pipeline.stats import (INTERVALS, SEED_BOOTSTRAP, SEED_CLUSTER_T, SEED_IMAGE_T, SPACECRAFT_RANDOM,
                            paired_seed_bootstrap, paired_seed_image_t)

# the test's simulation size: >= 1,000 replicates per scenario and seed count; the bootstrap reference
# with 500 resamples (its quantiles' Monte Carlo error only)
REPLICATES = 2000
RESAMPLES = 500


@pytest.fixture(scope="module")
def rows():
    return coverage.run(REPLICATES, RESAMPLES, intervals=[SEED_BOOTSTRAP, coverage.CHOSEN, SEED_CLUSTER_T])


# ------------------------------------------------------------------------------------- acceptance
def test_the_chosen_interval_covers_its_estimand_and_keeps_the_power(rows):
    chosen = [r for r in rows if r["interval"] == coverage.CHOSEN]
    assert {(r["scenario"], r["seeds"]) for r in chosen} == {(s, n) for s in coverage.SCENARIOS for n in coverage.SEEDS}
    for r in chosen:
        where = f"{r['scenario']}, S={r['seeds']}"
        assert r["cov_these"] >= coverage.MIN_COVERAGE, f"{where}: coverage {r['cov_these']:.3f}"
        # the power bound: it still detects a true gain of 0.03 in at least half of the replicates
        # where today's interval does, so it cannot pass by being wide
        assert r["kept"] >= coverage.MIN_KEPT, f"{where}: kept {r['kept']:.3f}"
        assert coverage.passes(r)


def test_the_rule_rejects_a_wide_interval_and_the_truth_matters(rows):
    by = {(r["scenario"], r["seeds"], r["interval"]): r for r in rows}
    # the cluster-t interval ("spacecraft like these", C - 1 = 2 df) covers its estimand but is too wide:
    # the power bound rejects it wherever spacecraft differ
    for s in coverage.SEEDS:
        wide = by[("image+spacecraft", s, SEED_CLUSTER_T)]
        assert wide["cov_like"] >= coverage.MIN_COVERAGE and wide["kept"] < coverage.MIN_KEPT
        assert not coverage.passes(wide)
        # and the "these spacecraft" interval does not cover "spacecraft like these": the estimand is stated
        assert by[("image+spacecraft", s, SEED_IMAGE_T)]["cov_like"] < 0.9


def test_todays_bootstrap_undercovers_when_seeds_dominate():
    heavy = coverage.run(REPLICATES, RESAMPLES, seeds=(3,), scenarios=["seed-heavy"],
                         intervals=[SEED_BOOTSTRAP, SEED_IMAGE_T])
    boot, t = (next(r for r in heavy if r["interval"] == k) for k in (SEED_BOOTSTRAP, SEED_IMAGE_T))
    assert boot["cov_these"] < 0.9 < t["cov_these"]


def test_the_benchmark_prints_its_table(capsys):
    out_rows = coverage.main(["--replicates", "200", "--resamples", "50", "--seeds", "3", "--scenarios", "image"])
    out = capsys.readouterr().out
    assert "| scenario | S | interval | estimand |" in out
    assert len(out_rows) == len(INTERVALS)
    for k in INTERVALS:
        assert f"| image | 3 | {k} |" in out
    assert '"chosen": "seed_image_t"' in out


# ----------------------------------------------------------------------------- the interval itself
def test_one_seed_one_spacecraft_is_the_one_sample_t_interval():
    d = np.random.default_rng(0).normal(0.02, 0.1, 25)
    res = paired_seed_image_t(d[None], np.zeros((1, 25)), np.zeros(25, dtype=int))
    lo, hi = sps.t.interval(0.95, 24, loc=d.mean(), scale=d.std(ddof=1) / 5)
    assert res.estimate == pytest.approx(d.mean())
    assert res.df == pytest.approx(24) and res.low == pytest.approx(lo) and res.high == pytest.approx(hi)
    assert res.pvalue == pytest.approx(sps.ttest_1samp(d, 0.0).pvalue)


def test_seed_noise_alone_is_the_t_interval_of_the_per_seed_means():
    # every image of seed s has the same difference m_s: no image variance, S - 1 df
    m = np.array([0.01, 0.05, 0.02, 0.04])
    d = np.repeat(m[:, None], 12, axis=1)
    res = paired_seed_image_t(d, np.zeros_like(d), np.repeat([0, 1, 2], 4))
    lo, hi = sps.t.interval(0.95, 3, loc=m.mean(), scale=m.std(ddof=1) / 2)
    assert res.df == pytest.approx(3) and res.low == pytest.approx(lo) and res.high == pytest.approx(hi)


def test_spacecraft_fixed_is_stratified_and_random_is_the_cluster_t():
    rng = np.random.default_rng(1)
    sizes = [5, 9]
    clusters = np.repeat([7, 3], sizes)             # labels need not be sorted
    d = rng.normal(0.0, 0.1, 14) + np.where(clusters == 7, 0.3, 0.0)
    res = paired_seed_image_t(d[None], np.zeros((1, 14)), clusters)
    terms = [(n / 14) ** 2 * d[clusters == c].var(ddof=1) / n for c, n in zip([7, 3], sizes)]
    # the spacecraft shift 0.3 is no part of a fixed-spacecraft interval's variance
    assert res.se == pytest.approx(np.sqrt(sum(terms)))
    med = [v * (n - 1) / sps.chi2.median(n - 1) for v, n in zip(terms, sizes)]
    df = sum(med) ** 2 / sum(m ** 2 / (n - 1) for m, n in zip(med, sizes))
    assert res.df == pytest.approx(df)
    assert res.high - res.estimate == pytest.approx(sps.t.ppf(0.975, df) * res.se)
    # random spacecraft, equal sizes, constant within each: the one-sample t interval of the 3 cluster means
    means = np.array([0.1, 0.4, 0.2])
    dd = np.repeat(means, 6)[None]
    rr = paired_seed_image_t(dd, np.zeros_like(dd), np.repeat([0, 1, 2], 6), spacecraft=SPACECRAFT_RANDOM)
    lo, hi = sps.t.interval(0.95, 2, loc=means.mean(), scale=means.std(ddof=1) / np.sqrt(3))
    assert rr.df == pytest.approx(2) and rr.low == pytest.approx(lo) and rr.high == pytest.approx(hi)


def test_interval_edge_cases():
    zero = np.zeros((3, 6))
    res = paired_seed_image_t(zero + 0.1, zero, np.repeat([0, 1], 3))           # constant difference
    assert res.low == pytest.approx(0.1) and res.high == pytest.approx(0.1) and res.pvalue == 0.0
    # a spacecraft with one image borrows the pooled within-spacecraft variance
    d = np.random.default_rng(2).normal(0, 0.1, (2, 7))
    one = paired_seed_image_t(d, np.zeros_like(d), np.array([0, 0, 0, 1, 1, 1, 2]))
    assert np.isfinite(one.low) and one.low < one.estimate < one.high
    # no within-spacecraft image at all, or one spacecraft as a sample of spacecraft: not estimated
    assert np.isnan(paired_seed_image_t(d[:, :3], np.zeros((2, 3)), np.arange(3)).low)
    assert np.isnan(paired_seed_image_t(d, np.zeros_like(d), np.zeros(7), spacecraft=SPACECRAFT_RANDOM).high)
    with pytest.raises(ValueError, match="NaN"):
        paired_seed_image_t(np.full((2, 3), np.nan), np.zeros((2, 3)), np.arange(3))
    with pytest.raises(ValueError, match="matched"):
        paired_seed_image_t(np.zeros((2, 3)), np.zeros((3, 3)), np.arange(3))
    with pytest.raises(ValueError, match="spacecraft"):
        paired_seed_image_t(zero, zero, np.arange(6), spacecraft="sometimes")


def test_columns_are_independent_intervals_and_shift_with_the_data():
    rng = np.random.default_rng(3)
    d = rng.normal(0, 0.08, (5, 30, 4)) + rng.normal(0, 0.02, (5, 1, 4))
    clusters = np.repeat([0, 1, 2], 10)
    both = paired_seed_image_t(d, np.zeros_like(d), clusters)
    for j in range(4):
        one = paired_seed_image_t(d[..., j], np.zeros((5, 30)), clusters)
        assert both.low[j] == pytest.approx(one.low) and both.high[j] == pytest.approx(one.high)
        # the p-value and the interval agree on excluding 0
        assert (one.pvalue < 0.05) == (one.low > 0 or one.high < 0)
    # the benchmark reads power off intervals shifted by the gain: every interval is translation-equivariant
    for fn in INTERVALS.values():
        a = fn(d, np.zeros_like(d), clusters, n_resamples=300, ci=0.95, seed=4)
        b = fn(d + 0.03, np.zeros_like(d), clusters, n_resamples=300, ci=0.95, seed=4)
        np.testing.assert_allclose(b.low, a.low + 0.03, atol=1e-12)
        np.testing.assert_allclose(b.high, a.high + 0.03, atol=1e-12)
    # the interval reached through INTERVALS is the function's
    via = INTERVALS[SEED_IMAGE_T](d, np.zeros_like(d), clusters, n_resamples=1, ci=0.95, seed=0)
    np.testing.assert_array_equal(via.low, both.low)
    assert INTERVALS[SEED_BOOTSTRAP] is paired_seed_bootstrap
