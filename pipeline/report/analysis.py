"""Teacher, gate, diagnostics and noise-floor analyses for the report: pure functions on DataFrames.

Also the teacher table they read (:func:`teacher_metrics`, the ``analyze_teacher`` stage's logic).  The teacher
table (``teacher_metrics.parquet``) has a row per image and source: ``prompt_<k>``, ``vote`` (eq:majority-vote) or
``val_selected`` (the prompt chosen on the validation split).
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np
import pandas as pd

from pipeline.artifacts.store import read_chunk_rows
from pipeline.methods import BASELINE, CONTINUATION, PROPOSED, SUPERVISED_CEILING
from pipeline.metrics import per_image_metrics
from pipeline.params import PAPER
from pipeline.runtime.errors import InputError
from pipeline.runtime.progress import progress
from pipeline.stats import (GAIN_SUPPORTED, LOSS_SUPPORTED, NO_DIFFERENCE, NOT_ESTIMATED, ONE_SEED, claim_status,
                            paired_seed_t_interval, seed_summary, spearman, vs_column)

__all__ = ["prompt_source", "select_prompt", "teacher_prompt_quality", "teacher_domain_quality", "gate_analysis",
           "teacher_vote_means", "epoch_swings", "size_split", "tau_text", "PRIMARY_ENDPOINT", "fixed_tau_findings",
           "noise_floor_records", "noise_floor_key", "select_noise_floor", "gain_noise_floor", "noise_floor_note",
           "teacher_metrics", "base_prompt_index"]

METRICS = ("iou", "bf1", "precision", "recall")


def prompt_source(k: int) -> str:
    """Name the teacher-table source of prompt ``k`` (``prompt_<k>``).

    Parameters
    ----------
    k : int
        The prompt's index in ``teacher.prompts`` (0-based).

    Returns
    -------
    str
        ``"prompt_<k>"``.
    """
    return f"prompt_{int(k)}"


def prompt_sources(tm: pd.DataFrame) -> list[str]:
    """List the single-prompt sources of teacher table ``tm``, by prompt index."""
    ks = sorted(int(s.split("_", 1)[1]) for s in tm["source"].unique() if str(s).startswith("prompt_"))
    return [prompt_source(k) for k in ks]


def select_prompt(tm: pd.DataFrame, split: str = "val", metric: str = "iou") -> tuple[str | None, pd.Series]:
    """Select the single prompt with the highest mean ``metric`` on ``split`` (ties to the lowest k).

    Parameters
    ----------
    tm : pandas.DataFrame
        The teacher table (``teacher_metrics.parquet``): a row per image and source.
    split : str
        The split the prompt is chosen on (the validation split: the test split never selects).
    metric : str
        The column compared (``iou``, ``bf1``, ...).

    Returns
    -------
    tuple of (str or None, pandas.Series)
        The chosen source (``prompt_<k>``; None when ``split`` has no single-prompt row) and the mean
        ``metric`` per prompt source, in prompt order.
    """
    sub = tm[(tm["split"] == split) & tm["source"].isin(prompt_sources(tm))]
    if sub.empty:
        return None, pd.Series(dtype=float)
    means = sub.groupby("source")[metric].mean()
    means = means.reindex([s for s in prompt_sources(tm) if s in means.index])
    return str(means.idxmax()), means


#: images per block of :func:`teacher_metrics` (memory only)
TEACHER_CHUNK = 32
#: the manifest columns the teacher table keeps
TEACHER_INFO = ["image_id", "dataset", "domain", "split", "group", "spacecraft"]


def base_prompt_index(teacher_meta) -> int:
    """Read the base prompt's index as recorded in the teacher artifact's params.

    Parameters
    ----------
    teacher_meta : pipeline.artifacts.lineage.Meta
        The teacher artifact's meta.

    Returns
    -------
    int
        ``teacher.base_prompt_index`` as recorded (unvalidated); the schema's default when absent.
    """
    p = teacher_meta.params or {}
    cfg = p.get("teacher", p)
    default = PAPER.teacher.base_prompt_index
    # unvalidated: a recorded artifact's params, written before the key existed
    return int(cfg.get("base_prompt_index", default)) if isinstance(cfg, dict) else default


def teacher_metrics(manifest, reference, teacher, consensus, tolerance: float, max_fraction: float
                    ) -> tuple[pd.DataFrame, str | None, pd.Series]:
    """Build the teacher table: each prompt's and the vote's per-image metrics on the validation and test images.

    Reference masks measure here only (post hoc), nothing feeds training.  The prompt with the best mean
    validation IoU (:func:`select_prompt`) is repeated as source ``val_selected``.

    Parameters
    ----------
    manifest, reference, teacher, consensus : pipeline.artifacts.store.Artifact
        The opened artifacts of one run.
    tolerance : float
        The boundary F1 tolerance in pixels (``evaluate.bf1_tolerance``).
    max_fraction : float
        The small-region limit (``evaluate.small_region_max_fraction``).

    Returns
    -------
    tuple
        (the table, the selected prompt's source or None, the per-prompt mean validation IoU).

    Raises
    ------
    InputError
        No validation or test image has a reference mask.
    """
    mdf = manifest.df
    prompts = list(teacher.attrs.get("prompts", []))
    k_prompts = teacher["masks"].shape[1]
    idx = np.flatnonzero(mdf["split"].isin(["val", "test"]).to_numpy() & reference.numpy("has_mask").astype(bool))
    if idx.size == 0:
        raise InputError(f"{manifest.path}: no validation/test image has a reference mask; nothing to analyse")
    info = mdf.iloc[idx][TEACHER_INFO].reset_index(drop=True)
    frames = []
    for s in progress(range(0, idx.size, TEACHER_CHUNK), desc="analyze_teacher"):
        rows = idx[s:s + TEACHER_CHUNK]
        gts = read_chunk_rows(reference["mask"], rows).astype(bool)
        masks = read_chunk_rows(teacher["masks"], rows).astype(bool)
        voted = read_chunk_rows(consensus["voted"], rows).astype(bool)
        sources = [(prompt_source(k), prompts[k] if k < len(prompts) else f"prompt {k}", masks[:, k])
                   for k in range(k_prompts)]
        sources.append(("vote", f"{k_prompts}-prompt majority vote", voted))
        for name, text, pred in sources:
            part = info.iloc[s:s + len(rows)].copy()
            part["source"], part["prompt"] = name, text
            for k, v in per_image_metrics(pred, gts, tolerance, max_fraction=max_fraction).items():
                part[k] = v
            frames.append(part)
    tm = pd.concat(frames, ignore_index=True)
    selected, val_means = select_prompt(tm, "val")
    if selected is not None:
        tm = pd.concat([tm, tm[tm["source"] == selected].assign(source="val_selected")], ignore_index=True)
    return tm, selected, val_means


def teacher_prompt_quality(tm: pd.DataFrame, group: str, base_source: str, selected_source: str | None,
                           prompts: list[str] | None = None) -> pd.DataFrame:
    """Tabulate the teacher's prompt quality on one group (paper Table ``tab:teacher-prompt-quality``).

    Rows: the base prompt, the validation-selected prompt, the mean ± std over the K separately evaluated
    prompts (not a fusion) and the K-prompt vote (eq:majority-vote).

    Parameters
    ----------
    tm : pandas.DataFrame
        The teacher table (``teacher_metrics.parquet``).
    group : str
        The test group tabulated.
    base_source : str
        The base prompt's source (``prompt_<k>``).
    selected_source : str or None
        The validation-selected prompt's source (:func:`select_prompt`); None leaves its row out.
    prompts : list of str, optional
        The prompt texts (``teacher.prompts``), shown in place of ``prompt_<k>``.

    Returns
    -------
    pandas.DataFrame
        Columns ``config``, ``n`` (images), and per metric ``<metric>`` and ``<metric>_std`` (the std is NaN but
        on the mean-over-prompts row).
    """
    g = tm[tm["group"] == group]
    srcs = prompt_sources(tm)

    def label(src):
        k = int(src.split("_", 1)[1])
        return f"`{prompts[k] if prompts and k < len(prompts) else src}`"

    rows = []

    def add(config, part, per_prompt=False):
        """Add a row of ``part``'s means (NaN std), or (``per_prompt``) the mean ± std of its prompts' means."""
        means = part.groupby("source")[list(METRICS)].mean() if per_prompt else part
        r = {"config": config, "n": int(part["image_id"].nunique())}
        for m in METRICS:
            r[m], r[f"{m}_std"] = float(means[m].mean()), float(means[m].std(ddof=1)) if per_prompt else np.nan
        rows.append(r)

    add(f"Base prompt: {label(base_source)}", g[g["source"] == base_source])
    if selected_source is not None:
        add(f"Validation-selected single prompt: {label(selected_source)}", g[g["source"] == selected_source])
    if len(prompted := g[g["source"].isin(srcs)]):
        add(f"Mean over {prompted['source'].nunique()} single prompts", prompted, per_prompt=True)
    add(f"{len(srcs)}-prompt majority vote", g[g["source"] == "vote"])
    return pd.DataFrame(rows)


def teacher_domain_quality(tm: pd.DataFrame, source: str = "vote", split: str = "test") -> pd.DataFrame:
    """Tabulate one teacher source's quality per domain (paper Table ``tab:teacher-domain-quality``).

    Parameters
    ----------
    tm : pandas.DataFrame
        The teacher table (``teacher_metrics.parquet``).
    source : str
        The source scored (``vote``: eq:majority-vote; or ``prompt_<k>``, ``val_selected``).
    split : str
        The split scored.

    Returns
    -------
    pandas.DataFrame
        Columns ``dataset``, ``domain``, ``group``, the mean metrics and ``n`` (images): a row per dataset /
        domain / group, plus a ``group="all"`` row for each dataset / domain with several groups.
    """
    sub = tm[(tm["source"] == source) & (tm["split"] == split)]
    per = _means(sub, ["dataset", "domain", "group"], sort=True).reset_index()
    pooled = _means(sub, ["dataset", "domain"], sort=True)
    pooled = pooled[sub.groupby(["dataset", "domain"], sort=True)["group"].nunique() > 1]
    return pd.concat([per, pooled.assign(group="all").reset_index()], ignore_index=True) if len(pooled) else per


def _means(df: pd.DataFrame, keys, sort: bool) -> pd.DataFrame:
    """Average :data:`METRICS` and count the images ``n`` per ``keys``."""
    out = df.groupby(keys, sort=sort)[list(METRICS)].mean()
    out["n"] = df.groupby(keys, sort=sort)["image_id"].nunique()
    return out


def gate_analysis(tm: pd.DataFrame, gates: pd.DataFrame, group: str | None = None,
                  split: str = "test") -> dict:
    """Relate the reliability gate g (eq:reliability-gate) to the vote's quality (paper Table ``tab:gate-groups``).

    Spearman's rho (with its p-value) between g and the vote's Image IoU / Boundary F1, and the mean quality of
    the images with g = 0 (geometry suppressed) against g > 0.

    Parameters
    ----------
    tm : pandas.DataFrame
        The teacher table (``teacher_metrics.parquet``); its ``vote`` rows are used.
    gates : pandas.DataFrame
        The gates table (``gates.parquet``): ``image_id`` and ``g``.
    group : str, optional
        The test group; None takes all of ``split``.
    split : str
        The split analysed.

    Returns
    -------
    dict
        ``group`` (``"all"`` for None), ``n`` (images with a gate), ``rho_iou``, ``p_iou``, ``rho_bf1``,
        ``p_bf1`` and ``table``: a DataFrame with columns ``state``, ``images``, ``iou``, ``bf1``.
    """
    v = tm[(tm["source"] == "vote") & (tm["split"] == split)]
    if group is not None:
        v = v[v["group"] == group]
    d = v.merge(gates[["image_id", "g"]], on="image_id", how="inner")
    rho = {k: spearman(d["g"].to_numpy(float), d[k].to_numpy(float)) for k in ("iou", "bf1")}
    states = (("g = 0: geometry suppressed", d[d["g"] <= 0]), ("g > 0: geometry enabled", d[d["g"] > 0]))
    rows = [{"state": state, "images": int(len(part)), "iou": float(part["iou"].mean()),
             "bf1": float(part["bf1"].mean())} for state, part in states]
    return {"group": group if group is not None else "all", "n": int(len(d)),
            "rho_iou": rho["iou"].rho, "p_iou": rho["iou"].pvalue, "rho_bf1": rho["bf1"].rho,
            "p_bf1": rho["bf1"].pvalue, "table": pd.DataFrame(rows)}


def teacher_vote_means(tm: pd.DataFrame, split: str = "test") -> pd.DataFrame:
    """Score the teacher vote (eq:majority-vote) as a predictor: its mean metrics per group of ``split``.

    Parameters
    ----------
    tm : pandas.DataFrame
        The teacher table (``teacher_metrics.parquet``).
    split : str
        The split scored.

    Returns
    -------
    pandas.DataFrame
        Indexed by group, in order of appearance: the mean ``iou``, ``bf1``, ``precision``, ``recall`` and
        ``n`` (images).
    """
    return _means(tm[(tm["source"] == "vote") & (tm["split"] == split)], "group", sort=False)


def epoch_swings(logs: pd.DataFrame) -> pd.DataFrame:
    """Measure how much validation Image IoU changes between adjacent epochs of a run, per (method, stage).

    Parameters
    ----------
    logs : pandas.DataFrame
        Training logs: ``method``, ``stage``, ``seed``, ``epoch``, ``val_iou`` (at the fixed tau), and where
        recorded ``val_iou_cal`` (at each epoch's calibrated tau) and ``val_tau_cal``.

    Returns
    -------
    pandas.DataFrame
        Per (method, stage) with a finite change: ``max_swing`` with its ``max_seed`` and ``max_epoch``,
        ``median_swing``, the same at the calibrated tau (``max_swing_cal``, ``median_swing_cal``; NaN
        without) and the calibrated tau's range (``tau_min``, ``tau_max``).
    """
    rows = []
    has_cal = "val_iou_cal" in logs.columns
    for (method, stage), part in logs.groupby(["method", "stage"], sort=False):
        d, dc, where = [], [], []
        for seed, run in part.sort_values("epoch").groupby("seed", sort=True):
            iou = run["val_iou"].to_numpy(float)
            d.extend(np.abs(np.diff(iou)))
            where.extend((int(seed), int(e)) for e in run["epoch"].to_numpy()[1:])
            if has_cal:
                dc.extend(np.abs(np.diff(run["val_iou_cal"].to_numpy(float))))
        d, dc = np.asarray(d, float), np.asarray(dc, float)
        ok = np.isfinite(d)
        if not ok.any():
            continue
        k = int(np.nanargmax(np.where(ok, d, -np.inf)))
        tau = part["val_tau_cal"].to_numpy(float) if "val_tau_cal" in part.columns else np.array([np.nan])
        fin = lambda a, f: float(f(a[np.isfinite(a)])) if np.isfinite(a).any() else np.nan  # noqa: E731
        rows.append({"method": method, "stage": int(stage), "max_swing": float(d[k]), "max_seed": where[k][0],
                     "max_epoch": where[k][1], "median_swing": fin(d, np.median),
                     "max_swing_cal": fin(dc, np.max), "median_swing_cal": fin(dc, np.median),
                     "tau_min": fin(tau, np.min), "tau_max": fin(tau, np.max)})
    return pd.DataFrame(rows)


def size_split(metrics: pd.DataFrame) -> pd.DataFrame:
    """Summarise Image IoU, Boundary F1 and area over seeds per method, threshold mode and target size.

    Parameters
    ----------
    metrics : pandas.DataFrame
        Per-image test metrics (``metrics.parquet``) with ``target_size`` (tiny under
        ``evaluate.tiny_target_max_fraction`` of the frame, or regular).

    Returns
    -------
    pandas.DataFrame
        :func:`pipeline.stats.seed_summary` of ``iou``, ``bf1`` and ``area_vs_reference``.
    """
    return seed_summary(metrics, ["method", "threshold_mode", "target_size"], ["iou", "bf1", "area_vs_reference"])


def tau_text(tau: float | None) -> str:
    """Write the fixed tau in the report's words: its value, or its param's name when unknown.

    Parameters
    ----------
    tau : float or None
        The fixed threshold (``calibrate.fixed_tau``, eq:inference-mask), None when not recorded.

    Returns
    -------
    str
        The value (``f"{tau:g}"``), or for None the param's name ``calibrate.fixed_tau`` in Markdown backticks.
    """
    return "`calibrate.fixed_tau`" if tau is None else f"{tau:g}"


@dataclasses.dataclass(frozen=True)
class Endpoint:
    """One difference a report can test: ``treatment`` - ``control`` in ``metric`` on ``group``."""

    group: str
    treatment: str
    control: str
    metric: str
    threshold_mode: str


#: the one primary endpoint of every report: the paper's lockbox comparison (docs/decisions.md)
PRIMARY_ENDPOINT = Endpoint(group="HJM", treatment=PROPOSED, control=BASELINE, metric="iou",
                            threshold_mode="calibrated")


def _f(x, digits=3) -> str:
    return "n/a" if x is None or not np.isfinite(x) else f"{x:.{digits}f}"


def _signed(x, digits=3) -> str:
    return "n/a" if x is None or not np.isfinite(x) else f"{x:+.{digits}f}"


@dataclasses.dataclass(frozen=True)
class _Cast:
    """Who is compared in :func:`fixed_tau_findings`, the groups, the labels and the fixed tau in words."""

    treatment: str
    control: str
    continuation: str
    ceiling: str
    groups: list
    label: Callable
    tau0: str
    T: str  # the labels of treatment, control and continuation
    C: str
    K: str


def _mean_tau(thresholds: pd.DataFrame, method: str, column: str = "tau") -> float:
    return float(thresholds.loc[thresholds["method"] == method, column].mean())


def _per_seed_difference(table: pd.DataFrame, treatment: str, control: str, column: str) -> list[float]:
    """``column`` of ``treatment`` minus ``control``, one per seed both have; [] without seeds."""
    if "seed" not in table.columns:
        return []
    per = table[table["method"].isin([treatment, control])].groupby(["method", "seed"])[column].mean()
    t, c = per.get(treatment), per.get(control)
    if t is None or c is None:
        return []
    return [float(t[s_] - c[s_]) for s_ in sorted(set(t.index) & set(c.index))]


def _threshold_findings(thresholds: pd.DataFrame | None, c: _Cast) -> tuple[list[str], float, float]:
    """Compare the calibrated tau of treatment and control, and their validation ECE; (sentences, tau_t, tau_c)."""
    if thresholds is None or not {c.treatment, c.control} <= set(thresholds["method"]):
        return [], np.nan, np.nan
    tau_t, tau_c = _mean_tau(thresholds, c.treatment), _mean_tau(thresholds, c.control)
    rel = "higher than" if tau_t > tau_c + 1e-9 else ("lower than" if tau_t < tau_c - 1e-9 else "equal to")
    out = [f"**Calibrated threshold.** The validation-calibrated tau of {c.T} is {_f(tau_t, 2)} (mean over "
           f"seeds), {rel} {c.C}'s {_f(tau_c, 2)} (difference {_signed(tau_t - tau_c, 2)})."]
    if "ece" in thresholds.columns:
        e_t, e_c = _mean_tau(thresholds, c.treatment, "ece"), _mean_tau(thresholds, c.control, "ece")
        d, lo, hi = paired_seed_t_interval(_per_seed_difference(thresholds, c.treatment, c.control, "ece"))
        if np.isfinite(lo) and (lo > 0 or hi < 0):
            verdict = f"{c.T} is {'worse' if lo > 0 else 'better'} calibrated at the pixel level"
        else:
            verdict = "no difference in pixel-level calibration detected"
        out.append(f"Validation expected calibration error: {c.T} {_f(e_t)}, {c.C} {_f(e_c)} (difference "
                   f"{_signed(d)}, 95 % t interval over the shared seeds [{_f(lo)}, {_f(hi)}]) -- {verdict}.")
    return out, tau_t, tau_c


#: the side of 0 an unadjusted CI lies on: the verdict words are reserved for the claim tables' full rule
INTERVAL_SIDE = {GAIN_SUPPORTED: "CI above 0", LOSS_SUPPORTED: "CI below 0", NO_DIFFERENCE: "CI covers 0",
                 ONE_SEED: ONE_SEED, NOT_ESTIMATED: NOT_ESTIMATED}


def _gain_findings(summary: pd.DataFrame | None, c: _Cast) -> tuple[list[str], bool | None]:
    """Give the sign of the Boundary F1 / Image IoU gain per group at both taus; (sentences, reversal)."""
    if summary is None:
        return [], None
    gains, verdicts = {}, {}
    for mode in ("calibrated", "fixed"):
        s = summary[(summary["threshold_mode"] == mode) & (summary["method"] == c.treatment)].set_index("group")
        gains[mode] = {k: [float(s.loc[g, f"gain_{k}"]) if g in s.index and f"gain_{k}" in s.columns else np.nan
                           for g in c.groups] for k in ("iou", "bf1")}
        verdicts[mode] = {k: [claim_status(*(float(s.loc[g].get(f"gain_{k}{x}", np.nan)) for x in ("", "_lo", "_hi")),
                                           None, s.loc[g].get("gain_seeds")) if g in s.index else NOT_ESTIMATED
                              for g in c.groups] for k in ("iou", "bf1")}
    n = sum(np.isfinite(x) for x in gains["fixed"]["bf1"])
    if not n:
        return [], None
    out = []
    for k, name in (("bf1", "Boundary F1"), ("iou", "Image IoU")):
        cal, fix = gains["calibrated"][k], gains["fixed"][k]
        vc, vf = verdicts["calibrated"][k], verdicts["fixed"][k]
        out.append(f"**{name} gain of {c.T} over {c.C}** per test group ({', '.join(c.groups)}), each with the "
                   f"side of 0 its seed-aware 95 % CI lies on (unadjusted and without the noise floor: the "
                   f"claim tables' verdicts add both): calibrated tau "
                   f"{', '.join(f'{_signed(x)} ({INTERVAL_SIDE[v]})' for x, v in zip(cal, vc))}; fixed tau = "
                   f"{c.tau0} {', '.join(f'{_signed(x)} ({INTERVAL_SIDE[v]})' for x, v in zip(fix, vf))}.")
    # a reversal is claimed only from intervals: a supported gain at the calibrated tau AND a supported
    # loss at the fixed tau, on most groups -- never from a majority of point-estimate signs
    vc, vf = verdicts["calibrated"]["bf1"], verdicts["fixed"]["bf1"]
    both = sum(a == GAIN_SUPPORTED and b == LOSS_SUPPORTED for a, b in zip(vc, vf))
    return out, both > n / 2


def _area_findings(metrics: pd.DataFrame | None, c: _Cast) -> tuple[list[str], bool | None]:
    """Median predicted / reference foreground area on the test images at both taus; (sentences, inflation)."""
    if metrics is None or "area_vs_reference" not in metrics.columns:
        return [], None
    med = metrics.groupby(["method", "threshold_mode"])["area_vs_reference"].median()
    get = lambda m, mode: float(med.get((m, mode), np.nan))  # noqa: E731
    if not (np.isfinite(get(c.treatment, "fixed")) and np.isfinite(get(c.control, "fixed"))):
        return [], None
    parts = [f"{c.label(m)} {_f(get(m, 'fixed'), 2)} at {c.tau0} and {_f(get(m, 'calibrated'), 2)} at its calibrated "
             f"tau" for m in (c.treatment, c.control, c.continuation, c.ceiling) if np.isfinite(get(m, "fixed"))]
    out = ["**Foreground area** (median predicted / reference area over the test images; 1 = none "
           "inflated): " + "; ".join(parts) + "."]
    return out, get(c.treatment, "fixed") > get(c.control, "fixed") and get(c.treatment, "fixed") > 1


def _reading(reversal: bool | None, inflation: bool | None, tau_t: float, tau_c: float, c: _Cast) -> list[str]:
    """Give the verdict on the fixed-tau reversal, from the three facts above."""
    if reversal is None or not np.isfinite(tau_t):
        return []
    facts = [reversal, tau_t > tau_c, bool(inflation)]
    if all(facts):
        return [f"**Reading.** The fixed-tau reversal is present and is a threshold effect: {c.T}'s "
                f"probabilities sit higher (calibrated tau {_signed(tau_t - tau_c, 2)} against {c.C}), so at "
                f"tau = {c.tau0} it inflates the foreground more than {c.C} and loses Boundary F1; the "
                f"validation-calibrated tau removes that loss."]
    if not reversal:
        return [f"**Reading.** No fixed-tau reversal detected: on most groups the Boundary F1 difference of {c.T} "
                f"does not have its seed-aware 95 % CI above 0 at the calibrated tau and below 0 at {c.tau0}."]
    missing = [w for w, ok in zip(("a higher calibrated tau", f"foreground inflation at {c.tau0}"), facts[1:])
               if not ok]
    return [f"**Reading.** The Boundary F1 gain reverses at tau = {c.tau0}, but without "
            f"{' or '.join(missing)}; the threshold explanation does not fully account for it here."]


def _continuation_findings(summary: pd.DataFrame | None, noise_floor: dict | None, c: _Cast) -> list[str]:
    """Treatment minus the budget-matched continuation, and the continuation minus control, at both taus."""
    vs = vs_column("gain_iou", c.continuation)
    if summary is None or vs not in summary.columns:
        return []
    out = []
    for mode, text in (("calibrated", "calibrated tau"), ("fixed", f"tau = {c.tau0}")):
        s = summary[summary["threshold_mode"] == mode].set_index(["method", "group"])
        geo = [(g, s.loc[(c.treatment, g)]) for g in c.groups if (c.treatment, g) in s.index]
        cont = [(g, s.loc[(c.continuation, g)]) for g in c.groups if (c.continuation, g) in s.index]
        if not geo or not cont:
            continue
        d_geo = [r[vs] for _, r in geo]
        # supported = seed-aware CI excludes 0 and the difference exceeds the noise floor (claim_status)
        st = [claim_status(r[vs], r[f"{vs}_lo"], r[f"{vs}_hi"],
                           gain_noise_floor(noise_floor, g, "iou") if noise_floor else None,
                           r.get(vs_column("gain_seeds", c.continuation))) for g, r in geo]
        d_cont = [r["gain_iou"] for _, r in cont]
        n_gain, n_loss = st.count(GAIN_SUPPORTED), st.count(LOSS_SUPPORTED)
        verdict = ("no geometry effect beyond the extra epochs detected (no seed-aware 95 % CI bound clears 0 "
                   "and the noise floor)" if not (n_gain or n_loss) else
                   f"the geometry terms raise Image IoU beyond the extra epochs on {n_gain} and lower it on "
                   f"{n_loss} of {len(st)} groups (the CI bound nearest 0 clears the noise floor)")
        share = ""
        tot = [r["gain_iou"] for _, r in geo]
        if all(np.isfinite(tot)) and np.mean(tot) > 1e-9:  # a share of a positive gain only
            share = (f"; the continuation accounts for {100 * np.mean(d_cont) / np.mean(tot):.0f} % of "
                     f"{c.T}'s mean Image IoU gain over {c.C}")
        out.append(f"**Budget-matched continuation ({text}).** {c.T} − {c.K}: Image IoU "
                   f"{', '.join(_signed(x) for x in d_geo)}; {c.K} − {c.C}: {', '.join(_signed(x) for x in d_cont)} "
                   f"-- {verdict}{share}.")
    return out


def _ceiling_finding(summary: pd.DataFrame | None, c: _Cast) -> list[str]:
    """Compare the supervised ceiling minus control at the calibrated tau with control's seed spread."""
    if summary is None or c.ceiling not in set(summary["method"]):
        return []
    s = summary[summary["threshold_mode"] == "calibrated"].set_index(["method", "group"])
    diff = [float(s.loc[(c.ceiling, g), "iou_mean"] - s.loc[(c.control, g), "iou_mean"])
            for g in c.groups if (c.ceiling, g) in s.index and (c.control, g) in s.index]
    if not diff:
        return []
    std = [float(s.loc[(c.control, g), "iou_std"]) for g in c.groups if (c.control, g) in s.index]
    spread = float(np.nanmax(std)) if np.isfinite(std).any() else 0.0
    verdict = ("no better than Plain beyond its seed spread: with this recipe the student, not the "
               "pseudo-labels, bounds quality" if max(diff) <= spread else
               "above Plain: better labels would raise this student")
    return [f"**{c.label(c.ceiling)}** minus {c.C}, Image IoU at the calibrated tau per "
            f"group: {', '.join(_signed(x) for x in diff)} (largest seed std of {c.C}: {_f(spread)}) -- "
            f"{verdict}."]


def _vote_finding(vote: pd.DataFrame | None, summary: pd.DataFrame | None, c: _Cast) -> list[str]:
    """Give the teacher vote's Image IoU minus the treatment's, per group."""
    if vote is None or summary is None or not len(vote):
        return []
    s = summary[summary["threshold_mode"] == "calibrated"].set_index(["method", "group"])
    gap = [float(vote.loc[g, "iou"] - s.loc[(c.treatment, g), "iou_mean"])
           for g in c.groups if g in vote.index and (c.treatment, g) in s.index]
    if not gap:
        return []
    return [f"**Teacher vote as a predictor**: its Image IoU minus {c.T}'s per group "
            f"{', '.join(_signed(x) for x in gap)} -- the students "
            f"{'stay below' if min(gap) > 0 else 'reach'} the pseudo-labels they learn from."]


def _size_finding(metrics: pd.DataFrame | None, c: _Cast) -> list[str]:
    """Give the treatment's Image IoU difference to the control on tiny targets and on the rest."""
    if metrics is None or "target_size" not in metrics.columns or "seed" not in metrics.columns:
        return []
    per_seed = metrics.groupby(["method", "threshold_mode", "target_size", "seed"])["iou"].mean()
    mean = per_seed.groupby(level=[0, 1, 2]).mean()
    n_img = metrics[metrics["method"] == c.control].groupby(["target_size", "seed", "threshold_mode"]).size()
    parts = []
    for size in ("tiny", "regular"):
        d = {mode: float(mean.get((c.treatment, mode, size), np.nan) - mean.get((c.control, mode, size), np.nan))
             for mode in ("calibrated", "fixed")}
        if np.isfinite(d["calibrated"]):
            n = int(n_img.xs(size, level="target_size").max()) if size in n_img.index.get_level_values(0) else 0
            parts.append(f"{size} targets ({n} images per seed): {_signed(d['calibrated'])} at the calibrated tau, "
                         f"{_signed(d['fixed'])} at {c.tau0}")
    if not parts:
        return []
    return [f"**Target size** ({c.T} − {c.C}, Image IoU; tiny = under evaluate.tiny_target_max_fraction of "
            f"the frame): " + "; ".join(parts) + "."]


def _swing_finding(logs: pd.DataFrame | None, c: _Cast) -> list[str]:
    """Compare the largest per-epoch change of validation IoU at the fixed tau with that at the calibrated tau."""
    if logs is None or "val_iou_cal" not in logs.columns:
        return []
    sw = epoch_swings(logs)
    if sw.empty:
        return []
    r = sw.loc[sw["max_swing"].idxmax()]
    cal = float(sw["max_swing_cal"].max())
    steadier = ("steadier: much of the swing is a threshold shift" if np.isfinite(cal) and cal < 0.5 * r["max_swing"]
                else "about as unsteady: the swing is not only a threshold shift")
    return [f"**Per-epoch validation IoU.** The largest change between adjacent epochs at tau {c.tau0} is "
            f"{_f(r['max_swing'])} ({c.label(r['method'])}, seed {int(r['max_seed'])}, epoch "
            f"{int(r['max_epoch'])}); at each epoch's calibrated tau the largest is {_f(cal)} -- {steadier}."]


def fixed_tau_findings(summary: pd.DataFrame | None, thresholds: pd.DataFrame | None, metrics: pd.DataFrame | None,
                       logs: pd.DataFrame | None, vote: pd.DataFrame | None, groups: list[str],
                       treatment: str = PROPOSED, control: str = BASELINE, continuation: str = CONTINUATION,
                       ceiling: str = SUPERVISED_CEILING, label=lambda m: m, noise_floor: dict | None = None,
                       fixed_tau: float | None = None) -> list[str]:
    """Write what the diagnostics show about the fixed-tau reversal, in sentences.

    Every verdict compares the numbers it quotes: one finding per ``_*_finding(s)`` function, where its inputs
    exist (a missing table drops its findings).

    Parameters
    ----------
    summary : pandas.DataFrame or None
        The seed summary (``summary.parquet``): per method, group and threshold mode, the metric means, stds and
        gains with their seed-aware CIs.
    thresholds : pandas.DataFrame or None
        The calibrated thresholds (``thresholds.parquet``): ``method``, ``seed``, ``tau``, and ``ece`` where
        recorded.
    metrics : pandas.DataFrame or None
        Per-image test metrics (``metrics.parquet``).
    logs : pandas.DataFrame or None
        Training logs (:func:`epoch_swings`).
    vote : pandas.DataFrame or None
        The teacher vote's means per group (:func:`teacher_vote_means`).
    groups : list of str
        The test groups, in report order.
    treatment, control, continuation, ceiling : str
        The methods compared: the proposed recipe, its control, the budget-matched continuation and the
        supervised ceiling.
    label : callable
        Method name -> its name in the report.
    noise_floor : dict, optional
        The noise-floor record of this configuration (:func:`select_noise_floor`); None: CIs alone decide.
    fixed_tau : float, optional
        The fixed threshold (``calibrate.fixed_tau``); None names the param instead (:func:`tau_text`).

    Returns
    -------
    list of str
        Markdown paragraphs.
    """
    c = _Cast(treatment, control, continuation, ceiling, list(groups), label, tau_text(fixed_tau), label(treatment),
              label(control), label(continuation))
    thresholds_out, tau_t, tau_c = _threshold_findings(thresholds, c)
    gains_out, reversal = _gain_findings(summary, c)
    area_out, inflation = _area_findings(metrics, c)
    return (thresholds_out + gains_out + area_out + _reading(reversal, inflation, tau_t, tau_c, c)
            + _continuation_findings(summary, noise_floor, c) + _ceiling_finding(summary, c)
            + _vote_finding(vote, summary, c) + _size_finding(metrics, c) + _swing_finding(logs, c))


NOISE_FLOOR_NOT_MEASURED = ("noise floor not measured in this report's configuration (recipe, resolution, data "
                            "sizes): the verdicts rest on the CI and the multiplicity rule alone; a floor measured "
                            "elsewhere is never applied (python -m benchmarks.stability --noise-floor measures one)")


def noise_floor_records(doc: dict | None) -> dict[str, dict]:
    """Read the records of a noise-floor file (reports/noise_floor.json) by key.

    Parameters
    ----------
    doc : dict or None
        The parsed file: ``{"recipes": {key: record}}``, or a former single-record file (with ``numbers``).

    Returns
    -------
    dict
        Key (:func:`noise_floor_key`) -> record; a single-record file's key is its ``info.recipe``.  Empty for
        None or an empty file.
    """
    if not doc:
        return {}
    if "numbers" in doc:
        return {doc.get("info", {}).get("recipe", "?"): doc}
    return dict(doc.get("recipes", {}))


def noise_floor_key(recipe: str, profile: str | None = None, resolution: int | None = None) -> str:
    """Key a record in reports/noise_floor.json: the recipe (demo profile), else ``<recipe>@<profile>-<res>``.

    Parameters
    ----------
    recipe : str
        The training recipe (``train.recipe``).
    profile : str, optional
        The params profile; None or ``"demo"`` keys by the recipe alone.
    resolution : int, optional
        The working resolution (``data.resolution``).

    Returns
    -------
    str
        The key.
    """
    if profile in (None, "demo"):
        return recipe
    return f"{recipe}@{profile}-{resolution}"


def select_noise_floor(doc: dict | None, recipe: str | None, resolution: int | None = None,
                       profile: str | None = None) -> dict | None:
    """Select the noise-floor record measured in the report's own configuration.

    A floor measured elsewhere is never applied: the record must match the recipe, and the resolution and
    profile where both sides know them.

    Parameters
    ----------
    doc : dict or None
        The parsed noise-floor file (:func:`noise_floor_records`).
    recipe : str or None
        The report's training recipe; None (several recipes, or unknown) selects nothing.
    resolution : int, optional
        The report's working resolution; None is not compared.
    profile : str, optional
        The report's params profile; None is not compared.

    Returns
    -------
    dict or None
        The record with ``applies_to`` (``recipe``, ``resolution``, ``profile``) added; None when none matches.
    """
    if recipe is None:
        return None
    for key, rec in noise_floor_records(doc).items():
        info = rec.get("info", {})
        if info.get("recipe", key) != recipe:
            continue
        if resolution is not None and info.get("resolution") is not None and int(info["resolution"]) != int(resolution):
            continue
        if profile and info.get("profile") and info["profile"] != profile:
            continue
        return {**rec, "applies_to": {"recipe": recipe, "resolution": resolution, "profile": profile or None}}
    return None


def gain_noise_floor(record: dict | None, group: str, metric: str) -> float:
    """Read the noise floor of a gain: the largest ``floor`` of any ``<treatment>-<control>/<group>/<metric>``.

    Parameters
    ----------
    record : dict or None
        A noise-floor record (:func:`select_noise_floor`).
    group : str
        The test group.
    metric : str
        The metric (``iou``, ``bf1``).

    Returns
    -------
    float
        The largest finite floor (a former record's ``pert``), or NaN when there is none.
    """
    if not record:
        return float("nan")
    vals = [v.get("floor", v.get("pert")) for k, v in record.get("numbers", {}).items()
            if "-" in k.split("/")[0] and k.split("/")[1:] == [str(group), metric]]
    vals = [x for x in vals if x is not None and np.isfinite(x)]
    return float(max(vals)) if vals else float("nan")


def noise_floor_note(record: dict | None) -> str:
    """Write one sentence naming where the noise floor comes from, or that it was not measured here.

    Parameters
    ----------
    record : dict or None
        The noise-floor record of this configuration (:func:`select_noise_floor`).

    Returns
    -------
    str
        The sentence (:data:`NOISE_FLOOR_NOT_MEASURED` for None).
    """
    if not record:
        return NOISE_FLOOR_NOT_MEASURED + "."
    i = record.get("info", {})
    seeds, perturbed = i.get("seeds", "?"), i.get("pert_seeds")
    if perturbed and list(perturbed) != list(seeds):  # the moves come from the perturbed seeds' mean only
        seeds = f"{seeds}, perturbed on {perturbed}"
    return (f"Noise floor: the largest move of a gain's seed-mean under a numerical perturbation "
            f"({', '.join(i.get('perturbations', ['?']))}; threads1 = 1 instead of 2 threads, precision = fp32 vs "
            f"bf16), measured by the stability benchmark in this report's configuration (recipe "
            f"{i.get('recipe', '?')}, tau rule {i.get('tau_rule', '?')}, {i.get('resolution', '?')}², "
            f"{i.get('profile', '?')} sizes, epochs {i.get('epochs', '?')}, seeds {seeds}"
            f"{', on ' + str(i['cpu']) if i.get('cpu') else ''}; reports/noise_floor.json); a difference is "
            f"supported only when the bound of its seed-aware CI nearest 0 clears the floor.")
