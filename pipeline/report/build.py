"""Gather the evaluation artifacts into one :class:`Report` and the plot tables DVC shows.

A missing input never fails the report: its section names the stage that produces it.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import yaml

from pipeline import catalog
from pipeline.artifacts.lineage import require_same_run
from pipeline.artifacts.store import open_artifact, read_chunk_rows
from pipeline.runtime.errors import ArtifactError
from pipeline.evaluation.inference import CORRECTED_VALIDATION, load_student, predict_probs
from pipeline.methods import BASELINE, METHODS, PROPOSED, STAGE_ONE, departures
from pipeline.metrics import image_iou
from pipeline.report import figures as F
from pipeline.report import tables as T
from pipeline.report.analysis import (epoch_swings, fixed_tau_findings, gate_analysis, select_noise_floor, size_split,
                                      tau_text, teacher_domain_quality, teacher_prompt_quality, teacher_vote_means)
from pipeline.report.document import Figure, Missing, Report, Section, Table, Text
from pipeline.report.environment import ending_table, environment_section, opened_runs, training_runs
from pipeline.report.glossary import glossary_section
from pipeline.teacher_table import find_teacher, is_simulator
from pipeline.thresholds import mask_from_probs

__all__ = ["MASK_INPUTS", "vote_means", "build_report"]

#: the figures' file names (pipeline.catalog.OUTPUT_FILES)
FIGURES = catalog.output_names("report_figures")
#: the catalogue artifacts the report reads
INPUTS = ("manifest", "images", "reference", "teacher", "consensus", "geometry", "gates", "thresholds", "metrics",
          "summary", "teacher_metrics", "efficiency")
MODES = ("calibrated", "fixed")
#: the training-curve figures' x axis (:func:`on_one_epoch_axis`)
EPOCH_AXIS = "epoch (Stage II after its Stage-I run's last epoch)"
#: the column :func:`on_one_epoch_axis` adds
AXIS_EPOCH = "axis_epoch"


@dataclasses.dataclass
class Inputs:
    """What the report read: the opened inputs, a note per missing one, and what the runs recorded.

    Attributes
    ----------
    art : Path
        The artifacts folder.
    found : dict
        Catalogue name (:data:`INPUTS`) -> its opened artifact.
    missing : dict
        Catalogue name -> the :class:`Missing` note naming the stage that produces it.
    logs : pandas.DataFrame or None
        The training logs of every active run (:func:`training_logs`).
    runs : list
        The training runs (:func:`pipeline.report.environment.training_runs`).
    no_masks : bool
        No validation or test image has a mask (a distill project without ``--val-masks``).
    noise_floor : dict or None
        The noise-floor record measured in this configuration (:func:`noise_floor_for_runs`).
    fixed_tau : float or None
        ``calibrate.fixed_tau`` as the runs recorded it (:func:`recorded_fixed_tau`).
    run_review : dict
        The runs trained on human corrections (:func:`recorded_review`).
    departures : dict
        Each method's departures from eq:raw-loss (:func:`recorded_departures`).
    corrected_validation : int
        The corrected training images calibrate used as validation images.
    """

    art: Path
    found: dict[str, Any]
    missing: dict[str, Missing]
    logs: pd.DataFrame | None = None
    runs: list = dataclasses.field(default_factory=list)
    no_masks: bool = False
    noise_floor: dict | None = None
    fixed_tau: float | None = None
    run_review: dict = dataclasses.field(default_factory=dict)
    departures: dict = dataclasses.field(default_factory=dict)
    corrected_validation: int = 0

    def get(self, name):
        """Return the opened input ``name``, or None when it is missing."""
        return self.found.get(name)

    def need(self, *names) -> list:
        """List a note per missing input of ``names``; without any mask, one :data:`NOT_COMPUTED` sentence instead."""
        if self.no_masks and any(n in MASK_INPUTS for n in names):
            return [Text(NOT_COMPUTED)]
        return [self.missing[n] for n in names if n in self.missing]


def load_inputs(art: str | Path, profile: str | None = None) -> Inputs:
    """Open every input that exists and a :class:`Missing` note for each other; ``profile``: the runs' profile."""
    art = Path(art)
    found, missing = {}, {}
    for name in INPUTS:
        spec = catalog.ARTIFACTS[name]
        try:
            found[name] = open_artifact(catalog.path(name, art), name)
        except ArtifactError as e:
            missing[name] = Missing(f"`{spec.path}`", f"{e} -- produced by the `{spec.stage}` stage.")
    require_same_run(*found.values())
    checkpoints, manifest, thr = catalog.path("checkpoints", art), found.get("manifest"), found.get("thresholds")
    runs, images = training_runs(checkpoints), found.get("images")
    thr_extra = (thr.meta.extra or {}) if thr is not None else {}
    return Inputs(art, found, missing, logs=training_logs(checkpoints), runs=runs,
                  no_masks=manifest is not None and no_reference_masks(manifest.df, found.get("reference")),
                  noise_floor=noise_floor_for_runs(catalog.path("noise_floor", art), runs, images, profile),
                  fixed_tau=recorded_fixed_tau(thr, found.get("metrics")), run_review=recorded_review(checkpoints),
                  departures=recorded_departures(checkpoints),
                  corrected_validation=int(thr_extra.get(CORRECTED_VALIDATION, 0)))


def recorded_review(checkpoints: Path) -> dict[str, dict]:
    """Map each method whose checkpoint records human corrections in the loss to ``{"corrections", "mode"}``."""
    extras = [(method, ckpt.meta.extra or {}) for method, _, ckpt in opened_runs(checkpoints)]
    return {method: {"corrections": int(e.get("human_corrections", 0)), "mode": e["corrections_mode"]}
            for method, e in extras if e.get("annotation_free") is False and e.get("corrections_mode")}


def recorded_departures(checkpoints: Path) -> dict[str, list[str]]:
    """Map each method to the departures from eq:raw-loss its runs recorded (:func:`pipeline.methods.departures`)."""
    out: dict[str, list[str]] = {}
    for method, _, ckpt in opened_runs(checkpoints):
        # unvalidated: the params a run recorded (an older run records fewer keys)
        names = departures((ckpt.meta.params or {}).get("params") or {})
        if names:
            out[method] = list(dict.fromkeys([*out.get(method, []), *names]))
    return out


def corrections_note(inp: Inputs) -> str | None:
    """Write a sentence on the human corrections and loss departures this run used; None without."""
    parts = []
    if inp.corrected_validation:
        parts.append(f"**{inp.corrected_validation} training images a person corrected are validation images** "
                     f"(`review.mode: validate`): their corrected masks select checkpoints and calibrate tau, and "
                     f"they left the training set, so the students stay annotation-free.")
    if inp.departures:
        names = ", ".join(T.label(m) for m in inp.departures)
        parts.append(f"**Departures from eq:raw-loss (issue 57's label-noise levers), named in every table:** "
                     f"{names}.")
    if inp.run_review:
        names = ", ".join(T.label(m) for m in inp.run_review)
        parts.append(f"**Trained on human corrections (`review.mode: replace`), NOT annotation-free:** {names}. "
                     f"Corrected masks replaced those images' voted masks in the loss; every table labels these runs.")
    return " ".join(parts) or None


def noise_floor_for_runs(path: Path, runs: list, images, profile: str | None = None) -> dict | None:
    """Select the noise-floor record at ``path`` measured with the runs' recipe, resolution and ``profile``."""
    doc = json.loads(path.read_text()) if path.is_file() else None
    recipes = {r["recipe"] for r in runs if r.get("recipe")}
    resolution = int(images["image"].shape[1]) if images is not None and "image" in images else None
    return select_noise_floor(doc, recipes.pop() if len(recipes) == 1 else None, resolution, profile)


def gain_interval(summary) -> str | None:
    """Read ``evaluate.interval`` as ``summary`` recorded it (None: recorded before it was)."""
    return ((summary.meta.extra or {}).get("interval")) if summary is not None else None


def recorded_fixed_tau(thresholds, metrics) -> float | None:
    """Read ``calibrate.fixed_tau`` as recorded in thresholds, else in the fixed-mode metrics; None unless one."""
    for art, column, rows in ((thresholds, "fixed_tau", None), (metrics, "tau", "fixed")):
        if art is None or column not in art.df.columns:
            continue
        df = art.df if rows is None else art.df[art.df["threshold_mode"] == rows]
        values = set(df[column].astype(float))
        if len(values) == 1:
            return values.pop()
    return None


def training_logs(checkpoints: Path) -> pd.DataFrame | None:
    """Stack all active runs' training logs, with method and seed columns (None when none)."""
    frames = []
    for method, seed, ckpt in opened_runs(checkpoints):
        try:
            log = ckpt.table(catalog.TRAINING_LOG_FILE).copy()
        except ArtifactError:
            continue
        log["method"], log["seed"] = method, seed
        frames.append(log)
    return pd.concat(frames, ignore_index=True) if frames else None


def teacher_note(backend: str) -> str:
    """Write the report's sentence on the teacher's numbers (``backend``'s row of the teacher table).

    The row is :data:`pipeline.teacher_table.TEACHER_TABLE` ``[backend]``, plug-ins included; an unknown backend is
    named as is.
    """
    spec = find_teacher(backend)
    return spec.note if spec is not None and spec.note else f"Teacher backend: `{backend}`."


NO_MASKS_NOTE = (
    "**No validation or test masks were available** (e.g. `geodistill distill` without `--val-masks`): every "
    "image is a training image, Stage I and Stage II keep their last epoch, the threshold is the fixed "
    "tau = `calibrate.fixed_tau` ({tau}, not calibrated), and there are no accuracy numbers -- the student's "
    "quality on this data is unmeasured.  Pass a few masks (`--val-masks DIR`) to select, calibrate and score.")
#: inputs computed only from validation/test masks
MASK_INPUTS = ("summary", "metrics", "teacher_metrics")
NOT_COMPUTED = ("**Not computed: no validation or test masks.** Scores need reference masks, and none were "
                "given (`geodistill distill` without `--val-masks`), so nothing here was measured.  Rerun with "
                "`--val-masks DIR` (a few masks named like their images) to compute it.")
FIXED_TAU_NOTE = ("**Threshold: the fixed tau = {tau:g}** (`calibrate.fixed_tau`), not calibrated: without "
                  "validation masks there is nothing to calibrate on.  Pass `--val-masks DIR` to calibrate it.")


def no_reference_masks(manifest_df: pd.DataFrame, reference) -> bool:
    """Tell whether no validation or test image has a reference mask (False without a reference artifact)."""
    if reference is None:
        return False
    held_out = manifest_df["split"].isin(["val", "test"]).to_numpy()
    return not (held_out & reference.numpy("has_mask").astype(bool)).any()


def test_groups(manifest_df: pd.DataFrame) -> list[str]:
    """List the test groups in manifest order (the first has the paper's KCP role: ablations, qualitative)."""
    return list(dict.fromkeys(manifest_df.loc[manifest_df["split"] == "test", "group"]))


def _modes(df: pd.DataFrame) -> list[str]:
    """List the threshold modes of :data:`MODES` that ``df`` has rows of."""
    return [mode for mode in MODES if (df["threshold_mode"] == mode).any()]


def _figure(key: str, title: str, caption: str, chart, name: str) -> Figure:
    """Make a report figure of ``chart`` (PNG and SVG) saved as :data:`FIGURES` ``[name]``."""
    return Figure(key, title, caption, F.png_bytes(chart), FIGURES[name], F.svg_bytes(chart))


def _mean_curves(df: pd.DataFrame, x: str, y: str, marker=None) -> list[dict]:
    """One line-plot series per method: ``y`` averaged over the seeds at each ``x`` (``marker(method)``: a dot)."""
    series = []
    for method, part in df.groupby("method", sort=False):
        mean = part.groupby(x)[y].mean()
        series.append({"x": mean.index.to_numpy(float), "y": mean.to_numpy(float), "label": T.label(method),
                       **({"marker": float(marker(method))} if marker else {}), **F.method_style(method)})
    return series


def on_one_epoch_axis(logs: pd.DataFrame) -> pd.DataFrame:
    """Add column :data:`AXIS_EPOCH` to ``logs``: where each run's epochs sit on the training-curve figures' one axis.

    A run that starts from scratch keeps its own epochs.  A warm-started run (a method with ``init: stage1``) sits
    after the last epoch of the Stage-I run it started from (:data:`pipeline.methods.STAGE_ONE` at its seed), so its
    epoch 0 -- the Stage-I model -- falls on that run's last epoch; each seed's own, since a plateau rule stops each
    Stage-I run at its own epoch.  Where that Stage-I log is absent, the run keeps its own epochs.

    Parameters
    ----------
    logs : pandas.DataFrame
        Stacked training logs with ``method``, ``seed`` and ``epoch`` columns (:func:`training_logs`).

    Returns
    -------
    pandas.DataFrame
        A copy of ``logs`` with :data:`AXIS_EPOCH` added.
    """
    out = logs.copy()
    last = out[out["method"] == STAGE_ONE].groupby("seed")["epoch"].max()
    warm = out["method"].map(lambda m: m in METHODS and METHODS[m].init == "stage1").astype(bool)
    offset = out["seed"].map(last).where(warm, 0).fillna(0)
    out[AXIS_EPOCH] = out["epoch"] + offset.astype(out["epoch"].dtype)
    return out


def _epoch_curves(logs: pd.DataFrame, y: str) -> list[dict]:
    """:func:`_mean_curves` of ``y`` on the figures' one epoch axis (:func:`on_one_epoch_axis`)."""
    return _mean_curves(on_one_epoch_axis(logs), AXIS_EPOCH, y)


def _spread(n_total: int, n: int) -> np.ndarray:
    """``min(n, n_total)`` positions evenly spaced over ``range(n_total)``."""
    return np.unique(np.linspace(0, n_total - 1, min(n, n_total)).round().astype(int))


def _student_masks(inp: Inputs, methods, seed: int, images: np.ndarray, tau, device) -> dict:
    """Predict each method's student masks of ``images`` (its ``seed``) at ``tau(method)`` (eq:inference-mask)."""
    students = {m: load_student(inp.art / "checkpoints" / m / str(seed), device)[0] for m in methods}
    return {m: mask_from_probs(predict_probs(model, images, device=device), tau(m)) for m, model in students.items()}


def _section(title: str, needs: tuple[str, ...] = ()):
    """Make a function that returns a section's blocks return the :class:`Section` ``title`` of them.

    Without an input of ``needs``, the section holds :meth:`Inputs.need`'s notes instead.
    """
    def decorate(blocks):
        @functools.wraps(blocks)
        def section(inp: Inputs, *args, **kwargs) -> Section:
            return Section(title, inp.need(*needs) or blocks(inp, *args, **kwargs))
        return section
    return decorate


@_section("Data, teacher and protocol", needs=("manifest",))
def data_section(inp: Inputs) -> list:
    df = inp.get("manifest").df
    datasets = sorted(df["dataset"].unique())
    backend = str(inp.get("teacher").attrs.get("backend", "unknown")) if inp.get("teacher") else "unknown"
    if "synthetic" in datasets:
        blocks = [Text(
            "**Dataset: the embedded SYNTHETIC spacecraft benchmark** (rendered spacecraft with a spacecraft-disjoint "
            "split shaped like SpaceSense-Bench), not SpaceSense-Bench, SPEED+ or TANGO. Its teacher is a "
            "**SIMULATOR** of prompt-dependent foundation-model errors, not SAM 3. The numbers below test the "
            "pipeline's behaviour on this benchmark; they are not comparable to the paper's.")]
    else:
        blocks = [Text(f"Dataset(s): {', '.join(f'`{d}`' for d in datasets)}.")]
    blocks += [Text(teacher_note(backend)), Text(
        "Manual (reference) masks are used only for validation-time checkpoint selection, threshold calibration "
        "and evaluation (and, on the synthetic benchmark, inside the teacher simulator); they never enter a "
        "student's training loss.")]
    if no_reference_masks(df, inp.get("reference")) and not inp.corrected_validation:
        blocks.append(Text(NO_MASKS_NOTE.format(tau=tau_text(inp.fixed_tau))))
    if (note := corrections_note(inp)) is not None:
        blocks.append(Text(note))
    spacecraft = T.spacecraft_per_group(df)  # the interval footnotes state the same counts
    rows = [[str(ds), str(split), str(group), str(len(part)), str(spacecraft[str(group)])]
            for (ds, split, group), part in df.groupby(["dataset", "split", "group"], sort=False)]
    return blocks + [Table("tab:data", "Images per split and group",
                           ["Dataset", "Split", "Group", "Images", "Spacecraft"], rows)]


@_section("Threshold calibration", needs=("thresholds",))
def threshold_section(inp: Inputs, plots: dict) -> list:
    df = inp.get("thresholds").df
    if inp.no_masks and not inp.corrected_validation:
        taus = sorted({float(t) for t in df["tau"]})
        return [Text(FIXED_TAU_NOTE.format(tau=taus[0] if len(taus) == 1 else float("nan")))]
    blocks = [T.thresholds_table(df, inp.fixed_tau)]
    if "grid" in df.columns and len(df):
        curves = pd.concat([pd.DataFrame({"tau": r["grid"], "val_iou": r["curve"], "method": r["method"],
                                          "seed": r["seed"]}) for _, r in df.iterrows()], ignore_index=True)
        plots["threshold_curve"] = curves
        series = _mean_curves(curves, "tau", "val_iou", lambda m: df.loc[df["method"] == m, "tau"].mean())
        img = F.line_plot(series, "Validation Image IoU vs threshold", "tau", "mean val Image IoU")
        blocks.append(_figure("fig:threshold-curves", "Threshold curves", "Mean validation Image IoU of [P >= "
                              "tau] over the calibration grid (mean over seeds per method; dot: mean calibrated "
                              "tau).", img, "threshold_curves"))
    return blocks


@_section("Student results on the test groups")
def results_section(inp: Inputs) -> list:
    s = inp.get("summary")
    if s is None:
        return inp.need("summary")
    groups, modes, vote = ordered_groups(inp, s.df["group"]), _modes(s.df), vote_means(inp)
    return ([T.results_table(s.df, mode, groups, inp.noise_floor, inp.fixed_tau, gain_interval(s),
                             spacecraft_counts(inp)) for mode in modes]
            + [T.diagnostics_table(s.df, mode, groups, inp.fixed_tau) for mode in modes]
            + [t for mode in modes if (t := T.reference_points_table(s.df, vote, mode, groups, inp.fixed_tau))])


def spacecraft_counts(inp: Inputs) -> dict[str, int] | None:
    m = inp.get("manifest")
    return T.spacecraft_per_group(m.df) if m is not None else None


def vote_means(inp: Inputs) -> pd.DataFrame | None:
    """Score the teacher vote as a predictor per test group (``teacher_metrics.parquet``).

    Parameters
    ----------
    inp : Inputs
        The report's inputs (:func:`build_report` returns them).

    Returns
    -------
    pandas.DataFrame or None
        :func:`pipeline.report.analysis.teacher_vote_means` of the teacher metrics; None when they are missing.
    """
    tm = inp.get("teacher_metrics")
    return teacher_vote_means(tm.df) if tm is not None else None


def ordered_groups(inp: Inputs, present) -> list[str]:
    """``present`` groups in the manifest's test-group order (unknown ones last)."""
    present = list(dict.fromkeys(present))
    order = test_groups(inp.get("manifest").df) if inp.get("manifest") is not None else []
    return [g for g in order if g in present] + [g for g in present if g not in order]


@_section("Controls and threshold diagnostics")
def diagnostics_section(inp: Inputs, plots: dict) -> list:
    """Report the controls and threshold/calibration diagnostics.

    They cover the fixed-tau reversal, the budget-matched control, calibration, per-epoch stability and target size.
    """
    if inp.no_masks:
        return [Text(NOT_COMPUTED)]
    s, thr, m = inp.get("summary"), inp.get("thresholds"), inp.get("metrics")
    if s is None and thr is None:
        return inp.need("summary", "thresholds")
    groups = ordered_groups(inp, s.df["group"] if s is not None else [])
    frames = [a.df if a is not None else None for a in (s, thr, m)]
    blocks = [Text(f) for f in fixed_tau_findings(*frames, inp.logs, vote_means(inp), groups, label=T.label,
                                                  noise_floor=inp.noise_floor, fixed_tau=inp.fixed_tau)]
    if s is not None:
        blocks += [t for mode in MODES if (t := T.controls_table(s.df, mode, groups, inp.noise_floor, inp.fixed_tau,
                                                                 gain_interval(s), spacecraft_counts(inp)))]
    if thr is not None and "ece" in thr.df.columns:
        blocks += calibration_blocks(thr.df, plots, inp.fixed_tau)
    if inp.logs is not None and "val_iou_cal" in inp.logs.columns and inp.logs["val_iou"].notna().any():
        blocks += [T.epoch_swing_table(epoch_swings(inp.logs), inp.fixed_tau),
                   epoch_calibrated_figure(inp.logs, inp.fixed_tau)]
    if m is not None and "target_size" in m.df.columns:
        split = size_split(m.df)
        frac = (m.meta.params or {}).get("evaluate.tiny_target_max_fraction")
        blocks += [T.size_split_table(split, mode, frac, inp.fixed_tau) for mode in _modes(split)]
    return blocks


def _seed_mean(part: pd.DataFrame, column: str) -> np.ndarray:
    """Average a list column element-wise over the rows (seeds), NaN-aware."""
    return np.nanmean(np.stack([np.asarray(v, float) for v in part[column]]), axis=0)


def calibration_blocks(thr: pd.DataFrame, plots: dict, fixed_tau: float | None = None) -> list:
    """Build the calibration table, the reliability diagram and the area-vs-tau figure (seed means per method)."""
    blocks = [T.calibration_table(thr, fixed_tau)]
    rel, area, long = [], [], []
    for method, part in thr.groupby("method", sort=False):
        with warnings.catch_warnings():  # a bin empty in every seed stays NaN (not drawn)
            warnings.simplefilter("ignore", RuntimeWarning)
            conf, freq = _seed_mean(part, "rel_confidence"), _seed_mean(part, "rel_frequency")
        rel.append({"x": conf, "y": freq, "label": f"{T.label(method)} (ECE {part['ece'].mean():.3f})",
                    **F.method_style(method)})
        area.append({"x": np.asarray(part["grid"].iloc[0], float), "y": _seed_mean(part, "area_curve"),
                     "label": T.label(method),
                     "marker": float(part["tau"].mean()), **F.method_style(method)})
        long += [pd.DataFrame({"tau": r["grid"], "area_ratio": r["area_curve"], "method": method, "seed": r["seed"]})
                 for _, r in part.iterrows()]
    plots["area_curve"] = pd.concat(long, ignore_index=True)
    rel.append({"x": [0.0, 1.0], "y": [0.0, 1.0], "label": "perfect calibration", "color": F.REFERENCE_LINE,
                "style": "dashed"})
    grid = np.asarray(thr["grid"].iloc[0], float)
    area.append({"x": grid, "y": np.ones_like(grid), "label": "no inflation (ratio 1)", "color": F.REFERENCE_LINE,
                 "style": "dashed"})
    return blocks + [
        _figure("fig:reliability", "Reliability diagram (validation pixels)",
                "Fraction of reference-foreground pixels against the mean predicted probability in each equal-width "
                "probability bin (mean over seeds per method); below the diagonal = over-confident foreground.",
                F.line_plot(rel, "Reliability diagram", "mean predicted probability", "foreground frequency",
                            ylim=(0.0, 1.0)), "reliability"),
        _figure("fig:area-vs-tau", "Predicted against reference foreground area across tau",
                "Median over validation images of predicted / reference foreground area of [P >= tau] "
                "(mean over seeds per method; dot: mean calibrated tau; dashed grey: no inflation).",
                F.line_plot(area, "Predicted / reference area vs threshold", "tau",
                            "median predicted / reference area"), "area_vs_tau")]


def epoch_calibrated_figure(logs: pd.DataFrame, fixed_tau: float | None = None) -> Figure:
    """Per-epoch validation Image IoU at each epoch's calibrated tau (mean over seeds per method)."""
    img = F.line_plot(_epoch_curves(logs, "val_iou_cal"), "Validation Image IoU at the per-epoch "
                      "calibrated tau", EPOCH_AXIS, "val Image IoU at calibrated tau")
    return _figure("fig:training-curves-calibrated", "Training curves at the calibrated tau",
                   "Validation Image IoU per epoch at the tau maximising it at that epoch (mean over seeds per "
                   "method; a warm-started Stage-II run is drawn after its Stage-I run's last epoch, at its seed); "
                   f"compare with the tau = {tau_text(fixed_tau)} curves in the training-curves section.",
                   img, "training_curves_calibrated")


@_section("Ablations of the geometry refinement")
def ablation_section(inp: Inputs) -> list:
    m = inp.get("metrics")
    if m is None:
        return inp.need("metrics")
    df = m.df
    abl = df[df["method"].isin(T.ABLATIONS)]
    if abl.empty:
        return [Text("No ablation run is listed in this profile (protocol.runs); the "
                     "warm-start and component tables need them.")]
    seed = int(abl["seed"].mode().iloc[0])
    group = (test_groups(inp.get("manifest").df) if inp.get("manifest") else sorted(df["group"].unique()))[0]
    epochs = {} if inp.logs is None else {
        method: int(part.loc[part["epoch"] > 0, "epoch"].nunique())
        for method, part in inp.logs[inp.logs["seed"] == seed].groupby("method")}
    blocks = [Text(f"Mechanistic ablations: seed {seed} on {group} (the first test group), same data, "
                   f"pseudo-labels, architecture and calibration protocol. Single-seed evidence only.")]
    for mode in MODES:
        means = T.ablation_means(df, group, seed, mode)
        blocks += [t for t in (T.warm_start_table(means, epochs, group, seed, mode, inp.fixed_tau),
                               T.component_table(means, group, seed, mode, inp.fixed_tau)) if t is not None]
    return blocks


@_section("Multi-prompt teacher and reliability gate")
def teacher_section(inp: Inputs) -> list:
    tmart = inp.get("teacher_metrics")
    if inp.no_masks:
        return [Text(NOT_COMPUTED.replace("Scores need", "The teacher's scores need")), *gate_distribution_blocks(inp)]
    if tmart is None:
        return inp.need("teacher_metrics")
    tm = tmart.df
    extra = tmart.meta.extra or {}
    backend = str(extra.get("teacher_backend", "unknown"))
    note = teacher_note(backend)
    selected = extra.get("selected_source")
    blocks = []
    if is_simulator(backend):
        blocks.append(Text("**All teacher numbers in this section describe the teacher SIMULATOR of the "
                               "synthetic benchmark, not SAM 3.**  Two of its findings are true by construction "
                               "and are not agreement with the paper: the six-prompt vote beating single prompts "
                               "(the simulator's errors are mostly prompt-specific, calibrated to the paper's "
                               "prompt table) and the gate separating poor from good pseudo-masks (its breakdown "
                           "on hard images leaves at most one valid prompt, so g = 0 there)."))
    if selected is None:
        blocks.append(Text("No validation image has a reference mask: no validation-selected prompt."))
    groups = list(dict.fromkeys(tm.loc[tm["split"] == "test", "group"]))
    blocks += [T.teacher_prompt_table(teacher_prompt_quality(tm, g, extra.get("base_source", "prompt_0"), selected,
                                                             list(extra.get("prompts") or [])), g, note)
               for g in groups]
    blocks.append(T.teacher_domain_table(teacher_domain_quality(tm), note))
    gates = inp.get("gates")
    if gates is None:
        return blocks + inp.need("gates")
    analyses = [gate_analysis(tm, gates.df, g) for g in groups + ([None] if len(groups) > 1 else [])]
    return blocks + [T.gate_table(analyses, note)]


#: the Efficiency section of a project made without its benchmark stage (``distill --no-benchmark``)
BENCHMARK_SKIPPED = ("**The efficiency benchmark was skipped on purpose** (`geodistill distill --no-benchmark`): this "
                     "project's pipeline has no {stage} stage, so the deployed student's speed and memory were not "
                     "measured.  Run distill again without `--no-benchmark` to measure them.")


def stage_left_out(art: Path, stage: str) -> bool:
    """Whether the dvc.yaml beside ``art`` lists stages but not ``stage``; False without a readable dvc.yaml."""
    try:
        stages = (yaml.safe_load((Path(art).parent / catalog.DVC_FILE).read_text()) or {}).get("stages")
    except (OSError, yaml.YAMLError, AttributeError):
        return False
    return isinstance(stages, dict) and bool(stages) and stage not in stages


@_section("Efficiency")
def efficiency_section(inp: Inputs) -> list:
    eff = inp.get("efficiency")
    stage = catalog.ARTIFACTS["efficiency"].stage
    if eff is not None:
        return [T.efficiency_table(eff.df)]
    return [Text(BENCHMARK_SKIPPED.format(stage=stage))] if stage_left_out(inp.art, stage) else inp.need("efficiency")


@_section("Training curves")
def training_section(inp: Inputs, plots: dict) -> list:
    logs = inp.logs
    if inp.no_masks:
        return [Text(NOT_COMPUTED.replace("Scores need", "Validation curves need")),
                *([loss_figure(logs)] if logs is not None and "loss" in logs.columns else [])]
    if logs is None or "val_iou" not in logs.columns:
        return [Missing("training logs", "no active checkpoint with a log.parquet under "
                        f"`{inp.art / 'checkpoints'}` -- produced by the `train` stages.")]
    cols = [c for c in ("epoch", "val_iou", "val_bf1", "val_iou_cal", "val_tau_cal", "loss", "stage", "method", "seed")
            if c in logs.columns]
    plots["training_curves"] = logs[cols].reset_index(drop=True)
    img = F.line_plot(_epoch_curves(logs, "val_iou"), f"Validation Image IoU during training "
                      f"(tau {tau_text(inp.fixed_tau)})", EPOCH_AXIS, "val Image IoU")
    return [_figure("fig:training-curves", "Training curves", "Validation Image IoU per epoch (mean over "
                    "seeds per method; a warm-started Stage-II run is drawn after its Stage-I run's last epoch, at "
                    "its seed).", img,
                    "training_curves"), *([ending_table(inp.runs)] if inp.runs else [])]


@_section("Qualitative results")
def qualitative_section(inp: Inputs, n_images: int, device="cpu", treatment: str = PROPOSED,
                        control: str = BASELINE) -> list:
    """Show control vs treatment on the first test group (paper Fig. ``fig:qualitative-results``).

    Same seed, calibrated thresholds; images evenly spaced by rank of the per-image IoU gain, from the largest
    gain to the largest loss.
    """
    if inp.no_masks:
        return pseudo_label_panels(inp, n_images, device, (control, treatment))
    if miss := inp.need("metrics", "thresholds", "images", "reference", "manifest"):
        return miss
    m = inp.get("metrics").df
    cal = m[m["threshold_mode"] == "calibrated"]
    seeds = sorted(set(cal.loc[cal.method == treatment, "seed"]) & set(cal.loc[cal.method == control, "seed"]))
    if not seeds or n_images <= 0:
        return [Missing(f"runs of both `{control}` and `{treatment}`",
                        "the qualitative panels compare them on the same seed.")]
    seed = seeds[0]
    group = test_groups(inp.get("manifest").df)[0]
    sub = cal[(cal.group == group) & (cal.seed == seed)]
    a = sub[sub.method == control].set_index("image_id")
    b = sub[sub.method == treatment].set_index("image_id")
    common = a.index.intersection(b.index)
    gain = (b.loc[common, "iou"] - a.loc[common, "iou"]).sort_values(ascending=False, kind="mergesort")
    pick = gain.index[_spread(len(gain), n_images)]
    ids = inp.get("manifest").df["image_id"].to_numpy()
    rows_idx = np.array([int(np.flatnonzero(ids == i)[0]) for i in pick])
    images = read_chunk_rows(inp.get("images")["image"], rows_idx)
    gts = read_chunk_rows(inp.get("reference")["mask"], rows_idx).astype(bool)
    preds = _student_masks(inp, (control, treatment), seed, images,
                           lambda method: float(sub[sub.method == method]["tau"].iloc[0]), device)
    rows = []
    for j, iid in enumerate(pick):
        scores = {T.label(mm): f"IoU {r['iou']:.3f}  BF1 {r['bf1']:.3f}"
                  for mm, r in ((control, a.loc[iid]), (treatment, b.loc[iid]))}
        rows.append(F.qualitative_row(images[j], gts[j], {T.label(mm): preds[mm][j] for mm in (control, treatment)},
                                      scores, f"({chr(97 + j)}) {iid}"))
    return [_figure(
        "fig:qualitative-results", f"{T.label(control)} vs {T.label(treatment)} on {group}",
        f"Seed {seed}, validation-calibrated thresholds. Green: true positives, red: false positives, blue: false "
        f"negatives; yellow: ground-truth contour. Rows ordered from the largest Image IoU gain to the largest loss "
        f"of {T.label(treatment)}; metrics on full frames.", F.image_grid(rows), "qualitative")]


def gate_extremes(g: np.ndarray, n_images: int) -> np.ndarray:
    """Positions of the ``max(1, n_images // 2)`` lowest gates (lowest first), then as many highest, each once."""
    k = max(1, n_images // 2)
    order = np.argsort(np.asarray(g, float), kind="mergesort")
    low = order[:k]
    high = [i for i in order[::-1][:k] if i not in set(low)]
    return np.asarray([*low, *high], dtype=np.int64)


def pseudo_label_panels(inp: Inputs, n_images: int, device="cpu",
                        methods: tuple[str, ...] = (BASELINE, PROPOSED)) -> list:
    """Show, without any mask, the students' masks beside their pseudo-labels (the vote M).

    The lowest- and the highest-gate training images (:func:`gate_extremes`), at each run's fixed tau;
    agreement, not accuracy.
    """
    if miss := inp.need("thresholds", "images", "consensus", "gates", "manifest"):
        return miss
    thr = inp.get("thresholds").df
    present = [m for m in methods if m in set(thr["method"])]
    seeds = sorted(set.intersection(*(set(thr.loc[thr["method"] == m, "seed"]) for m in present))) if present else []
    if not seeds or n_images <= 0:
        return [Missing(f"a run of `{'` or `'.join(methods)}`", "the panels show its student's masks.")]
    seed = seeds[0]
    mdf = inp.get("manifest").df
    gates = inp.get("gates").df.set_index("image_id")["g"]
    train = np.flatnonzero((mdf["split"] == "train").to_numpy() & mdf["image_id"].isin(gates.index).to_numpy())
    if train.size == 0:
        return [Text("No training image with a gate to show.")]
    ids = mdf["image_id"].to_numpy()
    g = gates.reindex(ids[train]).to_numpy(float)
    pos = gate_extremes(g, n_images)
    rows_idx = train[pos]
    images = read_chunk_rows(inp.get("images")["image"], rows_idx)
    voted = read_chunk_rows(inp.get("consensus")["voted"], rows_idx).astype(bool)
    taus = {m: float(thr.loc[(thr["method"] == m) & (thr["seed"] == seed), "tau"].iloc[0]) for m in present}
    preds = _student_masks(inp, present, seed, images, taus.get, device)
    rows = []
    for j, i in enumerate(rows_idx):
        scores = {T.label(m): f"IoU vs M {image_iou(preds[m][j], voted[j]):.2f}" for m in present}
        rows.append(F.qualitative_row(images[j], voted[j], {T.label(m): preds[m][j] for m in present}, scores,
                                      f"({chr(97 + j)}) g={g[pos[j]]:.2f} {ids[i]}",
                                      reference=("pseudo-label M", "(yellow contour)")))
    n_low = max(1, n_images // 2)
    tau_words = ", ".join(f"{T.label(m)} tau = {taus[m]:g}" for m in present)
    return [_figure(
        "fig:student-vs-pseudo-labels", "Students beside their pseudo-labels (no masks: agreement, not accuracy)",
        f"Seed {seed}; the {min(n_low, len(pos))} training image(s) with the lowest reliability gate g first, then "
        f"the highest ({tau_words}: the fixed threshold).  Yellow contour: the pseudo-label M (the teacher's 50 % "
        "vote the students were trained on), not a true mask.  Green: student and M agree on foreground, red: "
        "student only, blue: M only; IoU vs M is their agreement.  A low-gate row shows where the pseudo-label "
        "is least trusted; only masks (`--val-masks`) say which of the two is right.",
        F.image_grid(rows), "student_vs_pseudo_labels")]


def gate_distribution_blocks(inp: Inputs) -> list:
    """Plot the training images' reliability gate g (eq:reliability-gate) as a histogram with a sentence of counts."""
    gates = inp.get("gates")
    if gates is None:
        return inp.need("gates")
    df = gates.df
    g = df.loc[df["split"] == "train", "g"].to_numpy(float) if "split" in df.columns else df["g"].to_numpy(float)
    g = g[np.isfinite(g)]
    if g.size == 0:
        return [Text("No training image has a gate.")]
    zero = int((g == 0).sum())
    img = F.histogram(g, np.linspace(0.0, 1.0, 21), "Reliability gate of the training images", "gate g",
                      "training images")
    return [Text(f"Gate g over the {g.size} training images: median {np.median(g):.2f}, {zero} "
                 f"({zero / g.size:.0%}) at g = 0 (their pseudo-geometry terms get no weight in Stage II), "
                 f"{int((g >= 0.5).sum())} at g >= 0.5."),
            _figure("fig:gate-distribution", "Distribution of the reliability gate",
                    "Training images per gate bin (width 0.05); g = c-, v- and area-gate factors multiplied.  "
                    "Computed without masks.", img, "gate_distribution")]


def loss_figure(logs: pd.DataFrame) -> Figure:
    """Plot the training loss per epoch (mean over seeds per method), for a run without validation masks."""
    img = F.line_plot(_epoch_curves(logs, "loss"), "Training loss", EPOCH_AXIS, "loss")
    return _figure("fig:training-loss", "Training loss", "Training loss per epoch (mean over seeds per method; "
                   "Stage I and Stage II losses differ in their terms, so compare a method with itself).", img,
                   "training_loss")


@_section("Pseudo-target construction", needs=("manifest", "images", "teacher", "consensus", "geometry", "gates"))
def pseudo_target_section(inp: Inputs, n_images: int) -> list:
    """Paper Fig. pseudo-geometry for training images spread over the gate's range (highest g first)."""
    mdf = inp.get("manifest").df
    gates = inp.get("gates").df.set_index("image_id")
    train = mdf.index[mdf["split"] == "train"].to_numpy()
    if train.size == 0 or n_images <= 0:
        return [Text("No training image to show.")]
    ids = mdf["image_id"].to_numpy()
    g = gates.reindex(ids[train])["g"].to_numpy(float)
    ranked = train[np.argsort(-np.nan_to_num(g, nan=-1), kind="mergesort")]
    pick = np.sort(ranked[_spread(len(ranked), n_images)])
    teacher, consensus, geometry = inp.get("teacher"), inp.get("consensus"), inp.get("geometry")
    prompts = list(teacher.attrs.get("prompts", []))
    images, tmasks, scores, agreement, voted, sdf, skel = (
        read_chunk_rows(a, pick) for a in (inp.get("images")["image"], teacher["masks"], teacher["scores"],
                                           consensus["agreement"], consensus["voted"], geometry["sdf"],
                                           geometry["skeleton"]))
    rows = []
    for j, i in enumerate(pick):
        gr = gates.loc[ids[i]] if ids[i] in gates.index else None
        gate_text = ([f"c={gr['c']:.2f} v={gr['v']:.2f}", f"a={gr['a']:.3f} g={gr['g']:.2f}"]
                     if gr is not None else ["gate: n/a", ""])
        labels = [f"p{k + 1} s={scores[j, k]:.2f}" for k in range(tmasks.shape[1])]
        rows.append(F.pseudo_target_row(images[j], tmasks[j], labels, agreement[j], voted[j], sdf[j], skel[j],
                                        gate_text, str(ids[i])))
    prompt_list = "; ".join(f"p{k + 1} = `{p}`" for k, p in enumerate(prompts))
    sim = (" The prompt masks come from the teacher SIMULATOR, not SAM 3."
           if is_simulator(str(teacher.attrs.get("backend", "unknown"))) else "")
    return [_figure(
        "fig:pseudo-geometry", "Multi-prompt pseudo-target construction",
        f"Training images (highest gate g first): the {tmasks.shape[1]} prompt masks with teacher scores s, the "
        f"agreement map A, the 50 % vote M, the normalised SDF D (red inside, blue outside) and the skeleton K; the "
        f"gate's factors c (agreement), v (valid-prompt ratio), a (pseudo area) and g.{sim} Prompts: {prompt_list}.",
        F.image_grid(rows), "pseudo_targets")]


def provenance_section(inp: Inputs) -> Section:
    """Tabulate every input artifact's schema, stage and fingerprint, and the missing ones."""
    rows = [[f"`{catalog.ARTIFACTS[n].path}`", a.meta.schema, a.meta.stage, a.fingerprint[:16]]
            for n, a in inp.found.items()]
    rows += [[f"`{catalog.ARTIFACTS[n].path}`", "--", "--",
              "not computed (no masks)" if inp.no_masks and n in MASK_INPUTS else "missing"] for n in inp.missing]
    return Section("Provenance", [Table("tab:provenance", "Input artifacts", ["Artifact", "Schema", "Stage",
                                                                             "Fingerprint"], rows)])


def build_report(art: str | Path, cfg: dict, profile: str = "", device="cpu",
                 environment: dict | None = None) -> tuple[Report, dict, Inputs]:
    """Build the report from the artifacts under ``art``; a missing input becomes a note, never a failure.

    Parameters
    ----------
    art : str or Path
        The artifacts folder.
    cfg : dict
        The validated ``report`` params section (``report.qualitative_images``, ``report.pseudo_target_images``).
    profile : str
        The params profile the runs used (in the title; selects the noise floor); "" when unknown.
    device : str or torch.device
        Where the students predict the qualitative panels.
    environment : dict, optional
        The report machine's record (:func:`pipeline.artifacts.provenance.collect`); None: not recorded.

    Returns
    -------
    tuple of (Report, dict, Inputs)
        The report, the plot tables DVC shows (name -> DataFrame) and the opened inputs.
    """
    inp = load_inputs(art, profile or None)
    plots: dict[str, pd.DataFrame] = {}
    with T.human_trained(inp.run_review, inp.departures):
        sections = [glossary_section(), data_section(inp), results_section(inp),
                    qualitative_section(inp, cfg["qualitative_images"], device),
                    threshold_section(inp, plots), diagnostics_section(inp, plots), teacher_section(inp),
                    pseudo_target_section(inp, cfg["pseudo_target_images"]), ablation_section(inp),
                    efficiency_section(inp), training_section(inp, plots), environment_section(environment, inp.runs),
                    provenance_section(inp)]
    title = "GeoDistill-Refine report" + (f" ({profile} profile)" if profile else "")
    return Report(title, sections), plots, inp
