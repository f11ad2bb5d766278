"""Statistics of the evaluation (paper, "Metrics and Statistical Analysis").

Seed summaries, paired seed-aware intervals of a gain (docs/intervals.md), signed verdicts with Holm's
adjustment, and Spearman's rho.  Every resampling is seeded: the same inputs and seed give the same numbers.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Callable, Iterable, Iterator, Sequence

import numpy as np

from pipeline.methods import BASELINE
from pipeline.params import PAPER, SEED_BOOTSTRAP, SEED_CLUSTER_T, SEED_IMAGE_T

__all__ = ["SEED_BOOTSTRAP", "SEED_CLUSTER_T", "SEED_IMAGE_T", "ONE_SIDED_95_Z", "seed_summary", "cluster_layout",
           "paired_seed_image_t", "GAIN_SUPPORTED", "LOSS_SUPPORTED", "NO_DIFFERENCE", "ONE_SEED", "NOT_ESTIMATED",
           "ALPHA", "claim_status", "paired_seed_t_interval", "holm_adjust", "SpearmanResult", "spearman",
           "INTERVALS", "INTERVAL_TEXT", "DEFAULT_INTERVAL", "method_gains", "vs_column"]

# resample index arrays are generated in blocks of at most this many int64 entries (bounded memory)
_BLOCK_ENTRIES = 4_000_000

#: one-sided 95 % normal quantile (the plateau rule's bound, the non-inferiority checks)
ONE_SIDED_95_Z = 1.6449


def seed_summary(df, by: Sequence[str], metrics: Sequence[str], seed_col: str = "seed"):
    """Mean and sample standard deviation over seeds of the per-seed means, per group.

    For every ``by`` group: each metric's mean over a seed's images (NaN values, such as an undefined
    small-region IoU, skipped), then the mean and the standard deviation (ddof 1) of those per-seed means.

    Parameters
    ----------
    df : pandas.DataFrame
        Per-image table: one row per image and seed, with the ``by``, ``seed_col`` and metric columns.
    by : sequence of str
        Grouping columns.
    metrics : sequence of str
        Metric columns; names absent from ``df`` are skipped.
    seed_col : str, optional
        The seed column (default ``"seed"``).

    Returns
    -------
    pandas.DataFrame
        One row per group: the ``by`` columns, ``n_seeds``, ``n_images`` (the most images of a seed) and
        ``<metric>_mean`` and ``<metric>_std`` (NaN for one seed) per metric.
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


@dataclasses.dataclass(frozen=True)
class BootstrapCI:
    """A point estimate and its percentile interval, one entry per statistic.

    Attributes
    ----------
    estimate : numpy.ndarray
        The plain mean of the differences.
    low, high : numpy.ndarray
        The percentile interval's bounds.
    n_resamples : int
        Bootstrap resamples drawn.
    n_clusters : int
        Clusters (spacecraft) in the data.
    n_items : int
        Items (images) in the data.
    """

    estimate: np.ndarray
    low: np.ndarray
    high: np.ndarray
    n_resamples: int
    n_clusters: int
    n_items: int


def cluster_layout(clusters: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lay items out by cluster: the order that groups them, and each cluster's start and size in that order.

    Parameters
    ----------
    clusters : numpy.ndarray
        The cluster label of each item [n] (spacecraft names or ids).

    Returns
    -------
    tuple of numpy.ndarray
        (order, starts, sizes): the stable argsort of the items by cluster [n], each cluster's offset in that order
        [C] and its item count [C], clusters in sorted label order.
    """
    _, inverse, sizes = np.unique(clusters, return_inverse=True, return_counts=True)
    order = np.argsort(inverse, kind="stable")
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    return order, starts, sizes


def hierarchical_resample_counts(clusters: np.ndarray, n_resamples: int, rng: np.random.Generator,
                                 block_entries: int = _BLOCK_ENTRIES) -> Iterator[np.ndarray]:
    """Draw two-stage cluster-bootstrap resamples as multiplicity counts.

    Each resample draws C clusters with replacement out of the C clusters, then, for every drawn cluster of size
    n_c, n_c items with replacement within it.  The stream of ``rng`` is consumed block by block in a fixed
    order: a given ``rng`` state always gives the same counts.

    Parameters
    ----------
    clusters : array_like
        Cluster label of each of the n items.
    n_resamples : int
        Resamples in all.
    rng : numpy.random.Generator
        The random stream.
    block_entries : int, optional
        Bound on the int64 entries of one block's index arrays (memory).

    Yields
    ------
    numpy.ndarray
        int64 [b, n] blocks; entry [r, i] = how often item i (input order) was drawn in resample r.

    Raises
    ------
    ValueError
        There is no item.
    """
    clusters = np.asarray(clusters)
    if len(clusters) == 0:
        raise ValueError("no items to resample")
    order, starts, sizes = cluster_layout(clusters)
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
    """Bootstrap distribution of the mean under :func:`hierarchical_resample_counts`.

    Means = counts @ values / counts.sum(1), summed in a fixed order (``einsum``, not BLAS), so every bit of the
    result is independent of the thread count.

    Parameters
    ----------
    values : array_like
        [n] or [n, k]: k statistics resampled with the same draws.
    clusters : array_like
        Cluster label of each item, length n.
    n_resamples : int
        Resamples.
    rng : numpy.random.Generator
        The random stream.

    Returns
    -------
    numpy.ndarray
        float64 [n_resamples, k].

    Raises
    ------
    ValueError
        ``values`` and ``clusters`` differ in length, or there is no item.
    """
    values = np.asarray(values, dtype=np.float64)
    if values.ndim == 1:
        values = values[:, None]
    clusters = np.asarray(clusters)
    if len(values) != len(clusters):
        raise ValueError(f"values ({len(values)}) and clusters ({len(clusters)}) differ in length")
    # einsum, not BLAS: the summation order (every bit of the result) does not depend on the threads
    blocks = [np.einsum("rn,nk->rk", counts.astype(np.float64), values) / counts.sum(axis=1)[:, None]
              for counts in hierarchical_resample_counts(clusters, n_resamples, rng)]
    return np.concatenate(blocks) if blocks else np.empty((0, values.shape[1]))


def paired_hierarchical_bootstrap(treatment: np.ndarray, control: np.ndarray, clusters: np.ndarray,
                                  n_resamples: int = 10_000, ci: float = PAPER.evaluate.ci, seed: int = 0) -> BootstrapCI:  # not a param: the resampling stream
    """Percentile CI of the mean paired difference of one seed's matched per-image values (the paper's bootstrap).

    Spacecraft (``clusters``) are resampled, then images within them; resampling the per-image differences
    resamples matched rows of both methods at once.  Equal to :func:`paired_seed_bootstrap` of one seed.

    Parameters
    ----------
    treatment, control : array_like
        Matched per-image values [n] or [n, k] (row i = the same image in both).
    clusters : array_like
        The spacecraft of each image, length n.
    n_resamples : int, optional
        Bootstrap resamples (default 10 000).
    ci : float, optional
        Coverage of the interval, in (0, 1) (default 0.95).
    seed : int, optional
        Seed of the resampling (default 0).

    Returns
    -------
    BootstrapCI
        The mean difference and the percentile interval [q_(1-ci)/2, q_(1+ci)/2] of the resampled means.
    """
    t, c = np.asarray(treatment, dtype=np.float64), np.asarray(control, dtype=np.float64)
    return paired_seed_bootstrap(t[None], c[None], clusters, n_resamples, ci, seed)


#: the seed level's random stream, ``default_rng([seed, SEED_STREAM])``: the image draws stay those of one seed
SEED_STREAM = 1


def seed_differences(treatment, control, ci: float) -> tuple[np.ndarray, Callable]:
    """Check and return the paired differences of a seed-aware interval.

    Parameters
    ----------
    treatment, control : array_like
        Matched values [S, n] or [S, n, k]: row s = seed s, column i = image i.
    ci : float
        Coverage of the interval, in (0, 1).

    Returns
    -------
    tuple
        ``(d3, squeeze)``: treatment - control as float64 [S, n, k], and the function that gives a per-column
        result the inputs' shape back (a scalar column for [S, n] inputs).

    Raises
    ------
    ValueError
        The inputs are not matched [S, n] or [S, n, k] with S >= 1, ``ci`` is not in (0, 1), or a difference is
        NaN (drop undefined images first).
    """
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
    return d3, (lambda a: a[0]) if d.ndim == 2 else (lambda a: a)


def paired_seed_bootstrap(treatment: np.ndarray, control: np.ndarray, clusters: np.ndarray,
                          n_resamples: int = 10_000, ci: float = PAPER.evaluate.ci, seed: int = 0) -> BootstrapCI:  # not a param: the resampling stream
    """Seed-aware percentile CI of the mean paired difference: seeds, then spacecraft, then images.

    With d[s, i] = treatment - control, resample r draws seed multiplicities w_r (S draws with replacement) and
    image multiplicities c_r (spacecraft with replacement, then images within them, one draw for every seed);
    its value is sum_s w_rs (d[s] . c_r / sum c_r) / S.  The estimate is the plain mean of d.  S = 1 draws no
    seed: exactly :func:`paired_hierarchical_bootstrap` of d[0] with the same ``seed``.

    Parameters
    ----------
    treatment, control : array_like
        Matched values [S, n] or [S, n, k]: row s = the same seed of both methods, column i = the same image.
    clusters : array_like
        The spacecraft of each image, length n.
    n_resamples : int, optional
        Bootstrap resamples (default 10 000).
    ci : float, optional
        Coverage, in (0, 1) (default 0.95).
    seed : int, optional
        Seed of the resampling (default 0); the seed level draws from ``default_rng([seed, SEED_STREAM])``.

    Returns
    -------
    BootstrapCI
        Estimate and percentile interval, scalars per entry for [S, n] inputs, [k] for [S, n, k].

    Raises
    ------
    ValueError
        As :func:`seed_differences`.
    """
    d3, squeeze = seed_differences(treatment, control, ci)
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
    return BootstrapCI(estimate=squeeze(est), low=squeeze(lo), high=squeeze(hi), n_resamples=int(n_resamples),
                       n_clusters=len(np.unique(clusters)), n_items=n)


#: :func:`paired_seed_image_t`'s estimands: the effect on these test spacecraft, or on spacecraft like these
SPACECRAFT_FIXED = "fixed"
SPACECRAFT_RANDOM = "random"


@dataclasses.dataclass(frozen=True)
class TInterval:
    """A point estimate with its t interval, one entry per statistic.

    Attributes
    ----------
    estimate : numpy.ndarray
        The mean paired difference.
    low, high : numpy.ndarray
        Interval bounds, estimate -+ t_((1+ci)/2, df) se.
    se : numpy.ndarray
        Standard error.
    df : numpy.ndarray
        Satterthwaite degrees of freedom (inf where se = 0).
    pvalue : numpy.ndarray
        Two-sided p-value of a zero difference.
    n_seeds : int
        Seeds S.
    n_clusters : int
        Spacecraft C.
    n_items : int
        Images n.
    """

    estimate: np.ndarray
    low: np.ndarray
    high: np.ndarray
    se: np.ndarray
    df: np.ndarray
    pvalue: np.ndarray
    n_seeds: int
    n_clusters: int
    n_items: int


def paired_seed_image_t(treatment: np.ndarray, control: np.ndarray, clusters: np.ndarray, ci: float = PAPER.evaluate.ci,
                        spacecraft: str = SPACECRAFT_FIXED, n_resamples: int | None = None,
                        seed: int | None = None) -> TInterval:
    """Seed-aware t interval of the mean paired difference (docs/intervals.md).

    With d[s, i] = treatment - control and dbar its mean, SE^2 = V_seed + V_img:

    * V_seed = var_s(m_s) / S (ddof 1, df S - 1) of the per-seed mean differences m_s; 0 for S = 1;
    * ``spacecraft="fixed"`` (the effect on THESE spacecraft): with a_i the seed-averaged difference of image i,
      V_img = sum_c w_c^2 s_c^2 / n_c, s_c^2 the variance of a_i within spacecraft c (df n_c - 1), w_c = n_c / n;
      a spacecraft with one image borrows the pooled within-spacecraft variance and its df;
    * ``spacecraft="random"`` (the effect on spacecraft LIKE these): the cluster-robust CR1 variance
      C / (C - 1) sum_c w_c^2 (M_c - dbar)^2 of the spacecraft means M_c, df C - 1 (NaN interval for C = 1).

    Interval dbar -+ t_((1+ci)/2, df) SE and p = 2 P(T_df > |dbar| / SE), df by Satterthwaite from the
    median-unbiased terms V_k df_k / median(chi2_df_k).  A zero SE gives [dbar, dbar] (p = 1 when dbar = 0,
    else 0).

    Parameters
    ----------
    treatment, control : array_like
        Matched values [S, n] or [S, n, k], as :func:`paired_seed_bootstrap`.
    clusters : array_like
        The spacecraft of each image, length n.
    ci : float, optional
        Coverage, in (0, 1) (default 0.95).
    spacecraft : {"fixed", "random"}, optional
        The estimand (:data:`SPACECRAFT_FIXED` by default).
    n_resamples, seed : optional
        Unused (an analytic interval); accepted so that every entry of :data:`INTERVALS` is called alike.

    Returns
    -------
    TInterval
        Scalars per entry for [S, n] inputs, [k] for [S, n, k].

    Raises
    ------
    ValueError
        ``spacecraft`` is unknown, ``clusters`` and the images differ in length, or as :func:`seed_differences`.
    """
    from scipy.special import chdtri, stdtr, stdtrit

    if spacecraft not in (SPACECRAFT_FIXED, SPACECRAFT_RANDOM):
        raise ValueError(f"spacecraft={spacecraft!r}: one of {SPACECRAFT_FIXED!r}, {SPACECRAFT_RANDOM!r}")
    d3, squeeze = seed_differences(treatment, control, ci)
    clusters = np.asarray(clusters)
    n_seeds, n, k = d3.shape
    if len(clusters) != n:
        raise ValueError(f"clusters ({len(clusters)}) and images ({n}) differ in length")
    est = d3.mean(axis=(0, 1))                                               # [k]
    # seed term [k]
    v_seed = d3.mean(axis=1).var(axis=0, ddof=1) / n_seeds if n_seeds > 1 else np.zeros(k)
    terms, dfs = [v_seed], [np.full(k, max(n_seeds - 1, 1), dtype=np.float64)]
    # image / spacecraft term, on the seed-averaged differences a_i, grouped by spacecraft
    order, starts, sizes = cluster_layout(clusters)
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
    half, p = (np.where(np.isnan(v), np.nan, x) for x in (half, p))
    return TInterval(estimate=squeeze(est), low=squeeze(est - half), high=squeeze(est + half), se=squeeze(se),
                     df=squeeze(df), pvalue=squeeze(p), n_seeds=n_seeds, n_clusters=len(sizes), n_items=n)


#: :func:`claim_status` outcomes: a supported verdict carries its direction
GAIN_SUPPORTED = "gain supported"
LOSS_SUPPORTED = "loss supported"
NO_DIFFERENCE = "no difference detected"
ONE_SEED = "one seed"
NOT_ESTIMATED = "not estimated"
#: the significance level of every verdict (two-sided; the reports' 95 % intervals)
ALPHA = 0.05
VERDICTS = (GAIN_SUPPORTED, LOSS_SUPPORTED, NO_DIFFERENCE, ONE_SEED, NOT_ESTIMATED)


def claim_status(gain: float, low: float, high: float, noise_floor: float | None = None,
                 n_seeds: float | None = None, p_adjusted: float | None = None, alpha: float = ALPHA) -> str:
    """Return the signed verdict (one of :data:`VERDICTS`) on a gain with its seed-aware CI.

    In order: a non-finite gain or bound -> "not estimated"; fewer than two seeds -> "one seed" (such an
    interval holds no training noise); a CI covering 0, a bound nearest 0 with |bound| <= ``noise_floor``, or
    ``p_adjusted`` >= ``alpha`` -> "no difference detected"; otherwise "gain supported" (CI above 0) or
    "loss supported" (CI below 0).

    Parameters
    ----------
    gain : float
        The estimated difference.
    low, high : float
        Its CI bounds.
    noise_floor : float, optional
        The run-to-run noise floor the bound nearest 0 must clear; None or NaN: not measured (the CI decides).
    n_seeds : float, optional
        Seeds behind the interval; None or NaN: unknown.
    p_adjusted : float, optional
        Holm-adjusted p-value within the table's family (:func:`holm_adjust`); None or NaN: not adjusted.
    alpha : float, optional
        Significance level (default :data:`ALPHA`, 0.05).

    Returns
    -------
    str
        The verdict.
    """
    if not all(np.isfinite(x) for x in (gain, low, high)):
        return NOT_ESTIMATED
    if n_seeds is not None and np.isfinite(n_seeds) and n_seeds < 2:
        return ONE_SEED
    bound = float(low) if low > 0.0 else float(high)  # nearest 0 when [low, high] excludes it
    if (low <= 0.0 <= high or (noise_floor is not None and np.isfinite(noise_floor) and abs(bound) <= noise_floor)
            or (p_adjusted is not None and np.isfinite(p_adjusted) and p_adjusted >= alpha)):
        return NO_DIFFERENCE
    return GAIN_SUPPORTED if bound > 0.0 else LOSS_SUPPORTED


def paired_seed_t_interval(differences: Sequence[float], ci: float = 1.0 - ALPHA) -> tuple[float, float, float]:
    """Student's t interval of per-seed paired differences, S - 1 degrees of freedom.

    mean -+ t_((1+ci)/2, S-1) sd / sqrt(S), over the finite values: for a per-seed quantity without per-image
    pairing.

    Parameters
    ----------
    differences : sequence of float
        One difference per seed both runs share; non-finite values are dropped.
    ci : float, optional
        Coverage (default 1 - :data:`ALPHA`).

    Returns
    -------
    tuple of float
        (mean, low, high); NaN bounds with fewer than two finite values, NaN mean with none.
    """
    from scipy.special import stdtrit

    d = np.asarray([x for x in differences if np.isfinite(x)], dtype=np.float64)
    mean = float(d.mean()) if len(d) else float("nan")
    if len(d) < 2:
        return mean, float("nan"), float("nan")
    half = float(stdtrit(len(d) - 1, (1.0 + ci) / 2.0)) * float(d.std(ddof=1)) / np.sqrt(len(d))
    return mean, mean - half, mean + half


def holm_adjust(pvalues: Sequence[float]) -> np.ndarray:
    """Holm's step-down adjusted p-values.

    With the m finite p-values sorted p_(1) <= ... <= p_(m): adj_(j) = min(1, max_{i <= j} (m - i + 1) p_(i)).
    Calling a p-value significant when its adjusted value is below alpha controls the family-wise error rate.

    Parameters
    ----------
    pvalues : sequence of float
        The family's p-values; NaN entries are not in the family.

    Returns
    -------
    numpy.ndarray
        float64, the input's shape and order; NaN stays NaN.
    """
    p = np.asarray(pvalues, dtype=np.float64)
    out = np.full(p.shape, np.nan)
    ok = np.flatnonzero(np.isfinite(p))
    m = len(ok)
    order = ok[np.argsort(p[ok], kind="mergesort")]
    scaled = (m - np.arange(m)) * p[order]
    out[order] = np.minimum(1.0, np.maximum.accumulate(scaled))
    return out


def average_ranks(x: np.ndarray) -> np.ndarray:
    """Rank 1..n with ties averaged (``scipy.stats.rankdata(method="average")``).

    Parameters
    ----------
    x : array_like
        Values, 1-D.

    Returns
    -------
    numpy.ndarray
        float64 ranks.
    """
    from scipy.stats import rankdata

    return rankdata(np.asarray(x, dtype=np.float64), method="average")


@dataclasses.dataclass(frozen=True)
class SpearmanResult:
    """Spearman's rho with its p-value.

    Attributes
    ----------
    rho : float
        The rank correlation (NaN when undefined).
    pvalue : float
        Two-sided p-value (NaN when undefined).
    n : int
        Pairs used.
    """

    rho: float
    pvalue: float
    n: int


def spearman(x: Iterable[float], y: Iterable[float]) -> SpearmanResult:
    """Spearman's rho with its two-sided p-value.

    rho = the Pearson correlation of the average ranks; p from t = rho sqrt((n - 2) / (1 - rho^2)) with n - 2
    degrees of freedom.

    Parameters
    ----------
    x, y : iterable of float
        Paired values; pairs with a NaN in either are dropped.

    Returns
    -------
    SpearmanResult
        rho = p = NaN with fewer than 3 pairs or a constant input; p = 0 when |rho| = 1.

    Raises
    ------
    ValueError
        ``x`` and ``y`` differ in shape.
    """
    from scipy.special import stdtr

    x, y = (np.asarray(v if isinstance(v, np.ndarray) else list(v), dtype=np.float64) for v in (x, y))
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
    if abs(rho) >= 1.0:
        return SpearmanResult(rho, 0.0, n)
    t = rho * np.sqrt((n - 2) / ((1.0 - rho) * (1.0 + rho)))
    return SpearmanResult(rho, float(2.0 * stdtr(n - 2, -abs(t))), n)


#: the gain intervals of :func:`method_gains` (``evaluate.interval``; docs/intervals.md)
INTERVALS = {
    SEED_BOOTSTRAP: paired_seed_bootstrap,
    SEED_IMAGE_T: functools.partial(paired_seed_image_t, spacecraft=SPACECRAFT_FIXED),
    SEED_CLUSTER_T: functools.partial(paired_seed_image_t, spacecraft=SPACECRAFT_RANDOM),
}
#: what each interval covers, in a report's words; ``{spacecraft}``: the test groups' spacecraft count
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
DEFAULT_INTERVAL = PAPER.evaluate.interval
_GAIN_SUFFIXES = ("", "_lo", "_hi", "_seed_sd", "_p")


def method_gains(df, metrics: Sequence[str], control: str = BASELINE, by: Sequence[str] = ("dataset", "group", "threshold_mode"),
                 cluster_col: str = "spacecraft", n_resamples: int = 10_000, ci: float = PAPER.evaluate.ci, seed: int = 0,  # not a param: resampling
                 interval: str = DEFAULT_INTERVAL):
    """Gain of every method over ``control`` with paired seed-aware intervals, per ``by`` group.

    Each method is paired with the control on the seeds both have, seed by seed, and on the images every one of
    those seeds scored; images whose metric is NaN for either method are left out of that metric.
    ``gain_<m>`` is the mean over seeds and images of the differences (the difference of the seed-averaged
    means); its interval comes from ``interval``; comparisons on the same images share one resample set.

    Parameters
    ----------
    df : pandas.DataFrame
        Per-image metrics: ``method``, ``seed``, ``image_id``, ``cluster_col``, the ``by`` columns and the metrics.
    metrics : sequence of str
        Metric columns to compare.
    control : str, optional
        The control method (default :data:`pipeline.methods.BASELINE`); it gets no row.
    by : sequence of str, optional
        Grouping columns (default dataset, group, threshold_mode).
    cluster_col : str, optional
        The spacecraft column (default ``"spacecraft"``).
    n_resamples : int, optional
        Bootstrap resamples (default 10 000; unused by the t intervals).
    ci : float, optional
        Coverage (default 0.95).
    seed : int, optional
        Bootstrap seed, the same for every comparison (default 0).
    interval : str, optional
        A key of :data:`INTERVALS` (default :data:`DEFAULT_INTERVAL`, ``evaluate.interval``).

    Returns
    -------
    pandas.DataFrame
        One row per (by..., method): ``gain_seeds``, ``gain_images`` and per metric ``gain_<m>``,
        ``gain_<m>_lo``, ``gain_<m>_hi``, ``gain_<m>_seed_sd`` (NaN for one seed) and ``gain_<m>_p`` (NaN for
        the bootstrap).

    Raises
    ------
    ValueError
        ``interval`` is not a key of :data:`INTERVALS`.
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
        # comparisons on the same images share one resample set: one interval call, one column each
        pending: dict[tuple, list] = {}
        for method, treat in part[part["method"] != control].groupby("method", sort=True):
            seeds = sorted(set(treat["seed"]) & set(ctrl["seed"]))
            if not seeds:
                continue
            idx = ["image_id", cluster_col]
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
                    row.update({f"gain_{m}{s_}": np.nan for s_ in _GAIN_SUFFIXES})
                    continue
                tv, cv = sub[cols_t].to_numpy().T, sub[cols_c].to_numpy().T  # [S, n]
                per_seed = (tv - cv).mean(axis=1)
                row[f"gain_{m}_seed_sd"] = float(np.std(per_seed, ddof=1)) if len(seeds) > 1 else np.nan
                pending.setdefault((tuple(sub.index), len(seeds)), []).append((row, m, tv, cv))
            rows.append(row)
        for (items, _), cols in pending.items():
            res = interval_fn(np.stack([t for _, _, t, _ in cols], axis=2),
                              np.stack([c for _, _, _, c in cols], axis=2),
                              np.array([cl for _, cl in items]),
                              n_resamples=n_resamples, ci=ci, seed=seed)
            pvalue = getattr(res, "pvalue", None)
            for j, (row, m, _, _) in enumerate(cols):
                row.update({f"gain_{m}": float(res.estimate[j]), f"gain_{m}_lo": float(res.low[j]),
                            f"gain_{m}_hi": float(res.high[j]),
                            f"gain_{m}_p": float(pvalue[j]) if pvalue is not None else np.nan})
    cols = by + ["method", "gain_seeds", "gain_images"] + [f"gain_{m}{s}" for m in metrics for s in _GAIN_SUFFIXES]
    return pd.DataFrame(rows, columns=cols)


def vs_column(column: str, control: str) -> str:
    """Name a :func:`method_gains` column for a gain over ``control``.

    Parameters
    ----------
    column : str
        A gain column, e.g. ``gain_iou_lo``.
    control : str
        The control method.

    Returns
    -------
    str
        ``column`` unchanged over :data:`pipeline.methods.BASELINE`; else ``_vs_<control>`` before the bound
        suffix (``gain_iou_lo`` -> ``gain_iou_vs_continuation_lo``) or at the end.
    """
    if control == BASELINE:
        return column
    for end in ("_lo", "_hi", "_p"):
        if column.endswith(end):
            return f"{column.removesuffix(end)}_vs_{control}{end}"
    return f"{column}_vs_{control}"
