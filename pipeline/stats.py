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
  widen it.  :func:`method_gains` uses it.
* :func:`claim_status` -- the report's wording rule: a gain is "supported" only when its seed-aware
  CI excludes zero and the gain is larger than its noise floor.
* :func:`spearman` -- Spearman's rank correlation with its two-sided p-value (t approximation with
  n - 2 degrees of freedom, as ``scipy.stats.spearmanr``), used for the gate analysis.

Pure numpy functions on arrays (no I/O); the tables they feed are built in ``pipeline.report.tables``.
"""

from __future__ import annotations

import dataclasses
from typing import Iterable, Iterator, Sequence

import numpy as np

from pipeline.methods import BASELINE

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
    t = np.asarray(treatment, dtype=np.float64)
    c = np.asarray(control, dtype=np.float64)
    if t.shape != c.shape or t.ndim not in (2, 3) or t.shape[0] == 0:
        raise ValueError(f"treatment {t.shape} and control {c.shape} must be matched [S, n] or [S, n, k]")
    if not 0.0 < ci < 1.0:
        raise ValueError(f"ci={ci} must lie in (0, 1)")
    d = t - c
    d3 = d[..., None] if d.ndim == 2 else d
    if np.isnan(d3).any():
        raise ValueError("paired differences contain NaN; drop undefined images before bootstrapping")
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


#: :func:`claim_status` outcomes
SUPPORTED = "supported"
CI_COVERS_ZERO = "not supported: the CI covers 0"
BELOW_NOISE_FLOOR = "not supported: below the noise floor"
NOT_ESTIMATED = "not estimated"
ONE_SEED = "not supported: one seed (its CI holds no training noise)"


def claim_status(gain: float, low: float, high: float, noise_floor: float | None = None,
                 n_seeds: int | None = None) -> str:
    """Whether a gain may be called supported: its seed-aware CI [low, high] excludes 0 AND (when a
    noise floor is known) |gain| exceeds it AND (when ``n_seeds`` is given) it rests on at least two
    seeds -- a one-seed CI resamples spacecraft and images only, so it holds no training noise and is
    not seed-aware (the single-seed ablations); None or NaN = unknown.  ``noise_floor`` None or NaN = not measured (the CI alone
    decides; the report says the floor was not measured).  Non-finite gain or bounds -> not estimated.
    The CI check comes first: a gain inside its CI's zero-cover is reported as such."""
    if not all(np.isfinite(x) for x in (gain, low, high)):
        return NOT_ESTIMATED
    if low <= 0.0 <= high:
        return CI_COVERS_ZERO
    if noise_floor is not None and np.isfinite(noise_floor) and abs(gain) <= noise_floor:
        return BELOW_NOISE_FLOOR
    if n_seeds is not None and np.isfinite(n_seeds) and n_seeds < 2:
        return ONE_SEED
    return SUPPORTED


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
def method_gains(df, metrics: Sequence[str], control: str = BASELINE, by: Sequence[str] = ("dataset", "group", "threshold_mode"),
                 cluster_col: str = "spacecraft", n_resamples: int = 10_000, ci: float = 0.95, seed: int = 0):
    """Gain of every method over ``control`` with paired hierarchical bootstrap CIs, per ``by`` group.

    ``df`` is the per-image metrics table (columns: method, seed, image_id, ``cluster_col``, ``by``,
    metrics).  For each method the pairing uses the seeds it shares with the control (e.g. a seed-42
    ablation is compared with the seed-42 control), paired seed by seed, and the images every one of
    those seeds of both methods has; ``gain_<m>`` = mean over seeds and images of the differences
    (= the difference of the seed-averaged means) and its CI comes from :func:`paired_seed_bootstrap`
    (seeds, then spacecraft, then images; same ``seed`` for every comparison: every method is compared
    with the control on the same resamples).  ``gain_<m>_seed_sd`` = sample std over seeds of the
    per-seed mean differences (NaN for one seed).  Images whose metric is NaN for either method (an
    undefined small-region IoU) are left out of that metric's comparison.
    Returns one row per (by..., method) with ``gain_seeds`` (shared seeds), ``gain_images``,
    ``gain_<m>``, ``gain_<m>_lo``, ``gain_<m>_hi``, ``gain_<m>_seed_sd``; the control gets no row.
    """
    import pandas as pd

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
                                f"gain_{m}_seed_sd": np.nan})
                    continue
                tv, cv = sub[cols_t].to_numpy().T, sub[cols_c].to_numpy().T  # [S, n]
                per_seed = (tv - cv).mean(axis=1)
                row[f"gain_{m}_seed_sd"] = float(np.std(per_seed, ddof=1)) if len(seeds) > 1 else np.nan
                pending.setdefault((tuple(sub.index), len(seeds)), []).append((row, m, tv, cv))
            group_rows.append(row)
        for (items, _), cols in pending.items():
            res = paired_seed_bootstrap(np.stack([t for _, _, t, _ in cols], axis=2),
                                        np.stack([c for _, _, _, c in cols], axis=2),
                                        np.array([cl for _, cl in items]),
                                        n_resamples=n_resamples, ci=ci, seed=seed)
            for j, (row, m, _, _) in enumerate(cols):
                row.update({f"gain_{m}": float(res.estimate[j]), f"gain_{m}_lo": float(res.low[j]),
                            f"gain_{m}_hi": float(res.high[j])})
        rows.extend(group_rows)
    cols = by + ["method", "gain_seeds", "gain_images"] + [f"gain_{m}{s}" for m in metrics
                                                           for s in ("", "_lo", "_hi", "_seed_sd")]
    return pd.DataFrame(rows, columns=cols)


def vs_column(column: str, control: str) -> str:
    """The summary's name of :func:`method_gains` column ``column`` when the gain is over ``control``: as
    is over :data:`pipeline.methods.BASELINE` (``gain_iou``), else with ``_vs_<control>`` before the
    bound (``gain_iou_lo`` -> ``gain_iou_vs_continuation_lo``, ``gain_seeds`` -> ``gain_seeds_vs_continuation``)."""
    if control == BASELINE:
        return column
    for end in ("_lo", "_hi"):
        if column.endswith(end):
            return f"{column.removesuffix(end)}_vs_{control}{end}"
    return f"{column}_vs_{control}"
