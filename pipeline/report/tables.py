"""Tables shaped like the paper's: DataFrames in, :class:`pipeline.report.document.Table` out."""

from __future__ import annotations

import contextlib
import contextvars
from typing import Iterator, Mapping, Sequence

import numpy as np
import pandas as pd

from pipeline.report.dvc_results import EFFICIENCY_TARGETS, distillation_efficiency, efficiency_target_met, seed_ratio
from pipeline.methods import (BASELINE, CONTINUATION, METHODS, PROPOSED, STAGE_ONE, ablation_table_rows,
                              annotation_free_methods, in_table_order, method_label, methods_with_role, run_label)
from pipeline.report.analysis import PRIMARY_ENDPOINT, gain_noise_floor, noise_floor_note, tau_text
from pipeline.report.document import Table
from pipeline.stats import (ALPHA, DEFAULT_INTERVAL, INTERVAL_TEXT, NOT_ESTIMATED, SEED_BOOTSTRAP, claim_status,
                            holm_adjust, vs_column)

__all__ = ["ABLATIONS", "human_trained", "label", "spacecraft_per_group", "results_table", "diagnostics_table",
           "thresholds_table", "ablation_means", "warm_start_table", "component_table", "teacher_prompt_table",
           "teacher_domain_table", "gate_table", "efficiency_table", "controls_table", "reference_points_table",
           "calibration_table", "epoch_swing_table", "size_split_table"]

#: the main comparison's rows: every annotation-free method but the ablations, in table order
MAIN_ORDER = in_table_order(n for n in annotation_free_methods(METHODS) if METHODS[n].role != "ablation")
WARM_START_ROWS = ablation_table_rows("warm_start")
COMPONENT_ROWS = ablation_table_rows("component")
ABLATIONS = set(methods_with_role("ablation"))
#: the teacher vote scored as a predictor (a row of the reference-points table; not a method)
TEACHER_VOTE_LABEL = "Teacher vote (6-prompt majority, its own binary mask)"
VS_CONTINUATION = vs_column("", CONTINUATION)
#: the gain metrics a claim speaks of, with their names in a claim cell
CLAIM_METRICS = (("iou", "IoU"), ("bf1", "BF1"))
QUALITY = ("iou", "bf1", "precision", "recall")


def mode_text(mode: str, fixed_tau: float | None) -> str:
    """Write a threshold mode in words (``fixed_tau``: calibrate.fixed_tau as recorded; None names the param)."""
    return {"calibrated": "validation-calibrated tau", "fixed": f"fixed tau = {tau_text(fixed_tau)}"}.get(mode, mode)


#: {method: the ``review`` params its runs trained under} while a report is built (:func:`human_trained`)
_RUN_REVIEW: contextvars.ContextVar[Mapping] = contextvars.ContextVar("run_review", default={})


#: {method: the names of its runs' departures from eq:raw-loss} while a report is built (:func:`human_trained`)
_DEPARTURES: contextvars.ContextVar[Mapping] = contextvars.ContextVar("departures", default={})


@contextlib.contextmanager
def human_trained(run_review: Mapping[str, Mapping], departures: Mapping[str, list] | None = None
                  ) -> Iterator[None]:
    """Label runs by how they trained while the block runs (a context manager).

    Within the block, :func:`label` marks the runs trained on human corrections NOT annotation-free, and names the
    departures from eq:raw-loss a method's runs trained with.

    Parameters
    ----------
    run_review : Mapping
        Method -> the ``review`` params its runs trained under (:func:`pipeline.report.build.recorded_review`).
    departures : Mapping, optional
        Method -> the names of its runs' departures from eq:raw-loss
        (:func:`pipeline.report.build.recorded_departures`).

    Yields
    ------
    None
        Control, with the labels in force; they are restored on leaving.
    """
    tokens = _RUN_REVIEW.set(dict(run_review)), _DEPARTURES.set(dict(departures or {}))
    try:
        yield
    finally:
        _RUN_REVIEW.reset(tokens[0])
        _DEPARTURES.reset(tokens[1])


def label(method: str) -> str:
    """Give the method's display label, for the runs it names (:func:`human_trained`).

    Parameters
    ----------
    method : str
        The method's name (a key of :data:`pipeline.methods.METHODS`, or any other name).

    Returns
    -------
    str
        Its label (:func:`pipeline.methods.run_label`), marked NOT annotation-free where its runs trained on human
        corrections, and followed by ``+ <departure names>`` where they departed from eq:raw-loss (e.g.
        "Plain Student + bootstrapped targets, beta 0.8").
    """
    base = run_label(METHODS[method], _RUN_REVIEW.get().get(method)) if method in METHODS else method_label(method)
    names = _DEPARTURES.get().get(method)
    return f"{base} + {', '.join(names)}" if names else base


def not_annotation_free(methods: Sequence[str]) -> list[str]:
    """List the methods (each once, in order) that are not annotation-free."""
    free = set(annotation_free_methods(methods))
    return [m for m in dict.fromkeys(methods) if m not in free]


def _finite(x) -> bool:
    """Tell whether ``x`` is a finite number (not None)."""
    return x is not None and bool(np.isfinite(x))


def fmt(x, digits: int = 4) -> str:
    """Format ``x`` with ``digits`` decimals; ``--`` when it is missing or not finite."""
    return f"{x:.{digits}f}" if _finite(x) else "--"


def fmt_pm(mean, std, digits: int = 4) -> str:
    """Format ``mean ± std``; the std is omitted where undefined (one seed)."""
    return fmt(mean, digits) + (f" ± {std:.{digits}f}" if _finite(mean) and _finite(std) else "")


def fmt_ci(gain, lo, hi, digits: int = 4) -> str:
    """Format a signed gain and its CI, ``+g [lo, hi]``; ``--`` without a finite gain."""
    return f"{gain:+.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]" if _finite(gain) else "--"


def fmt_p(p) -> str:
    """Format a p-value (scientific below 1e-3); ``--`` when it is not finite."""
    return (f"{p:.2e}" if p < 1e-3 else f"{p:.4f}") if _finite(p) else "--"


def _ms(r, key: str, digits: int = 4) -> str:
    """Format ``<key>_mean ± <key>_std`` of a summary row."""
    return fmt_pm(r.get(f"{key}_mean"), r.get(f"{key}_std"), digits)


def main_methods(methods: Sequence[str]) -> list[str]:
    """Order the main comparison's methods present as the paper does (unknown names last, ablations out)."""
    present = annotation_free_methods(list(dict.fromkeys(methods)))
    known = [m for m in MAIN_ORDER if m in present]
    return known + sorted(m for m in present if m not in MAIN_ORDER and m not in ABLATIONS)


def group_method_rows(summary: pd.DataFrame, mode: str, groups: Sequence[str]):
    """Yield (group, method, summary row) at threshold ``mode``: groups in the given order, main methods in order."""
    s = summary[summary["threshold_mode"] == mode]
    for g in groups:
        part = s[s["group"] == g].set_index("method")
        for m in main_methods(part.index):
            yield g, m, part.loc[m]


def is_primary(group: str, treatment: str, control: str, mode: str) -> bool:
    """Tell whether this Image IoU difference is the report's one primary endpoint."""
    e = PRIMARY_ENDPOINT
    return (group, treatment, control, mode) == (e.group, e.treatment, e.control, e.threshold_mode)


def family_holm(entries) -> dict:
    """Holm-adjust the p-values of one table's family: ``{(key, metric): adjusted p}``.

    ``entries``: (key, summary row, suffix, is_primary) per shown difference.  The primary endpoint is tested
    alone, outside every family.
    """
    keys, ps = [], []
    for key, r, suffix, primary in entries:
        for k, _ in CLAIM_METRICS:
            if primary and k == PRIMARY_ENDPOINT.metric:
                continue
            keys.append((key, k))
            ps.append(float(r.get(f"gain_{k}{suffix}_p", np.nan)))
    return dict(zip(keys, holm_adjust(ps)))


def _gain_cells(r, suffix: str, group: str, key, holm: Mapping, primary: bool, noise_floor) -> list[str]:
    """Write a summary row's gain cells: each gain's CI, the group's noise floor and the claim.

    The CI of each :data:`CLAIM_METRICS` gain ``gain_<metric><suffix>``; the claim is
    :func:`pipeline.stats.claim_status` of each gain against the floor, with the p-value ``holm[(key, metric)]``
    (:func:`family_holm`); ``primary``: the row holds the primary endpoint.
    """
    cis, claims = [], []
    for k, name in CLAIM_METRICS:
        gain = [float(r.get(f"gain_{k}{suffix}{x}", np.nan)) for x in ("", "_lo", "_hi")]
        cis.append(fmt_ci(*gain))
        st = claim_status(*gain, gain_noise_floor(noise_floor, group, k) if noise_floor else None,
                          r.get(f"gain_seeds{suffix}"), holm.get((key, k)))
        if st != NOT_ESTIMATED:
            claims.append(f"{name}: {st}" + (" (primary endpoint)" if primary and k == PRIMARY_ENDPOINT.metric else ""))
    return [*cis, floor_cell(group, noise_floor), "; ".join(claims) or "--"]


def spacecraft_per_group(manifest: pd.DataFrame) -> dict[str, int]:
    """Count the distinct spacecraft per group (for the data table and the interval footnotes).

    Parameters
    ----------
    manifest : pandas.DataFrame
        The image manifest: ``group`` and ``spacecraft`` per image.

    Returns
    -------
    dict
        Group -> its number of distinct spacecraft, in manifest order.
    """
    return {str(g): int(n) for g, n in manifest.groupby("group", sort=False)["spacecraft"].nunique().items()}


def spacecraft_words(spacecraft: Mapping[str, int] | None, groups: Sequence[str]) -> str:
    """Write how many spacecraft ``groups`` hold, "3 spacecraft" (or "1-3 spacecraft"); "few spacecraft" unknown."""
    counts = sorted({int(spacecraft[g]) for g in groups if g in spacecraft}) if spacecraft else []
    if not counts:
        return "few spacecraft"
    return f"{counts[0]} spacecraft" if len(counts) == 1 else f"{counts[0]}-{counts[-1]} spacecraft"


def interval_text(interval: str | None, spacecraft: Mapping[str, int] | None = None,
                  groups: Sequence[str] = ()) -> str:
    """Write how a table's CIs were made (``interval``: evaluate.interval as recorded; None: the former bootstrap)."""
    return INTERVAL_TEXT[interval or SEED_BOOTSTRAP].format(spacecraft=spacecraft_words(spacecraft, groups))


def multiplicity_note(holm: Mapping) -> str:
    """Name the primary endpoint, the family and the procedure (a summary without p-values: not adjusted)."""
    e = PRIMARY_ENDPOINT
    family_size = sum(np.isfinite(p) for p in holm.values())
    if holm and not family_size:
        return (f"Primary endpoint: {e.group}, {label(e.treatment)} − {label(e.control)}, Image IoU at the "
                f"validation-calibrated tau.  This summary holds no p-values (evaluated before they were "
                f"recorded), so the {len(holm)} exploratory differences are NOT multiplicity-adjusted here.")
    return (f"Primary endpoint: {e.group}, {label(e.treatment)} − {label(e.control)}, Image IoU at the "
            f"validation-calibrated tau (the paper's lockbox), tested alone at alpha = {ALPHA}.  Every other "
            f"difference is exploratory: Holm's step-down procedure over the {family_size} differences this "
            f"table shows (its family) controls the family-wise error at alpha = {ALPHA}.  A difference is "
            f"supported only when its CI excludes 0, its bound nearest 0 clears the noise floor and its "
            f"Holm-adjusted p-value is below alpha; otherwise \"no difference detected\", with no direction.")


def floor_cell(group: str, noise_floor) -> str:
    """Write a group's noise floor as ``IoU / BF1``, or "not measured"."""
    vals = [gain_noise_floor(noise_floor, group, k) for k in ("iou", "bf1")]
    return "not measured" if not all(np.isfinite(vals)) else f"{fmt(vals[0])} / {fmt(vals[1])}"


def results_table(summary: pd.DataFrame, mode: str, groups: Sequence[str], noise_floor: dict | None = None,
                  fixed_tau: float | None = None, interval: str | None = DEFAULT_INTERVAL,
                  spacecraft: Mapping[str, int] | None = None) -> Table:
    """Tabulate the main results (paper Table ``tab:spacesense-results``).

    Per group and method: Image IoU and Boundary F1 over seeds, the gains against Plain Student with their CIs,
    the noise floor and the claim (Holm-adjusted over the table's family, the primary endpoint alone).

    Parameters
    ----------
    summary : pandas.DataFrame
        The seed summary (``summary.parquet``): per group, method and threshold mode, the metrics' seed means and
        stds and the gains with their CIs, p-values and seed counts.
    mode : str
        The threshold mode shown: ``"calibrated"`` or ``"fixed"``.
    groups : sequence of str
        The test groups, in table order.
    noise_floor : dict, optional
        The noise-floor record of this configuration (:func:`pipeline.report.analysis.select_noise_floor`); None:
        not measured, the claims rest on the CIs and the multiplicity rule alone.
    fixed_tau : float, optional
        ``calibrate.fixed_tau`` as the runs recorded it, for the caption; None names the param.
    interval : str or None
        ``evaluate.interval`` as the summary recorded it (the footnote says how the CIs were made); None: the
        former seed-aware bootstrap.
    spacecraft : Mapping, optional
        Group -> its number of distinct spacecraft (:func:`spacecraft_per_group`), for the interval footnote.

    Returns
    -------
    Table
        The table, with its interval, noise-floor and multiplicity notes.
    """
    shown = list(group_method_rows(summary, mode, groups))
    gains = [((g, m), r, "", is_primary(g, m, BASELINE, mode))
             for g, m, r in shown if np.isfinite(r.get("gain_iou", np.nan))]
    holm = family_holm(gains)
    rows = []
    for g, m, r in shown:
        cells = _gain_cells(r, "", g, (g, m), holm, is_primary(g, m, BASELINE, mode), noise_floor)
        if not np.isfinite(r.get("gain_iou", np.nan)):
            cells[2:] = ["--", "--"]
        rows.append([g, label(m), _ms(r, "iou"), _ms(r, "bf1"), *cells, str(int(r["n_seeds"]))])
    return Table("tab:spacesense-results", f"Segmentation results on the test groups ({mode_text(mode, fixed_tau)})",
                 ["Evaluation set", "Method", "Image IoU", "Boundary F1", "Image IoU gain [95% CI]",
                  "Boundary F1 gain [95% CI]", "Noise floor (IoU / BF1)", "Claim", "Seeds"], rows,
                 [f"Mean ± sample std over seeds of the per-seed means; gains against {label(BASELINE)} with 95 % CIs: "
                  f"{interval_text(interval, spacecraft, groups)}.  A single seed has no std, and its CI holds "
                  "no training noise.", noise_floor_note(noise_floor),
                  multiplicity_note(holm)])


def diagnostics_table(summary: pd.DataFrame, mode: str, groups: Sequence[str], fixed_tau: float | None = None) -> Table:
    """Tabulate precision, recall, predicted foreground fraction and small-region IoU (like tab:external-results).

    Parameters
    ----------
    summary : pandas.DataFrame
        The seed summary (``summary.parquet``): per group, method and threshold mode, the metrics' seed means and
        stds and the gains with their CIs, p-values and seed counts.
    mode : str
        The threshold mode shown: ``"calibrated"`` or ``"fixed"``.
    groups : sequence of str
        The test groups, in table order.
    fixed_tau : float, optional
        ``calibrate.fixed_tau`` as the runs recorded it, for the caption; None names the param.

    Returns
    -------
    Table
        Per group and method, each metric's mean ± std over seeds.
    """
    rows = [[g, label(m)] + [_ms(r, k) for k in ("precision", "recall", "area_ratio", "small_iou")]
            for g, m, r in group_method_rows(summary, mode, groups)]
    return Table("tab:diagnostics", f"Foreground precision, recall and diagnostics ({mode_text(mode, fixed_tau)})",
                 ["Evaluation set", "Method", "Precision", "Recall", "Foreground fraction", "Small-region IoU"], rows,
                 ["Foreground fraction: predicted foreground pixels / image pixels (pipeline.metrics; not the "
                  "predicted / reference area of the calibration table).  "
                  "Small-region IoU: IoU within small ground-truth components (see pipeline.metrics."
                  "small_region_iou); images without a small component are left out of its mean."])


def thresholds_table(thr: pd.DataFrame, fixed_tau: float | None = None) -> Table:
    """Tabulate the calibrated threshold tau of each run (eq:inference-mask) and its validation Image IoU.

    Parameters
    ----------
    thr : pandas.DataFrame
        The calibrated thresholds (``thresholds.parquet``): ``method``, ``seed``, ``tau``, ``val_iou``, and where
        recorded ``fixed_val_iou`` and ``n_val``.
    fixed_tau : float, optional
        ``calibrate.fixed_tau`` as the runs recorded it, for the caption; None names the param.

    Returns
    -------
    Table
        A row per (method, seed).
    """
    rows = [[label(r["method"]), str(int(r["seed"])), fmt(r["tau"], 2), fmt(r["val_iou"]),
             fmt(r.get("fixed_val_iou", np.nan)), str(int(r.get("n_val", 0)))]
            for _, r in thr.sort_values(["method", "seed"]).iterrows()]
    return Table("tab:thresholds", "Calibrated thresholds (validation split)",
                 ["Method", "Seed", "tau", "Val Image IoU at tau", f"Val Image IoU at {tau_text(fixed_tau)}",
                  "Val images"], rows,
                 ["tau maximises the mean validation Image IoU over the grid and is applied unchanged to every "
                  "test group.  Manual validation masks are used only for this calibration (and checkpoint "
                  "selection), never in a training loss."])


def ablation_means(metrics: pd.DataFrame, group: str, seed: int, mode: str) -> pd.DataFrame:
    """Average Image IoU / Boundary F1 per method on one group for one seed (single-seed mechanistic ablations).

    Parameters
    ----------
    metrics : pandas.DataFrame
        Per-image test metrics (``metrics.parquet``).
    group : str
        The test group.
    seed : int
        The seed.
    mode : str
        The threshold mode shown: ``"calibrated"`` or ``"fixed"``.

    Returns
    -------
    pandas.DataFrame
        Indexed by method: the mean ``iou`` and ``bf1``.
    """
    sub = metrics[(metrics["group"] == group) & (metrics["seed"] == seed) & (metrics["threshold_mode"] == mode)]
    return sub.groupby("method")[["iou", "bf1"]].mean()


def _epochs(m: str, epochs: Mapping[str, int]):
    """Write (Stage I, Stage II, total) epochs of method ``m`` from the training logs' epoch counts."""
    spec = METHODS.get(m)
    own = epochs.get(m)
    if own is None:
        return "?", "?", "?"
    if spec is None or spec.stage == 1:
        return str(own), "--", str(own)
    if spec.init == "stage1":
        s1 = epochs.get(STAGE_ONE)
        return (str(s1) if s1 is not None else "?"), str(own), (str(s1 + own) if s1 is not None else "?")
    return "--", str(own), str(own)


def _ablation_rows(order: Sequence[str], means: pd.DataFrame) -> list[str] | None:
    """Pick the rows of ``order`` present in ``means``; None when no ablation ran."""
    present = [m for m in order if m in means.index]
    return present if any(m in ABLATIONS for m in present) else None


def warm_start_table(means: pd.DataFrame, epochs: Mapping[str, int], group: str, seed: int, mode: str,
                     fixed_tau: float | None = None) -> Table | None:
    """Tabulate the warm-start ablation (paper Table ``tab:warm-start-ablation``), rows present in ``means`` only.

    Parameters
    ----------
    means : pandas.DataFrame
        Per-method means on the ablation's group and seed (:func:`ablation_means`).
    epochs : Mapping
        Method -> its epochs, from the training logs.
    group : str
        The test group the ablation ran on (the first: the paper's KCP role).
    seed : int
        The seed shown.
    mode : str
        The threshold mode shown: ``"calibrated"`` or ``"fixed"``.
    fixed_tau : float, optional
        ``calibrate.fixed_tau`` as the runs recorded it, for the caption; None names the param.

    Returns
    -------
    Table or None
        The table; None when no ablation ran.
    """
    if (present := _ablation_rows(WARM_START_ROWS, means)) is None:
        return None
    rows = [[label(m), *_epochs(m, epochs), fmt(means.loc[m, "iou"]), fmt(means.loc[m, "bf1"])] for m in present]
    return Table("tab:warm-start-ablation",
                 f"Warm-start ablation on {group}, seed {seed} ({mode_text(mode, fixed_tau)})",
                 ["Training configuration", "Stage I", "Stage II", "Total epochs", "Image IoU", "Boundary F1"], rows,
                 ["Epoch counts are read from the training logs (Stage I of a warm-started run = the plain "
                  "student's epochs)."])


def component_table(means: pd.DataFrame, group: str, seed: int, mode: str,
                    fixed_tau: float | None = None) -> Table | None:
    """Tabulate the component ablation (paper Table ``tab:component-ablation``).

    The check marks (SDF, skeleton, area terms and the gate) come from the method definitions
    (:data:`pipeline.methods.METHODS`).

    Parameters
    ----------
    means : pandas.DataFrame
        Per-method means on the ablation's group and seed (:func:`ablation_means`).
    group : str
        The test group the ablation ran on (the first: the paper's KCP role).
    seed : int
        The seed shown.
    mode : str
        The threshold mode shown: ``"calibrated"`` or ``"fixed"``.
    fixed_tau : float, optional
        ``calibrate.fixed_tau`` as the runs recorded it, for the caption; None names the param.

    Returns
    -------
    Table or None
        The table; None when no ablation ran.
    """
    if (present := _ablation_rows(COMPONENT_ROWS, means)) is None:
        return None
    rows = []
    for m in present:
        spec = METHODS.get(m)
        terms = spec.terms if spec else ()
        ticks = ["sdf" in terms, "skel" in terms, "area" in terms, spec is not None and spec.gate == "g"]
        rows.append([label(m), *("✓" if t else "" for t in ticks), fmt(means.loc[m, "iou"]), fmt(means.loc[m, "bf1"])])
    return Table("tab:component-ablation", f"Component ablation on {group}, seed {seed} ({mode_text(mode, fixed_tau)})",
                 ["Refinement configuration", "SDF", "Skel.", "Area", "Gate", "IoU", "BF1"], rows)


def teacher_prompt_table(q: pd.DataFrame, group: str, teacher_note: str) -> Table:
    """Tabulate the teacher's prompting configurations on one group (paper Table ``tab:teacher-prompt-quality``).

    Parameters
    ----------
    q : pandas.DataFrame
        :func:`pipeline.report.analysis.teacher_prompt_quality` of the group.
    group : str
        The test group, for the caption.
    teacher_note : str
        The sentence on the teacher's numbers (:func:`pipeline.report.build.teacher_note`), a footnote.

    Returns
    -------
    Table
        A row per configuration: Image IoU, Boundary F1, precision and recall (mean ± std on the mean row).
    """
    rows = [[r["config"]] + [fmt_pm(r[m], r[f"{m}_std"]) for m in QUALITY] for _, r in q.iterrows()]
    return Table("tab:teacher-prompt-quality", f"Pseudo-mask quality of teacher prompting configurations on {group}",
                 ["Teacher configuration", "Image IoU", "Boundary F1", "Precision", "Recall"], rows,
                 [teacher_note, "The single prompt is selected on the validation split by mean Image IoU; the mean row "
                  "is the mean ± sample std of the separately evaluated single prompts (not a fusion)."])


def teacher_domain_table(d: pd.DataFrame, teacher_note: str) -> Table:
    """Tabulate the voted teacher masks' quality per dataset / domain (paper Table ``tab:teacher-domain-quality``).

    Parameters
    ----------
    d : pandas.DataFrame
        :func:`pipeline.report.analysis.teacher_domain_quality`.
    teacher_note : str
        The sentence on the teacher's numbers (:func:`pipeline.report.build.teacher_note`), a footnote.

    Returns
    -------
    Table
        A row per dataset / domain / group: images, Image IoU, Boundary F1, precision and recall.
    """
    rows = [[f"{r['dataset']} / {r['domain']} ({r['group']})", str(int(r["n"]))] + [fmt(r[m]) for m in QUALITY]
            for _, r in d.iterrows()]
    return Table("tab:teacher-domain-quality", "Multi-prompt (voted) teacher pseudo-mask quality per dataset / domain",
                 ["Dataset / domain (group)", "Images", "Image IoU", "Boundary F1", "Precision", "Recall"], rows,
                 [teacher_note])


def gate_table(analyses: Sequence[dict], teacher_note: str) -> Table:
    """Tabulate the teacher's quality on images the gate suppresses or keeps (paper Table ``tab:gate-groups``).

    Parameters
    ----------
    analyses : sequence of dict
        :func:`pipeline.report.analysis.gate_analysis` per group (eq:reliability-gate).
    teacher_note : str
        The sentence on the teacher's numbers (:func:`pipeline.report.build.teacher_note`), a footnote.

    Returns
    -------
    Table
        Two rows per group (g = 0, g > 0), with each group's Spearman rho in the notes.
    """
    rows = [[a["group"], r["state"], str(int(r["images"])), fmt(r["iou"]), fmt(r["bf1"])]
            for a in analyses for _, r in a["table"].iterrows()]
    notes = [f"Spearman rho between g and the voted teacher mask's quality on {a['group']} (n = {a['n']}): "
             f"Image IoU {fmt(a['rho_iou'])} (p = {fmt_p(a['p_iou'])}), Boundary F1 {fmt(a['rho_bf1'])} "
             f"(p = {fmt_p(a['p_bf1'])})." for a in analyses]
    return Table("tab:gate-groups", "Teacher pseudo-mask quality for samples suppressed or retained by the gate",
                 ["Group", "Gating state", "Images", "Teacher Image IoU", "Teacher Boundary F1"], rows,
                 notes + [teacher_note, "Post-hoc analysis: manual masks only measure teacher quality here; "
                          "the gate never sees them."])


def efficiency_table(eff: pd.DataFrame) -> Table:
    """Tabulate the deployed student's cost (paper Table ``tab:efficiency``), with speed-up and fp32 agreement.

    Parameters
    ----------
    eff : pandas.DataFrame
        The benchmark table (``efficiency.parquet``): a row per variant.

    Returns
    -------
    Table
        A row per variant: parameters, GFLOPs, latency, throughput, peak memory, and the optional columns
        (speed-up, IoU change and agreement against fp32, resolution, device) that hold a value.
    """
    labels = {"speedup": "Speed-up vs fp32 eager", "iou_delta": "Val Image IoU change vs fp32",
              "iou_vs_fp32": "Mask IoU with fp32 (val)", "resolution": "Resolution", "device": "Device"}
    # a column with no value at all (the IoU columns without validation masks) is left out, not shown as "--"
    extra = [c for c in labels if c in eff.columns and not (eff[c].dtype.kind == "f" and eff[c].isna().all())]
    rows = []
    for _, r in eff.iterrows():
        # an untimed variant (unsupported, or pathologically slow here) shows why instead of numbers;
        # a timed one with a caveat (e.g. bf16 emulated) carries it beside its name
        timed = bool(r["timed"]) if "timed" in eff.columns else True
        remark = str(r["remark"]) if "remark" in eff.columns and isinstance(r["remark"], str) else ""
        name = str(r["variant"]) + (f" ({remark})" if timed and remark else "")
        speed = ([fmt(r["latency_ms"], 2), fmt(r["throughput"], 1), fmt(r["peak_mb"], 1)] if timed
                 else [remark or "not timed", "--", "--"])
        params = r["params"]
        n_params = (f"{params / 1e6:.3f} M" if isinstance(params, (int, float, np.number)) and np.isfinite(params)
                    else str(params))
        rows.append([name, n_params, fmt(r["gflops"], 2), *speed,
                     *(fmt(r[c]) if isinstance(r[c], (float, np.floating)) else str(r[c]) for c in extra)])
    return Table("tab:efficiency", "Computational efficiency of the deployed student",
                 ["Variant", "Parameters", "GFLOPs", "Latency (ms/image)", "Throughput (image/s)", "Peak memory (MB)"]
                 + [labels[c] for c in extra], rows,
                 ["Measured by the benchmark stage on this machine; latency (batch 1, median, timed round-robin "
                  "across the variants), throughput and memory at the Resolution column, excluding disk input; "
                  "the IoU columns on the validation images at the model's working resolution"
                  + ("." if "iou_delta" in extra else " (left out: no validation images with masks).")])


def _ordered_with_ceiling_last(methods: Sequence[str]) -> list[str]:
    """Order annotation-free methods (main order, then ablations by name), then the not-annotation-free ones."""
    present = list(dict.fromkeys(methods))
    free = main_methods(present)
    free += sorted(m for m in present if m in ABLATIONS and m not in free)
    free += [m for m in present if m not in free and m not in not_annotation_free(present)]
    order = {m: i for i, m in enumerate(METHODS)}
    return free + sorted(not_annotation_free(present), key=lambda m: order.get(m, 99))


def controls_table(summary: pd.DataFrame, mode: str, groups: Sequence[str],
                   noise_floor: dict | None = None, fixed_tau: float | None = None,
                   interval: str | None = DEFAULT_INTERVAL, spacecraft: Mapping[str, int] | None = None
                   ) -> Table | None:
    """Tabulate the budget-matched control per group: where the gain comes from.

    Continuation - Plain (the extra epochs alone), each warm-started method - Continuation (geometry at a
    matched budget) and GeoDistill-Refine - Plain, each with its CI, noise floor and claim.

    Parameters
    ----------
    summary : pandas.DataFrame
        The seed summary (``summary.parquet``): per group, method and threshold mode, the metrics' seed means and
        stds and the gains with their CIs, p-values and seed counts.
    mode : str
        The threshold mode shown: ``"calibrated"`` or ``"fixed"``.
    groups : sequence of str
        The test groups, in table order.
    noise_floor : dict, optional
        The noise-floor record of this configuration (:func:`pipeline.report.analysis.select_noise_floor`); None:
        not measured, the claims rest on the CIs and the multiplicity rule alone.
    fixed_tau : float, optional
        ``calibrate.fixed_tau`` as the runs recorded it, for the caption; None names the param.
    interval : str or None
        ``evaluate.interval`` as the summary recorded it (the footnote says how the CIs were made); None: the
        former seed-aware bootstrap.
    spacecraft : Mapping, optional
        Group -> its number of distinct spacecraft (:func:`spacecraft_per_group`), for the interval footnote.

    Returns
    -------
    Table or None
        The table; None without a continuation run (or its gains) in ``summary``.
    """
    s = summary[summary["threshold_mode"] == mode]
    if CONTINUATION not in set(s["method"]) or f"gain_iou{VS_CONTINUATION}" not in s.columns:
        return None
    shown = []  # (group, comparison in words, summary row, suffix, is_primary)
    for g in groups:
        part = s[s["group"] == g].set_index("method")
        warm = [PROPOSED] + sorted(m for m in part.index if m != PROPOSED)
        for what, m, suffix, control in (
                [(f"{label(CONTINUATION)} − {label(BASELINE)} (extra epochs only)", CONTINUATION, "", BASELINE)]
                + [(f"{label(m)} − {label(CONTINUATION)} (geometry at a matched budget)", m, VS_CONTINUATION,
                    CONTINUATION) for m in warm]
                + [(f"{label(PROPOSED)} − {label(BASELINE)} (the paper's comparison)", PROPOSED, "", BASELINE)]):
            if m in part.index and np.isfinite(part.loc[m].get(f"gain_iou{suffix}", np.nan)):
                shown.append((g, what, part.loc[m], suffix, is_primary(g, m, control, mode)))
    holm = family_holm([((g, what), r, suffix, p) for g, what, r, suffix, p in shown])
    rows = [[g, what, *_gain_cells(r, suffix, g, (g, what), holm, p, noise_floor), str(int(r[f"gain_seeds{suffix}"]))]
            for g, what, r, suffix, p in shown]
    return Table("tab:controls", f"Budget-matched control: where the gain comes from ({mode_text(mode, fixed_tau)})",
                 ["Evaluation set", "Comparison", "Image IoU difference [95% CI]", "Boundary F1 difference [95% CI]",
                  "Noise floor (IoU / BF1)", "Claim", "Seeds"], rows,
                 ["The continuation warm-starts from the same Stage-I checkpoint and trains with Stage II's schedule, "
                  "epochs and checkpoint selection on L_raw only: a method minus the continuation isolates its "
                  "geometry terms; the continuation minus Plain isolates the extra epochs.  95 % CIs over the seeds "
                  f"both runs share: {interval_text(interval, spacecraft, groups)}.",
                  noise_floor_note(noise_floor), multiplicity_note(holm)])


def reference_points_table(summary: pd.DataFrame, vote: pd.DataFrame | None, mode: str,
                           groups: Sequence[str], fixed_tau: float | None = None) -> Table | None:
    """Tabulate the reference points beside the students, never compared with CIs.

    The teacher vote scored as a predictor and the supervised ceiling, with Plain Student and GeoDistill-Refine
    for context; each student's distillation efficiency (IoU ÷ vote) and label cost (÷ ceiling).

    Parameters
    ----------
    summary : pandas.DataFrame
        The seed summary (``summary.parquet``): per group, method and threshold mode, the metrics' seed means and
        stds and the gains with their CIs, p-values and seed counts.
    vote : pandas.DataFrame or None
        The teacher vote's means per group (:func:`pipeline.report.analysis.teacher_vote_means`).
    mode : str
        The threshold mode shown: ``"calibrated"`` or ``"fixed"``.
    groups : sequence of str
        The test groups, in table order.
    fixed_tau : float, optional
        ``calibrate.fixed_tau`` as the runs recorded it, for the caption; None names the param.

    Returns
    -------
    Table or None
        The table; None with neither a not-annotation-free run nor a vote.
    """
    s = summary[summary["threshold_mode"] == mode]
    ceiling = not_annotation_free(s["method"].unique())
    if not ceiling and (vote is None or vote.empty):
        return None
    rows, verdicts = [], []
    for g in groups:
        part = s[s["group"] == g].set_index("method")
        vote_iou = float(vote.loc[g, "iou"]) if vote is not None and g in vote.index else float("nan")
        top = part.loc[ceiling[0]] if ceiling and ceiling[0] in part.index else None
        for m in [BASELINE, PROPOSED, *ceiling]:
            if m in part.index:
                r = part.loc[m]
                e, lo, hi = distillation_efficiency(r["iou_mean"], r["iou_std"], r["n_seeds"], vote_iou)
                cost = ("--" if top is None or m in ceiling else efficiency_text(*seed_ratio(
                    r["iou_mean"], r["iou_std"], r["n_seeds"], top["iou_mean"], top["iou_std"], top["n_seeds"])))
                rows.append([g, label(m), *(_ms(r, k) for k in QUALITY), str(int(r["n_seeds"])),
                             efficiency_text(e, lo, hi), cost])
                verdicts.append((m, efficiency_target_met(m, e, lo)))
        if vote is not None and g in vote.index:
            v = vote.loc[g]
            rows.append([g, TEACHER_VOTE_LABEL, *(fmt(v[k]) for k in QUALITY), "--", "1", "--"])
    return Table("tab:reference-points", f"Reference points: the teacher vote and the supervised ceiling "
                 f"({mode_text(mode, fixed_tau)} for the students)",
                 ["Evaluation set", "Predictor", "Image IoU", "Boundary F1", "Precision", "Recall", "Seeds",
                  "IoU ÷ vote", "Label cost"], rows,
                 [n for n in ["The supervised ceiling is the Plain Student's recipe trained on the training split's "
                  "REFERENCE masks: it is not annotation-free and is never part of a gain or its confidence "
                  "interval.  The teacher vote is the pseudo-label every annotation-free student learns from, scored "
                  "at its own binary mask (no threshold), identical in both threshold modes.",
                  "IoU ÷ vote is the distillation efficiency: the seed-mean Image IoU divided by the teacher vote's "
                  "on the same test images, with a 95 % per-seed ratio t interval (the vote has no seed; the "
                  "interval covers training noise, not the sampling of the images).",
                  "The split of the gap to the vote: label cost = Plain ÷ ceiling (the Label cost column; what "
                  "training on pseudo-labels instead of reference masks costs), generalization = ceiling ÷ vote (the "
                  "ceiling's IoU ÷ vote: what the student's capacity and data leave).  The ceiling ratio's interval "
                  "adds both runs' seed noise (delta method); both are meaningful only with each run at its plateau.",
                  efficiency_targets_note(verdicts)] if n])


def efficiency_targets_note(verdicts: Sequence[tuple[str, bool | None]]) -> str:
    """Name the distillation-efficiency targets and on how many groups each is met (``verdicts``: (method, met))."""
    parts = []
    for m, (target, on_interval) in EFFICIENCY_TARGETS.items():
        judged = [v for mm, v in verdicts if mm == m and v is not None]
        if not any(mm == m for mm, _ in verdicts):
            continue
        what = f"{label(m)} {'interval above' if on_interval else '≥'} {target:.2f} × the vote"
        parts.append(f"{what}: met on {sum(judged)} of {len(judged)} groups" if judged else f"{what}: not judged")
    return ("Targets (printed, not asserted): " + "; ".join(parts) + ".") if parts else ""


def efficiency_text(e: float, lo: float, hi: float) -> str:
    """Format a (ratio, low, high) as ``0.84 [0.80, 0.88]``; ``--`` without a vote."""
    return fmt(e, 2) + (f" [{lo:.2f}, {hi:.2f}]" if _finite(e) and _finite(lo) else "")


def calibration_table(thr: pd.DataFrame, fixed_tau: float | None = None) -> Table:
    """Tabulate, per method, the validation-split calibration diagnostics (mean ± std over seeds).

    Parameters
    ----------
    thr : pandas.DataFrame
        The calibrated thresholds (``thresholds.parquet``): ``tau``, ``val_iou`` and where recorded
        ``fixed_val_iou``, ``ece``, ``area_ratio``, ``fixed_area_ratio`` per method and seed.
    fixed_tau : float, optional
        ``calibrate.fixed_tau`` as the runs recorded it, for the caption; None names the param.

    Returns
    -------
    Table
        A row per method, annotation-free ones first.
    """
    rows = []
    for m in _ordered_with_ceiling_last(thr["method"].unique()):
        part = thr[thr["method"] == m]

        def ms(col, digits=4, part=part):  # a single seed's std is NaN: no "±"
            v = part[col].astype(float) if col in part.columns else None
            return "--" if v is None else fmt_pm(v.mean(), v.std(), digits)

        rows.append([label(m), ms("tau", 2), ms("val_iou"), ms("fixed_val_iou"), ms("ece"), ms("area_ratio", 2),
                     ms("fixed_area_ratio", 2), str(len(part))])
    return Table("tab:calibration", "Calibration diagnostics on the validation split",
                 ["Method", "Calibrated tau", "Val IoU at tau", f"Val IoU at {tau_text(fixed_tau)}", "ECE (pixels)",
                  "Pred./ref. area at tau", f"Pred./ref. area at {tau_text(fixed_tau)}", "Seeds"], rows,
                 ["ECE: expected calibration error of the pixel probabilities over equal-width bins "
                  "(pipeline.evaluation.diagnostics).  Pred./ref. area: median over validation images of predicted / "
                  "reference foreground area (1 = no inflation).  Mean ± sample std over seeds."])


def epoch_swing_table(swings: pd.DataFrame, fixed_tau: float | None = None) -> Table:
    """Tabulate the changes of validation Image IoU between adjacent epochs, per method and stage.

    Parameters
    ----------
    swings : pandas.DataFrame
        :func:`pipeline.report.analysis.epoch_swings`.
    fixed_tau : float, optional
        ``calibrate.fixed_tau`` as the runs recorded it, for the caption; None names the param.

    Returns
    -------
    Table
        A row per method and stage.
    """
    rows = [[label(m), str(int(r["stage"])), f"{fmt(r['max_swing'], 3)} (seed {int(r['max_seed'])}, "
             f"epochs {int(r['max_epoch']) - 1}->{int(r['max_epoch'])})", fmt(r["median_swing"], 3),
             fmt(r["max_swing_cal"], 3), fmt(r["median_swing_cal"], 3),
             f"{fmt(r['tau_min'], 2)}–{fmt(r['tau_max'], 2)}"]
            for m in _ordered_with_ceiling_last(swings["method"].unique())
            for _, r in swings[swings["method"] == m].iterrows()]
    return Table("tab:epoch-swings", "Validation Image IoU between adjacent epochs (training logs)",
                 ["Method", "Stage", f"Largest change at tau {tau_text(fixed_tau)}",
                  f"Median change at {tau_text(fixed_tau)}",
                  "Largest change at calibrated tau", "Median change at calibrated tau", "Calibrated tau range"], rows,
                 ["Absolute change of the mean validation Image IoU from one epoch to the next, over all seeds; "
                  "'calibrated tau' is the tau maximising that epoch's validation IoU (a diagnostic: checkpoint "
                  f"selection uses tau {tau_text(fixed_tau)})."])


def size_split_table(split: pd.DataFrame, mode: str, max_fraction: float | None,
                     fixed_tau: float | None = None) -> Table:
    """Tabulate the metrics split by target size, pooled over the test groups.

    Parameters
    ----------
    split : pandas.DataFrame
        :func:`pipeline.report.analysis.size_split` (with ``n_images``).
    mode : str
        The threshold mode shown: ``"calibrated"`` or ``"fixed"``.
    max_fraction : float or None
        ``evaluate.tiny_target_max_fraction`` as used (the tiny/regular boundary); None names the param.
    fixed_tau : float, optional
        ``calibrate.fixed_tau`` as the runs recorded it, for the caption; None names the param.

    Returns
    -------
    Table
        A row per method and size class (tiny, regular, empty).
    """
    s = split[split["threshold_mode"] == mode]
    rows = []
    for m in _ordered_with_ceiling_last(s["method"].unique()):
        part = s[s["method"] == m].set_index("target_size")
        for size in ("tiny", "regular", "empty"):
            if size in part.index:
                r = part.loc[size]
                rows.append([label(m), size, str(int(r["n_images"])), _ms(r, "iou"), _ms(r, "bf1"),
                             _ms(r, "area_vs_reference", 2)])
    lim = f"{100 * max_fraction:g} %" if max_fraction is not None else "evaluate.tiny_target_max_fraction"
    return Table("tab:size-split", f"Metrics split by target size, all test groups ({mode_text(mode, fixed_tau)})",
                 ["Method", "Target size", "Images per seed", "Image IoU", "Boundary F1", "Mean area vs reference"],
                 rows, [f"tiny: reference foreground under {lim} of the frame; regular: the rest; empty: no "
                        f"reference foreground.  Mean ± sample std over seeds of the per-seed means."])
