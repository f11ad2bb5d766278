"""Statistics of the evaluation (paper section "Metrics and Statistical Analysis").

* :func:`seed_summary` -- "mean and standard deviation over three random seeds": the per-seed mean
  over images first, then the mean and the *sample* standard deviation (ddof = 1) of those per-seed
  means.  One seed gives std = NaN (undefined), never 0.
* :func:`paired_hierarchical_bootstrap` -- "95 % confidence intervals ... from matched per-image
  outputs using 10 000 paired hierarchical bootstrap resamples": spacecraft are resampled with
  replacement, then images with replacement within each drawn spacecraft; the *same* draw is applied
  to every method (and every metric), so the interval is for a paired difference.
* :func:`paired_seed_bootstrap` -- the same interval with training noise in it (issue 24): seeds are a
  level of the hierarchy.  Each resample draws the seeds with replacement and, independently,
  spacecraft then images (one image draw for every seed: seeds and images are crossed, each seed
  scores every test image); the statistic is the mean over the drawn seeds of the per-seed resampled
  mean difference.  With one seed it is exactly :func:`paired_hierarchical_bootstrap`; with several
  seeds that agree it equals that interval of the seed-averaged differences; seeds that disagree
  widen it.  :func:`method_gains` uses it by default.
* :func:`paired_seed_image_t` -- a t interval with a stated estimand (docs/intervals.md): the effect on
  these test spacecraft (seed-to-seed variance of the per-seed mean differences plus the stratified
  within-spacecraft image variance, Satterthwaite df), or on spacecraft like these (cluster variance,
  C - 1 df).  :data:`INTERVALS` names the intervals :func:`method_gains` can use.
* :func:`claim_status` -- the report's wording rule, a signed verdict: "gain supported" or "loss
  supported" only when the seed-aware CI excludes zero, its bound nearest zero clears the noise floor
  and (within a table's family) the Holm-adjusted p-value (:func:`holm_adjust`) is below alpha.
* :func:`spearman` -- Spearman's rank correlation with its two-sided p-value (t approximation with
  n - 2 degrees of freedom, as ``scipy.stats.spearmanr``), used for the gate analysis.

Pure numpy functions on arrays (no I/O); the tables they feed are built in ``pipeline.report.tables``.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Iterable, Iterator, Sequence

import numpy as np

from pipeline.methods import BASELINE
from pipeline.params import PAPER, SEED_BOOTSTRAP, SEED_CLUSTER_T, SEED_IMAGE_T

# resample index arrays are generated in blocks of at most this many int64 entries (bounded memory
# for a large single-spacecraft test set such as TANGO's 3,002 images)
_BLOCK_ENTRIES = 4_000_000


# --------------------------------------------------------------------------------------------------
# Seed aggregation
# --------------------------------------------------------------------------------------------------
def seed_summary(df, by: Sequence[str], metrics: Sequence[str], seed_col: str = "seed"):
    """Mean and sample std over seeds of the per-seed means.

    ``df`` is a per-image table (one row per image, seed and whatever ``by`` names).  For every ``by``
    group: per-seed mean of each metric over its images (NaN values, e.g. an undefined small-region
    IoU, are skipped), then ``<metric>_mean`` = mean over seeds and ``<metric>_std`` = sample
    standard deviation over seeds (ddof = 1; NaN for a single seed).  Also returns ``n_seeds`` and
    ``n_images`` (images per seed; the maximum when seeds differ).
    """
    import pandas as pd

    by = list(by)
    metrics = [m for m in metrics if m in df.columns]
    per_seed = df.groupby(by + [seed_col], sort=True, dropna=False)[metrics].mean()
    counts = df.groupby(by + [seed_col], sort=True, dropna=False).size()
    grouped = per_seed.groupby(level=list(range(len(by))), sort=True, dropna=False)
    out = pd.DataFrame({
        "n_seeds": grouped.size(),
        "n_images": counts.groupby(level=list(range(len(by))), sort=True, dropna=False).max(),
    })
    for m in metrics:
        out[f"{m}_mean"] = grouped[m].mean()
        out[f"{m}_std"] = grouped[m].std(ddof=1)
    return out.reset_index()


# --------------------------------------------------------------------------------------------------
# Paired hierarchical bootstrap
# --------------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class BootstrapCI:
    """Point estimate (mean over all images) and percentile interval, one entry per column."""

    estimate: np.ndarray
    low: np.ndarray
    high: np.ndarray
    n_resamples: int
    n_clusters: int
    n_items: int


def _cluster_layout(clusters: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """-> (order that sorts items by cluster, cluster start offsets, cluster sizes)."""
    _, inverse, sizes = np.unique(clusters, return_inverse=True, return_counts=True)
    order = np.argsort(inverse, kind="stable")
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    return order, starts, sizes


def hierarchical_resample_counts(clusters: np.ndarray, n_resamples: int, rng: np.random.Generator,
                                 block_entries: int = _BLOCK_ENTRIES) -> Iterator[np.ndarray]:
    """Two-level resamples as multiplicity counts: yields int64 blocks [b, n] (b resamples each, n_resamples
    in all), entry [r, i] = how many times item i (input order) was drawn in resample r.

    Each resample draws C clusters with replacement out of the C clusters, then, for every drawn cluster
    of size n_c, n_c items with replacement from that cluster (the usual two-stage cluster bootstrap; a
    resample's total size is random when clusters differ in size).  The random stream is consumed block
    by block exactly as the statistic needs it, so a given ``rng`` state always gives the same counts.
    """
    clusters = np.asarray(clusters)
    if len(clusters) == 0:
        raise ValueError("no items to resample")
    order, starts, sizes = _cluster_layout(clusters)
    n, n_clusters, n_max = len(clusters), len(sizes), int(sizes.max())
    block = max(1, block_entries // (n_clusters * n_max))
    for b0 in range(0, n_resamples, block):
        b = min(block, n_resamples - b0)
        drawn = rng.integers(0, n_clusters, size=(b, n_clusters))                 # level 1: clusters
        n_drawn = sizes[drawn]                                                     # [b, C]
        within = (rng.random((b, n_clusters, n_max)) * n_drawn[..., None]).astype(np.int64)  # level 2
        keep = np.arange(n_max) < n_drawn[..., None]                               # [b, C, n_max]
        item = order[np.where(keep, starts[drawn][..., None] + within, 0)]         # input positions
        row = np.broadcast_to(np.arange(b)[:, None, None], item.shape)
        yield np.bincount((row * n + item)[keep], minlength=b * n).reshape(b, n)


def hierarchical_resample_means(values: np.ndarray, clusters: np.ndarray, n_resamples: int,
                                rng: np.random.Generator) -> np.ndarray:
    """Bootstrap distribution of the mean of ``values`` under two-level resampling
    (:func:`hierarchical_resample_counts`).  ``values`` is [n] or [n, k] (k statistics resampled with
    the same draws); returns [n_resamples, k].  One matrix product per block: means = counts @ values
    / counts.sum(1) (``einsum`` without BLAS, so the summation order -- and every bit of the result --
    does not depend on the number of threads).
    """
    values = np.asarray(values, dtype=np.float64)
    if values.ndim == 1:
        values = values[:, None]
    clusters = np.asarray(clusters)
    if len(values) != len(clusters):
        raise ValueError(f"values ({len(values)}) and clusters ({len(clusters)}) differ in length")
    if len(values) == 0:
        raise ValueError("no items to resample")
    out = np.empty((n_resamples, values.shape[1]), dtype=np.float64)
    b0 = 0
    for counts in hierarchical_resample_counts(clusters, n_resamples, rng):
        b = len(counts)
        out[b0:b0 + b] = np.einsum("rn,nk->rk", counts.astype(np.float64), values) / counts.sum(axis=1)[:, None]
        b0 += b
    return out


def paired_hierarchical_bootstrap(treatment: np.ndarray, control: np.ndarray, clusters: np.ndarray,
                                  n_resamples: int = 10_000, ci: float = 0.95, seed: int = 0) -> BootstrapCI:
    """CI of the mean paired difference ``treatment - control`` (paper: paired hierarchical bootstrap).

    ``treatment`` and ``control`` are matched per-image values ([n] or [n, k], row i = the same image
    for both; with several seeds pass each method's seed-averaged value per image, so the estimate is
    the difference of the seed-averaged means).  ``clusters`` [n] names each image's spacecraft.
    Resampling the per-image differences is resampling matched rows of both methods at once, which is
    what "paired" means.  The interval is the percentile interval [q_{(1-ci)/2}, q_{(1+ci)/2}] of the
    bootstrap means; the estimate is the plain mean of the differences.  Seeded: the same inputs and
    ``seed`` give the same interval.
    """
    t = np.asarray(treatment, dtype=np.float64)
    c = np.asarray(control, dtype=np.float64)
    if t.shape != c.shape:
        raise ValueError(f"treatment {t.shape} and control {c.shape} are not matched")
    if not 0.0 < ci < 1.0:
        raise ValueError(f"ci={ci} must lie in (0, 1)")
    diff = t - c
    diff2 = diff[:, None] if diff.ndim == 1 else diff
    if np.isnan(diff2).any():
        raise ValueError("paired differences contain NaN; drop undefined images before bootstrapping")
    rng = np.random.default_rng(seed)
    boot = hierarchical_resample_means(diff2, clusters, int(n_resamples), rng)
    alpha = (1.0 - ci) / 2.0
    lo, hi = np.quantile(boot, [alpha, 1.0 - alpha], axis=0)
    est = diff2.mean(axis=0)
    squeeze = (lambda a: a[0]) if diff.ndim == 1 else (lambda a: a)
    return BootstrapCI(estimate=squeeze(est), low=squeeze(lo), high=squeeze(hi), n_resamples=int(n_resamples),
                       n_clusters=len(np.unique(clusters)), n_items=len(diff2))


#: the seed level's random stream: ``default_rng([seed, SEED_STREAM])`` -- separate from the image
#: level's ``default_rng(seed)``, so the image draws are those of :func:`paired_hierarchical_bootstrap`
SEED_STREAM = 1


def seed_differences(treatment, control, ci: float) -> tuple[np.ndarray, np.ndarray]:
    """The checked paired differences of a seed-aware interval: ``(d, d3)`` with d = treatment - control
    ([S, n] or [S, n, k]) and d3 its [S, n, k] view.  ValueError when the two are not matched, ``ci`` is
    not in (0, 1) or a difference is NaN (drop undefined images first)."""
    t = np.asarray(treatment, dtype=np.float64)
    c = np.asarray(control, dtype=np.float64)
    if t.shape != c.shape or t.ndim not in (2, 3) or t.shape[0] == 0:
        raise ValueError(f"treatment {t.shape} and control {c.shape} must be matched [S, n] or [S, n, k]")
    if not 0.0 < ci < 1.0:
        raise ValueError(f"ci={ci} must lie in (0, 1)")
    d = t - c
    d3 = d[..., None] if d.ndim == 2 else d
    if np.isnan(d3).any():
        raise ValueError("paired differences contain NaN; drop undefined images before the interval")
    return d, d3


def paired_seed_bootstrap(treatment: np.ndarray, control: np.ndarray, clusters: np.ndarray,
                          n_resamples: int = 10_000, ci: float = 0.95, seed: int = 0) -> BootstrapCI:
    """Seed-aware CI of the mean paired difference ``treatment - control``: seeds, then spacecraft,
    then images.

    ``treatment``, ``control``: [S, n] or [S, n, k] -- row s = seed s (the same seed of both methods:
    a warm-started method and its Stage-I control share it), column i = the same image for every seed
    and method.  Let d[s, i] be the differences.  Resample r draws seed multiplicities w_r (S draws with
    replacement out of S) and image multiplicities c_r (spacecraft with replacement, then images within
    them, :func:`hierarchical_resample_counts`, one draw for all seeds); its value is
    sum_s w_rs (d[s] . c_r / sum c_r) / S.  The estimate is the plain mean of d; the interval the
    percentile interval of the resampled values.

    Edge cases: S = 1 draws no seed (w = 1): exactly :func:`paired_hierarchical_bootstrap` of d[0]
    with the same ``seed``.  Identical rows d[s] give that interval of their mean for any S.
    """
    d, d3 = seed_differences(treatment, control, ci)
    n_seeds, n, k = d3.shape
    # image level: every seed's column block resampled with the same draws -> [R, S, k]
    per_seed = hierarchical_resample_means(d3.transpose(1, 0, 2).reshape(n, n_seeds * k), clusters,
                                           int(n_resamples), np.random.default_rng(seed))
    per_seed = per_seed.reshape(int(n_resamples), n_seeds, k)
    if n_seeds == 1:
        boot = per_seed[:, 0, :]
    else:  # seed level: multiplicities of S draws with replacement
        drawn = np.random.default_rng([seed, SEED_STREAM]).integers(0, n_seeds, size=(int(n_resamples), n_seeds))
        w = np.stack([np.bincount(row, minlength=n_seeds) for row in drawn]).astype(np.float64)
        boot = np.einsum("rs,rsk->rk", w, per_seed) / n_seeds
    alpha = (1.0 - ci) / 2.0
    lo, hi = np.quantile(boot, [alpha, 1.0 - alpha], axis=0)
    est = d3.reshape(n_seeds * n, k).mean(axis=0)
    squeeze = (lambda a: a[0]) if d.ndim == 2 else (lambda a: a)
    return BootstrapCI(estimate=squeeze(est), low=squeeze(lo), high=squeeze(hi), n_resamples=int(n_resamples),
                       n_clusters=len(np.unique(clusters)), n_items=n)


#: :func:`paired_seed_image_t` spacecraft levels, i.e. the two estimands a gain can have (docs/intervals.md)
SPACECRAFT_FIXED = "fixed"      # "the effect on these test spacecraft": their images and the seeds are samples
SPACECRAFT_RANDOM = "random"    # "the effect on spacecraft like these": the spacecraft are a sample too


@dataclasses.dataclass(frozen=True)
class TInterval:
    """Point estimate, t interval, its standard error, Satterthwaite degrees of freedom and two-sided
    p-value (H0: no difference), one entry per column."""

    estimate: np.ndarray
    low: np.ndarray
    high: np.ndarray
    se: np.ndarray
    df: np.ndarray
    pvalue: np.ndarray
    n_seeds: int
    n_clusters: int
    n_items: int


def paired_seed_image_t(treatment: np.ndarray, control: np.ndarray, clusters: np.ndarray, ci: float = 0.95,
                        spacecraft: str = SPACECRAFT_FIXED, n_resamples: int | None = None,
                        seed: int | None = None) -> TInterval:
    """Seed-aware t interval of the mean paired difference ``treatment - control`` (docs/intervals.md).

    Inputs as :func:`paired_seed_bootstrap`: [S, n] or [S, n, k], row s = seed s, column i = image i,
    ``clusters`` [n] its spacecraft c (n_c images, weight w_c = n_c / n, C spacecraft).  With
    d[s, i] the differences, the estimate is dbar = mean of d, and

    * seed term: m_s = mean_i d[s, i] (per-seed mean difference), V_seed = var_s(m_s) / S (ddof 1),
      df_seed = S - 1;
    * ``spacecraft="fixed"`` -- the effect on THESE spacecraft (their images and the seeds random):
      a_i = mean_s d[s, i] (seed-averaged difference of image i), s_c^2 = its sample variance within
      spacecraft c, V_img = sum_c w_c^2 s_c^2 / n_c (stratified), df_c = n_c - 1 per stratum; a
      spacecraft with one image borrows the pooled within-spacecraft variance (and its df);
    * ``spacecraft="random"`` -- the effect on spacecraft LIKE these: M_c = mean of a_i over c,
      V_img = C / (C - 1) sum_c w_c^2 (M_c - dbar)^2 (cluster-robust, CR1), one term with df C - 1
      (NaN interval for C = 1);
    * SE^2 = V_seed + V_img (each V_k a term above, df_k its df); interval dbar +- t_{(1+ci)/2, df} SE,
      p = 2 P(T_df > |dbar| / SE), with Satterthwaite's df = (sum_k V'_k)^2 / sum_k V'_k^2 / df_k
      computed from the median-unbiased terms V'_k = V_k df_k / median(chi2_{df_k}).  The plain
      plug-in (V'_k = V_k) is liberal with 3 seeds: a seed variance drawn small (a chi2_2 falls below
      its mean 63 % of the time) both shrinks SE and raises df (coverage 0.925 at nominal 0.95 when
      seeds dominate); the median-unbiased share keeps >= 0.93 (docs/intervals.md).  For large df_k
      V'_k -> V_k: plain Satterthwaite.

    Under d[s, i] = theta + b_c(i) + u_s + e_i + e_si the terms estimate sigma_u^2 / S + sigma_si^2 / (nS)
    and sigma_e^2 / n + sigma_si^2 / (nS) (fixed; plus sigma_b^2 / C for random), so SE^2 counts the
    seed-by-image term twice: conservative by sigma_si^2 / (nS), which is small beside the rest.  The
    seed term has only S - 1 df, so with 3 seeds and seed noise dominating the t quantile is ~3-4:
    that width is the price of coverage (the bootstrap's percentile of 3 resampled seeds is not).
    S = 1: no seed term (the interval holds no training noise, as the bootstrap's).  A zero SE gives
    the zero-width interval [dbar, dbar].  ``n_resamples`` and ``seed`` are unused (an analytic
    interval); they are accepted so that every entry of :data:`INTERVALS` is called alike.
    """
    from scipy.special import chdtri, stdtr, stdtrit

    if spacecraft not in (SPACECRAFT_FIXED, SPACECRAFT_RANDOM):
        raise ValueError(f"spacecraft={spacecraft!r}: one of {SPACECRAFT_FIXED!r}, {SPACECRAFT_RANDOM!r}")
    d, d3 = seed_differences(treatment, control, ci)
    clusters = np.asarray(clusters)
    n_seeds, n, k = d3.shape
    if len(clusters) != n:
        raise ValueError(f"clusters ({len(clusters)}) and images ({n}) differ in length")
    est = d3.mean(axis=(0, 1))                                               # [k]
    # seed term
    if n_seeds > 1:
        v_seed = d3.mean(axis=1).var(axis=0, ddof=1) / n_seeds                # [k]
    else:
        v_seed = np.zeros(k)
    terms, dfs = [v_seed], [np.full(k, max(n_seeds - 1, 1), dtype=np.float64)]
    # image / spacecraft term, on the seed-averaged differences a_i, grouped by spacecraft
    order, starts, sizes = _cluster_layout(clusters)
    a = d3.mean(axis=0)[order]                                               # [n, k], sorted by spacecraft
    w = sizes / n                                                            # [C]
    means = np.add.reduceat(a, starts, axis=0) / sizes[:, None]              # [C, k]
    if spacecraft == SPACECRAFT_FIXED:
        ss = np.add.reduceat((a - np.repeat(means, sizes, axis=0)) ** 2, starts, axis=0)  # [C, k]
        df_c = (sizes - 1).astype(np.float64)
        pooled_df = df_c.sum()
        pooled = ss.sum(axis=0) / pooled_df if pooled_df > 0 else np.full(k, np.nan)
        single = df_c == 0
        s2 = np.where(single[:, None], pooled[None, :], ss / np.maximum(df_c, 1.0)[:, None])
        terms += list((w ** 2 / sizes)[:, None] * s2)
        dfs += [np.full(k, pooled_df if one else dfc) for one, dfc in zip(single, df_c)]
    else:
        n_cl = len(sizes)
        v_cl = (n_cl / (n_cl - 1) * ((w[:, None] * (means - est)) ** 2).sum(axis=0) if n_cl > 1
                else np.full(k, np.nan))
        terms.append(v_cl)
        dfs.append(np.full(k, max(n_cl - 1, 1), dtype=np.float64))
    v = np.sum(terms, axis=0)
    # Satterthwaite df from median-unbiased terms: V_k scaled by df_k / median(chi2_df_k)
    med = [tk * dk / chdtri(dk, 0.5) for tk, dk in zip(terms, dfs)]
    with np.errstate(divide="ignore", invalid="ignore"):
        df = np.where(v > 0, np.sum(med, axis=0) ** 2 / np.sum([m ** 2 / dk for m, dk in zip(med, dfs)], axis=0),
                      np.inf)
        se = np.sqrt(v)
        half = np.where(v > 0, stdtrit(df, (1.0 + ci) / 2.0) * se, 0.0)
        p = np.where(v > 0, 2.0 * stdtr(df, -np.abs(est) / se), np.where(est == 0, 1.0, 0.0))
    half = np.where(np.isnan(v), np.nan, half)
    p = np.where(np.isnan(v), np.nan, p)
    squeeze = (lambda x: x[0]) if d.ndim == 2 else (lambda x: x)
    return TInterval(estimate=squeeze(est), low=squeeze(est - half), high=squeeze(est + half), se=squeeze(se),
                     df=squeeze(df), pvalue=squeeze(p), n_seeds=n_seeds, n_clusters=len(sizes), n_items=n)


#: :func:`claim_status` outcomes: the five verdicts a report may print beside a difference (issue 33).
#: A verdict always carries its direction; "no difference detected" never names one.
GAIN_SUPPORTED = "gain supported"
LOSS_SUPPORTED = "loss supported"
NO_DIFFERENCE = "no difference detected"
ONE_SEED = "one seed"
NOT_ESTIMATED = "not estimated"
#: the significance level of every verdict (two-sided; the reports' 95 % intervals)
ALPHA = 0.05
VERDICTS = (GAIN_SUPPORTED, LOSS_SUPPORTED, NO_DIFFERENCE, ONE_SEED, NOT_ESTIMATED)
#: the verdicts that claim a difference
SUPPORTED_VERDICTS = (GAIN_SUPPORTED, LOSS_SUPPORTED)


def bound_nearest_zero(low: float, high: float) -> float:
    """The end of the interval [low, high] nearest 0 when the interval excludes 0 (``low`` of an interval
    above 0, ``high`` of one below it); NaN when it covers 0 or is not finite."""
    if not (np.isfinite(low) and np.isfinite(high)) or low <= 0.0 <= high:
        return float("nan")
    return float(low) if low > 0.0 else float(high)


def claim_status(gain: float, low: float, high: float, noise_floor: float | None = None,
                 n_seeds: float | None = None, p_adjusted: float | None = None, alpha: float = ALPHA) -> str:
    """The signed verdict on a difference ``gain`` with its seed-aware CI [low, high] (one of
    :data:`VERDICTS`).

    In order:

    * non-finite gain or bounds -> "not estimated";
    * fewer than two seeds (``n_seeds``; None or NaN = unknown) -> "one seed": a one-seed interval
      resamples spacecraft and images only, so it holds no training noise and decides nothing;
    * the CI covers 0 -> "no difference detected";
    * the floor on the bound: the CI bound nearest zero (:func:`bound_nearest_zero`) must clear the
      noise floor, ``|bound| > noise_floor`` -- a floor against the point estimate would call a
      difference supported whose interval reaches into the noise (issue 33).  ``noise_floor`` None or
      NaN = not measured in this configuration: the CI alone decides, and the report says so;
    * multiplicity: ``p_adjusted`` (the Holm-adjusted p-value of the difference within the family its
      table shows, :func:`holm_adjust`; None = not adjusted, e.g. the one primary endpoint) must be
      below ``alpha``;
    * otherwise "gain supported" (bound above 0) or "loss supported" (below 0).
    """
    if not all(np.isfinite(x) for x in (gain, low, high)):
        return NOT_ESTIMATED
    if n_seeds is not None and np.isfinite(n_seeds) and n_seeds < 2:
        return ONE_SEED
    bound = bound_nearest_zero(low, high)
    if not np.isfinite(bound):
        return NO_DIFFERENCE
    if noise_floor is not None and np.isfinite(noise_floor) and abs(bound) <= noise_floor:
        return NO_DIFFERENCE
    if p_adjusted is not None and np.isfinite(p_adjusted) and p_adjusted >= alpha:
        return NO_DIFFERENCE
    return GAIN_SUPPORTED if bound > 0.0 else LOSS_SUPPORTED


def paired_seed_t_interval(differences: Sequence[float], ci: float = 1.0 - ALPHA) -> tuple[float, float, float]:
    """(mean, low, high) of per-seed paired differences (one value per seed both runs share, e.g. a
    calibration error of two methods at the same seed): Student's t interval with S - 1 degrees of
    freedom, mean +- t_{(1+ci)/2, S-1} sd / sqrt(S).  NaN bounds for fewer than two finite values.
    Used where a report compares a per-seed quantity (no per-image pairing exists)."""
    from scipy.special import stdtrit

    d = np.asarray([x for x in differences if np.isfinite(x)], dtype=np.float64)
    if len(d) == 0:
        return float("nan"), float("nan"), float("nan")
    mean = float(d.mean())
    if len(d) < 2:
        return mean, float("nan"), float("nan")
    half = float(stdtrit(len(d) - 1, (1.0 + ci) / 2.0)) * float(d.std(ddof=1)) / np.sqrt(len(d))
    return mean, mean - half, mean + half


def holm_adjust(pvalues: Sequence[float]) -> np.ndarray:
    """Holm's step-down adjusted p-values (Holm 1979; the family-wise error rate is controlled at any
    level alpha by calling a p-value significant when its adjusted value is below alpha).

    With the m finite p-values sorted p_(1) <= ... <= p_(m):
    adj_(j) = min(1, max_{i <= j} (m - i + 1) p_(i)).  NaN entries are not in the family and stay NaN.
    Chosen over Benjamini-Hochberg because a report's verdicts are read one by one (a family-wise
    guarantee), and the families are small (one table, 3 groups x a few comparisons x 2 metrics)."""
    p = np.asarray(pvalues, dtype=np.float64)
    out = np.full(p.shape, np.nan)
    ok = np.flatnonzero(np.isfinite(p))
    m = len(ok)
    if not m:
        return out
    order = ok[np.argsort(p[ok], kind="mergesort")]
    scaled = (m - np.arange(m)) * p[order]
    out[order] = np.minimum(1.0, np.maximum.accumulate(scaled))
    return out


# --------------------------------------------------------------------------------------------------
# Spearman rank correlation
# --------------------------------------------------------------------------------------------------
def average_ranks(x: np.ndarray) -> np.ndarray:
    """Ranks 1..n with ties given the average of the ranks they span (``rankdata(method='average')``)."""
    x = np.asarray(x, dtype=np.float64)
    order = np.argsort(x, kind="mergesort")
    xs = x[order]
    new_run = np.concatenate([[True], xs[1:] != xs[:-1]])
    run_id = np.cumsum(new_run) - 1
    run_start = np.flatnonzero(new_run)
    run_end = np.concatenate([run_start[1:], [len(x)]])       # exclusive
    avg = (run_start + run_end + 1) / 2.0                       # mean of ranks start+1 .. end
    ranks = np.empty(len(x), dtype=np.float64)
    ranks[order] = avg[run_id]
    return ranks


@dataclasses.dataclass(frozen=True)
class SpearmanResult:
    rho: float
    pvalue: float
    n: int


def spearman(x: Iterable[float], y: Iterable[float]) -> SpearmanResult:
    """Spearman's rho = Pearson correlation of the average ranks of x and y, with the two-sided p-value
    from t = rho sqrt((n - 2) / (1 - rho^2)) ~ Student t with n - 2 degrees of freedom.

    Pairs with a NaN in either value are dropped.  Undefined cases (fewer than 3 pairs, or a constant
    input) give rho = p = NaN.  |rho| = 1 gives p = 0.
    """
    from scipy.special import stdtr

    x = np.asarray(list(x) if not isinstance(x, np.ndarray) else x, dtype=np.float64)
    y = np.asarray(list(y) if not isinstance(y, np.ndarray) else y, dtype=np.float64)
    if x.shape != y.shape:
        raise ValueError(f"x {x.shape} and y {y.shape} differ in shape")
    ok = ~(np.isnan(x) | np.isnan(y))
    x, y = x[ok], y[ok]
    n = len(x)
    if n < 3:
        return SpearmanResult(float("nan"), float("nan"), n)
    rx, ry = average_ranks(x), average_ranks(y)
    rx -= rx.mean()
    ry -= ry.mean()
    denom = np.sqrt((rx * rx).sum() * (ry * ry).sum())
    if denom == 0:
        return SpearmanResult(float("nan"), float("nan"), n)
    rho = float(np.clip((rx * ry).sum() / denom, -1.0, 1.0))
    dof = n - 2
    if abs(rho) >= 1.0:
        return SpearmanResult(rho, 0.0, n)
    t = rho * np.sqrt(dof / ((1.0 - rho) * (1.0 + rho)))
    p = float(2.0 * stdtr(dof, -abs(t)))
    return SpearmanResult(rho, p, n)


# --------------------------------------------------------------------------------------------------
# Gains against a control method on a per-image table
# --------------------------------------------------------------------------------------------------
#: the gain intervals :func:`method_gains` can use (docs/intervals.md), each called as
#: ``f(treatment [S, n, k], control, clusters, n_resamples=, ci=, seed=)`` -> ``.estimate/.low/.high``
#: (names: pipeline.params.GAIN_INTERVALS, the schema of ``evaluate.interval``)
INTERVALS = {
    SEED_BOOTSTRAP: paired_seed_bootstrap,
    SEED_IMAGE_T: functools.partial(paired_seed_image_t, spacecraft=SPACECRAFT_FIXED),
    SEED_CLUSTER_T: functools.partial(paired_seed_image_t, spacecraft=SPACECRAFT_RANDOM),
}
#: what each interval covers, in a report's words (its estimand and how it is built); ``{spacecraft}``:
#: the test groups' spacecraft count as the report's data table shows it (pipeline.report.tables.interval_text)
INTERVAL_TEXT = {
    SEED_BOOTSTRAP: "a seed-aware paired hierarchical bootstrap (seeds, then spacecraft, then images within "
                    "spacecraft; pipeline.stats.paired_seed_bootstrap; no stated estimand, and it under-covers "
                    "with few seeds when seed noise dominates: docs/intervals.md)",
    SEED_IMAGE_T: "seed-aware paired t intervals for the effect on THESE test spacecraft (seed-to-seed variance "
                  "plus the image variance within each spacecraft, Satterthwaite degrees of freedom; "
                  "pipeline.stats.paired_seed_image_t).  They do not cover the effect on other spacecraft like "
                  "these: with {spacecraft} per test group that interval is much wider, and with one there is "
                  "none (docs/intervals.md)",
    SEED_CLUSTER_T: "seed-aware cluster t intervals for the effect on spacecraft LIKE these (C - 1 degrees of "
                    "freedom; pipeline.stats.paired_seed_image_t with spacecraft random; docs/intervals.md)",
}
#: :func:`method_gains`' interval unless told otherwise: the one whose coverage and power the known-truth
#: simulation of our design (3 spacecraft x 20 images, 3-10 seeds) supports, for the stated estimand
#: "the effect on these test spacecraft" (docs/intervals.md; tests/test_coverage.py)
DEFAULT_INTERVAL = PAPER.evaluate.interval


def method_gains(df, metrics: Sequence[str], control: str = BASELINE, by: Sequence[str] = ("dataset", "group", "threshold_mode"),
                 cluster_col: str = "spacecraft", n_resamples: int = 10_000, ci: float = 0.95, seed: int = 0,
                 interval: str = DEFAULT_INTERVAL):
    """Gain of every method over ``control`` with paired seed-aware CIs, per ``by`` group.

    ``df`` is the per-image metrics table (columns: method, seed, image_id, ``cluster_col``, ``by``,
    metrics).  For each method the pairing uses the seeds it shares with the control (e.g. a seed-42
    ablation is compared with the seed-42 control), paired seed by seed, and the images every one of
    those seeds of both methods has; ``gain_<m>`` = mean over seeds and images of the differences
    (= the difference of the seed-averaged means) and its CI comes from ``interval``, a key of
    :data:`INTERVALS` (:data:`DEFAULT_INTERVAL` ``"seed_image_t"``: :func:`paired_seed_image_t`, the effect
    on these test spacecraft, docs/intervals.md; ``"seed_bootstrap"``: :func:`paired_seed_bootstrap`, seeds
    then spacecraft then images, the same ``seed`` for every comparison, so every method is compared with
    the control on the same resamples).  ``gain_<m>_seed_sd`` = sample std over seeds of the
    per-seed mean differences (NaN for one seed).  Images whose metric is NaN for either method (an
    undefined small-region IoU) are left out of that metric's comparison.
    Returns one row per (by..., method) with ``gain_seeds`` (shared seeds), ``gain_images``,
    ``gain_<m>``, ``gain_<m>_lo``, ``gain_<m>_hi``, ``gain_<m>_seed_sd`` and ``gain_<m>_p`` (the
    interval's two-sided p-value, NaN for the bootstrap, which has none); the control gets no row.
    """
    import pandas as pd

    if interval not in INTERVALS:
        raise ValueError(f"interval={interval!r}: one of {sorted(INTERVALS)}")
    interval_fn = INTERVALS[interval]
    by = list(by)
    rows = []
    for key, part in df.groupby(by, sort=True, dropna=False):
        key = key if isinstance(key, tuple) else (key,)
        ctrl = part[part["method"] == control]
        if ctrl.empty:
            continue
        # every (method, metric) comparison of this group, keyed by the images it pairs: comparisons on
        # the same images share one resample set (same seed), so they are bootstrapped as the columns
        # of one matrix -- the same numbers as one bootstrap per comparison, in one pass
        pending: dict[tuple, list] = {}
        group_rows = []
        for method, treat in part[part["method"] != control].groupby("method", sort=True):
            seeds = sorted(set(treat["seed"]) & set(ctrl["seed"]))
            if not seeds:
                continue
            idx = ["image_id", cluster_col]
            # one row per image, columns <metric>_t<s> / <metric>_c<s> per shared seed (inner join: images
            # every seed of both methods scored)
            both = None
            for s_ in seeds:
                t = treat[treat["seed"] == s_].groupby(idx)[list(metrics)].mean().add_suffix(f"_t{s_}")
                c = ctrl[ctrl["seed"] == s_].groupby(idx)[list(metrics)].mean().add_suffix(f"_c{s_}")
                tc = t.join(c, how="inner")
                both = tc if both is None else both.join(tc, how="inner")
            row = dict(zip(by, key), method=method, gain_seeds=len(seeds), gain_images=len(both))
            for m in metrics:
                cols_t = [f"{m}_t{s_}" for s_ in seeds]
                cols_c = [f"{m}_c{s_}" for s_ in seeds]
                sub = both[both[cols_t + cols_c].notna().all(axis=1)]
                if sub.empty:
                    row.update({f"gain_{m}": np.nan, f"gain_{m}_lo": np.nan, f"gain_{m}_hi": np.nan,
                                f"gain_{m}_seed_sd": np.nan, f"gain_{m}_p": np.nan})
                    continue
                tv, cv = sub[cols_t].to_numpy().T, sub[cols_c].to_numpy().T  # [S, n]
                per_seed = (tv - cv).mean(axis=1)
                row[f"gain_{m}_seed_sd"] = float(np.std(per_seed, ddof=1)) if len(seeds) > 1 else np.nan
                pending.setdefault((tuple(sub.index), len(seeds)), []).append((row, m, tv, cv))
            group_rows.append(row)
        for (items, _), cols in pending.items():
            res = interval_fn(np.stack([t for _, _, t, _ in cols], axis=2),
                              np.stack([c for _, _, _, c in cols], axis=2),
                              np.array([cl for _, cl in items]),
                              n_resamples=n_resamples, ci=ci, seed=seed)
            pvalue = getattr(res, "pvalue", None)  # the t intervals' two-sided p (Holm in the report)
            for j, (row, m, _, _) in enumerate(cols):
                row.update({f"gain_{m}": float(res.estimate[j]), f"gain_{m}_lo": float(res.low[j]),
                            f"gain_{m}_hi": float(res.high[j]),
                            f"gain_{m}_p": float(pvalue[j]) if pvalue is not None else np.nan})
        rows.extend(group_rows)
    cols = by + ["method", "gain_seeds", "gain_images"] + [f"gain_{m}{s}" for m in metrics
                                                           for s in ("", "_lo", "_hi", "_seed_sd", "_p")]
    return pd.DataFrame(rows, columns=cols)


def vs_column(column: str, control: str) -> str:
    """The summary's name of :func:`method_gains` column ``column`` when the gain is over ``control``: as
    is over :data:`pipeline.methods.BASELINE` (``gain_iou``), else with ``_vs_<control>`` before the
    bound (``gain_iou_lo`` -> ``gain_iou_vs_continuation_lo``, ``gain_seeds`` -> ``gain_seeds_vs_continuation``)."""
    if control == BASELINE:
        return column
    for end in ("_lo", "_hi", "_p"):
        if column.endswith(end):
            return f"{column.removesuffix(end)}_vs_{control}{end}"
    return f"{column}_vs_{control}"
