"""Gather the evaluation artifacts into one :class:`Report` (tables, figures, honest statements) and
the plot tables DVC shows.  A missing input never fails the report: its section says what is missing
and which stage produces it."""

from __future__ import annotations

import dataclasses
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
from pipeline.evaluation.inference import CORRECTED_VALIDATION, iter_runs, load_student, predict_probs
from pipeline.methods import BASELINE, PROPOSED
from pipeline.metrics import image_iou
from pipeline.report import figures as F
from pipeline.report import tables as T
from pipeline.report.analysis import (epoch_swings, fixed_tau_findings, gate_analysis, select_noise_floor, size_split,
                                      tau_text, teacher_domain_quality, teacher_prompt_quality, teacher_vote_means)
from pipeline.report.document import Figure, Missing, Report, Section, Table, Text
from pipeline.report.environment import environment_section, training_runs
from pipeline.report.glossary import glossary_section
from pipeline.thresholds import mask_from_probs

#: the figures' file names (pipeline.catalog.OUTPUT_FILES)
FIGURES = catalog.output_names("report_figures")
# artifact file -> (schema, stage that produces it)
#: the catalogue artifacts the report reads (paths, schemas and producing stages from pipeline.catalog)
INPUTS = ("manifest", "images", "reference", "teacher", "consensus", "geometry", "gates", "thresholds", "metrics",
          "summary", "teacher_metrics", "efficiency")


@dataclasses.dataclass
class Inputs:
    art: Path
    found: dict[str, Any]
    missing: dict[str, Missing]
    logs: pd.DataFrame | None = None
    runs: list = dataclasses.field(default_factory=list)  # pipeline.report.environment.training_runs
    no_masks: bool = False  # no validation or test image has a mask (a distill project without --val-masks)
    #: the stability benchmark's noise-floor record of the runs' recipe (reports/noise_floor.json), None when
    #: not measured
    noise_floor: dict | None = None
    #: calibrate.fixed_tau as the run recorded it (:func:`recorded_fixed_tau`), None when unknown
    fixed_tau: float | None = None
    #: {method: the review params its runs recorded} for runs trained on human corrections
    #: (:func:`recorded_review`; labels: :func:`pipeline.report.tables.human_trained`)
    run_review: dict = dataclasses.field(default_factory=dict)
    #: corrected training images calibrate used as validation images (review.mode validate), 0 if none
    corrected_validation: int = 0

    def get(self, name):
        return self.found.get(name)

    def need(self, *names) -> list:
        """A note per missing input; without any mask, inputs that need masks are not missing but not
        computed, and one plain sentence says so (:data:`NOT_COMPUTED`)."""
        if self.no_masks and any(n in MASK_INPUTS for n in names):
            return [Text(NOT_COMPUTED)]
        return [self.missing[n] for n in names if n in self.missing]


def load_inputs(art: str | Path, profile: str | None = None) -> Inputs:
    """Open every input that exists; record a :class:`Missing` note for each one that does not.
    ``profile``: the params profile of the runs (the noise floor must come from its data sizes)."""
    art = Path(art)
    found, missing = {}, {}
    for name in INPUTS:
        spec = catalog.ARTIFACTS[name]
        try:
            found[name] = open_artifact(catalog.path(name, art), name)
        except ArtifactError as e:
            missing[name] = Missing(f"`{spec.path}`", f"{e} -- produced by the `{spec.stage}` stage.")
    require_same_run(*found.values())
    inp = Inputs(art, found, missing)
    inp.logs = training_logs(art / "checkpoints")
    inp.runs = training_runs(catalog.path("checkpoints", art))
    if found.get("manifest") is not None:
        inp.no_masks = no_reference_masks(found["manifest"].df, found.get("reference"))
    inp.noise_floor = noise_floor_for_runs(catalog.path("noise_floor", art), inp.runs, found.get("images"), profile)
    inp.fixed_tau = recorded_fixed_tau(found.get("thresholds"), found.get("metrics"))
    inp.run_review = recorded_review(catalog.path("checkpoints", art))
    thr = found.get("thresholds")
    inp.corrected_validation = int((thr.meta.extra or {}).get(CORRECTED_VALIDATION, 0)) if thr is not None else 0
    return inp


def recorded_review(checkpoints: Path) -> dict[str, dict]:
    """{method: ``review`` params} of the runs whose checkpoint records human corrections in the loss
    (``annotation_free: false`` with ``corrections_mode``, written by
    :func:`pipeline.training.inputs.replace_targets`); {} when none did or there are no checkpoints."""
    try:
        extras = [(method, _meta_extra(path)) for method, _, path in iter_runs(checkpoints)]
    except ArtifactError:
        return {}
    return {method: {"corrections": int(e.get("human_corrections", 0)), "mode": e["corrections_mode"]}
            for method, e in extras if e.get("annotation_free") is False and e.get("corrections_mode")}


def _meta_extra(path: Path) -> dict:
    """The ``extra`` fields of the artifact at ``path`` ({} when it cannot be read)."""
    try:
        return open_artifact(path).meta.extra or {}
    except ArtifactError:
        return {}


def corrections_note(inp: Inputs) -> str | None:
    """A sentence on the human corrections this run used (review params; pipeline/review/apply.py), None without."""
    parts = []
    if inp.corrected_validation:
        parts.append(f"**{inp.corrected_validation} training images a person corrected are validation images** "
                     f"(`review.mode: validate`): their corrected masks select checkpoints and calibrate tau, and "
                     f"they left the training set, so the students stay annotation-free.")
    if inp.run_review:
        names = ", ".join(T.label(m) for m in inp.run_review)
        parts.append(f"**Trained on human corrections (`review.mode: replace`), NOT annotation-free:** {names}. "
                     f"Corrected masks replaced those images' voted masks in the loss; every table labels these runs.")
    return " ".join(parts) or None


def noise_floor_for_runs(path: Path, runs: list, images, profile: str | None = None) -> dict | None:
    """The stability benchmark's noise-floor record (``path``, absent = not measured) measured in this
    report's configuration: the recipe the training ``runs`` used, the resolution of ``images`` and the
    ``profile``'s data sizes (:func:`pipeline.report.analysis.select_noise_floor`)."""
    doc = json.loads(path.read_text()) if path.is_file() else None
    recipes = {r["recipe"] for r in runs if r.get("recipe")}
    resolution = int(images["image"].shape[1]) if images is not None and "image" in images else None
    return select_noise_floor(doc, recipes.pop() if len(recipes) == 1 else None, resolution, profile)


def gain_interval(summary) -> str | None:
    """The gain interval (evaluate.interval) the evaluate stage recorded in ``summary``'s meta; None for a
    summary written before it was recorded (then the former seed-aware bootstrap)."""
    return ((summary.meta.extra or {}).get("interval")) if summary is not None else None


def recorded_fixed_tau(thresholds, metrics) -> float | None:
    """The fixed tau of this run (``calibrate.fixed_tau``) as its artifacts recorded it: thresholds.parquet's
    ``fixed_tau`` column, else the tau of metrics.parquet's fixed-mode rows; None when neither holds exactly
    one value.  The report's words about the fixed threshold quote it."""
    for art, column, rows in ((thresholds, "fixed_tau", None), (metrics, "tau", "fixed")):
        if art is None or column not in art.df.columns:
            continue
        df = art.df if rows is None else art.df[art.df["threshold_mode"] == rows]
        values = set(df[column].astype(float))
        if len(values) == 1:
            return values.pop()
    return None


def training_logs(checkpoints: Path) -> pd.DataFrame | None:
    """All active runs' training logs stacked, with method and seed columns (None when none)."""
    frames = []
    try:
        runs = list(iter_runs(checkpoints))
    except ArtifactError:
        return None
    for method, seed, path in runs:
        try:
            log = open_artifact(path).table(catalog.TRAINING_LOG_FILE).copy()
        except ArtifactError:
            continue
        log["method"], log["seed"] = method, seed
        frames.append(log)
    return pd.concat(frames, ignore_index=True) if frames else None


def teacher_note(backend: str) -> str:
    if backend == "simulated":
        return ("Teacher = a SIMULATOR of prompt-dependent foundation-model errors (synthetic benchmark), "
                "not SAM 3: these teacher numbers describe the simulator.")
    if backend == "sam3":
        return "Teacher = SAM 3 with the six fixed text prompts (backend `sam3`)."
    return f"Teacher backend: `{backend}`."


NO_MASKS_NOTE = (
    "**No validation or test masks were available** (e.g. `geodistill distill` without `--val-masks`): every "
    "image is a training image, Stage I and Stage II keep their last epoch, the threshold is the fixed "
    "tau = `calibrate.fixed_tau` ({tau}, not calibrated), and there are no accuracy numbers -- the student's "
    "quality on this data is unmeasured.  Pass a few masks (`--val-masks DIR`) to select, calibrate and score.")


#: inputs computed only from validation/test masks (the scores; the teacher scored against the masks)
MASK_INPUTS = ("summary", "metrics", "teacher_metrics")
NOT_COMPUTED = ("**Not computed: no validation or test masks.** Scores need reference masks, and none were "
                "given (`geodistill distill` without `--val-masks`), so nothing here was measured.  Rerun with "
                "`--val-masks DIR` (a few masks named like their images) to compute it.")
FIXED_TAU_NOTE = ("**Threshold: the fixed tau = {tau:g}** (`calibrate.fixed_tau`), not calibrated: without "
                  "validation masks there is nothing to calibrate on.  Pass `--val-masks DIR` to calibrate it.")


def no_reference_masks(manifest_df: pd.DataFrame, reference) -> bool:
    """True when no validation or test image has a reference mask (nothing was selected, calibrated or scored)."""
    if reference is None:
        return False
    held_out = manifest_df["split"].isin(["val", "test"]).to_numpy()
    return not (held_out & reference.numpy("has_mask").astype(bool)).any()


def test_groups(manifest_df: pd.DataFrame) -> list[str]:
    """Test groups in manifest order (the first is the paper's KCP role: ablations, qualitative)."""
    return list(dict.fromkeys(manifest_df.loc[manifest_df["split"] == "test", "group"]))


# --------------------------------------------------------------------------------------------------
# Sections
# --------------------------------------------------------------------------------------------------
def data_section(inp: Inputs) -> Section:
    sec = Section("Data, teacher and protocol")
    m = inp.get("manifest")
    if m is None:
        sec.blocks += inp.need("manifest")
        return sec
    df = m.df
    datasets = sorted(df["dataset"].unique())
    backend = str(inp.get("teacher").attrs.get("backend", "unknown")) if inp.get("teacher") else "unknown"
    if "synthetic" in datasets:
        sec.blocks.append(Text(
            "**Dataset: the embedded SYNTHETIC spacecraft benchmark** (rendered spacecraft with a spacecraft-disjoint "
            "split shaped like SpaceSense-Bench), not SpaceSense-Bench, SPEED+ or TANGO. Its teacher is a "
            "**SIMULATOR** of prompt-dependent foundation-model errors, not SAM 3. The numbers below test the "
            "pipeline's behaviour on this benchmark; they are not comparable to the paper's."))
    else:
        sec.blocks.append(Text(f"Dataset(s): {', '.join(f'`{d}`' for d in datasets)}."))
    sec.blocks.append(Text(teacher_note(backend)))
    sec.blocks.append(Text(
        "Manual (reference) masks are used only for validation-time checkpoint selection, threshold calibration "
        "and evaluation (and, on the synthetic benchmark, inside the teacher simulator); they never enter a "
        "student's training loss."))
    if no_reference_masks(df, inp.get("reference")) and not inp.corrected_validation:
        sec.blocks.append(Text(NO_MASKS_NOTE.format(tau=tau_text(inp.fixed_tau))))
    if (note := corrections_note(inp)) is not None:
        sec.blocks.append(Text(note))
    rows, spacecraft = [], T.spacecraft_per_group(df)  # the footnotes state the same counts
    for (ds, split, group), part in df.groupby(["dataset", "split", "group"], sort=False):
        rows.append([str(ds), str(split), str(group), str(len(part)), str(spacecraft[str(group)])])
    sec.blocks.append(Table("tab:data", "Images per split and group", ["Dataset", "Split", "Group", "Images",
                                                                      "Spacecraft"], rows))
    return sec


def threshold_section(inp: Inputs, plots: dict) -> Section:
    sec = Section("Threshold calibration")
    thr = inp.get("thresholds")
    if thr is None:
        sec.blocks += inp.need("thresholds")
        return sec
    df = thr.df
    if inp.no_masks and not inp.corrected_validation:
        taus = sorted({float(t) for t in df["tau"]})
        sec.blocks.append(Text(FIXED_TAU_NOTE.format(tau=taus[0] if len(taus) == 1 else float("nan"))))
        return sec
    sec.blocks.append(T.thresholds_table(df, inp.fixed_tau))
    long = [pd.DataFrame({"tau": r["grid"], "val_iou": r["curve"], "method": r["method"], "seed": r["seed"]})
            for _, r in df.iterrows() if "grid" in df.columns]
    if long:
        curves = pd.concat(long, ignore_index=True)
        plots["threshold_curve"] = curves
        series = []
        for method, part in curves.groupby("method", sort=False):
            mean = part.groupby("tau")["val_iou"].mean()
            taus = df[df["method"] == method]["tau"]
            series.append({"x": mean.index.to_numpy(), "y": mean.to_numpy(), "label": T.label(method),
                           "marker": float(taus.mean()), **F.method_style(method)})
        img = F.line_plot(series, "Validation Image IoU vs threshold", "tau", "mean val Image IoU")
        sec.blocks.append(Figure("fig:threshold-curves", "Threshold curves", "Mean validation Image IoU of [P >= tau] "
                                 "over the calibration grid (mean over seeds per method; dot: mean calibrated tau).",
                                 F.png_bytes(img), FIGURES["threshold_curves"], F.svg_bytes(img)))
    return sec


def results_section(inp: Inputs) -> Section:
    sec = Section("Student results on the test groups")
    s = inp.get("summary")
    if s is None:
        sec.blocks += inp.need("summary")
        return sec
    groups = list(dict.fromkeys(s.df["group"]))
    if inp.get("manifest") is not None:
        order = test_groups(inp.get("manifest").df)
        groups = [g for g in order if g in groups] + [g for g in groups if g not in order]
    for mode in ("calibrated", "fixed"):
        if (s.df["threshold_mode"] == mode).any():
            sec.blocks.append(T.results_table(s.df, mode, groups, inp.noise_floor, inp.fixed_tau, gain_interval(s),
                                              spacecraft_counts(inp)))
    for mode in ("calibrated", "fixed"):
        if (s.df["threshold_mode"] == mode).any():
            sec.blocks.append(T.diagnostics_table(s.df, mode, groups, inp.fixed_tau))
    vote = vote_means(inp)
    for mode in ("calibrated", "fixed"):
        if (s.df["threshold_mode"] == mode).any():
            tab = T.reference_points_table(s.df, vote, mode, groups, inp.fixed_tau)
            if tab is not None:
                sec.blocks.append(tab)
    return sec


def spacecraft_counts(inp: Inputs) -> dict[str, int] | None:
    """{group: spacecraft} of the manifest (the data table's column), None without a manifest."""
    m = inp.get("manifest")
    return T.spacecraft_per_group(m.df) if m is not None else None


def vote_means(inp: Inputs) -> pd.DataFrame | None:
    """The teacher vote scored as a predictor per test group (teacher_metrics.parquet), or None."""
    tm = inp.get("teacher_metrics")
    return teacher_vote_means(tm.df) if tm is not None else None


def ordered_groups(inp: Inputs, present) -> list[str]:
    """``present`` groups in the manifest's test-group order (unknown ones last)."""
    present = list(dict.fromkeys(present))
    if inp.get("manifest") is None:
        return present
    order = test_groups(inp.get("manifest").df)
    return [g for g in order if g in present] + [g for g in present if g not in order]


def diagnostics_section(inp: Inputs, plots: dict) -> Section:
    """Controls and threshold/calibration diagnostics (issue 17): what the numbers say about the
    fixed-tau reversal, the budget-matched control, calibration, per-epoch stability, target size."""
    sec = Section("Controls and threshold diagnostics")
    if inp.no_masks:
        sec.blocks.append(Text(NOT_COMPUTED))
        return sec
    s, thr, m = inp.get("summary"), inp.get("thresholds"), inp.get("metrics")
    if s is None and thr is None:
        sec.blocks += inp.need("summary", "thresholds")
        return sec
    groups = ordered_groups(inp, s.df["group"] if s is not None else [])
    findings = fixed_tau_findings(s.df if s is not None else None, thr.df if thr is not None else None,
                                  m.df if m is not None else None, inp.logs, vote_means(inp), groups, label=T.label,
                                  noise_floor=inp.noise_floor, fixed_tau=inp.fixed_tau)
    sec.blocks += [Text(f) for f in findings]
    if s is not None:
        for mode in ("calibrated", "fixed"):
            tab = T.controls_table(s.df, mode, groups, inp.noise_floor, inp.fixed_tau, gain_interval(s),
                                   spacecraft_counts(inp))
            if tab is not None:
                sec.blocks.append(tab)
    if thr is not None and "ece" in thr.df.columns:
        sec.blocks += calibration_blocks(thr.df, plots, inp.fixed_tau)
    if inp.logs is not None and "val_iou_cal" in inp.logs.columns and inp.logs["val_iou"].notna().any():
        sec.blocks.append(T.epoch_swing_table(epoch_swings(inp.logs), inp.fixed_tau))
        sec.blocks.append(epoch_calibrated_figure(inp.logs, inp.fixed_tau))
    if m is not None and "target_size" in m.df.columns:
        split = size_split(m.df)
        frac = (m.meta.params or {}).get("evaluate.tiny_target_max_fraction")
        for mode in ("calibrated", "fixed"):
            if (split["threshold_mode"] == mode).any():
                sec.blocks.append(T.size_split_table(split, mode, frac, inp.fixed_tau))
    return sec


def calibration_blocks(thr: pd.DataFrame, plots: dict, fixed_tau: float | None = None) -> list:
    """The calibration table, the reliability diagram and the area-vs-tau figure (validation split;
    mean over seeds per method)."""
    blocks = [T.calibration_table(thr, fixed_tau)]
    rel, area = [], []
    for method, part in thr.groupby("method", sort=False):
        with warnings.catch_warnings():  # a bin empty in every seed stays NaN (not drawn)
            warnings.simplefilter("ignore", RuntimeWarning)
            conf = np.nanmean(np.stack([np.asarray(c, float) for c in part["rel_confidence"]]), axis=0)
            freq = np.nanmean(np.stack([np.asarray(f, float) for f in part["rel_frequency"]]), axis=0)
        rel.append({"x": conf, "y": freq, "label": f"{T.label(method)} (ECE {part['ece'].mean():.3f})",
                    **F.method_style(method)})
        curve = np.nanmean(np.stack([np.asarray(a, float) for a in part["area_curve"]]), axis=0)
        area.append({"x": np.asarray(part["grid"].iloc[0], float), "y": curve, "label": T.label(method),
                     "marker": float(part["tau"].mean()), **F.method_style(method)})
        for _, r in part.iterrows():
            plots.setdefault("_area", []).append(pd.DataFrame({"tau": r["grid"], "area_ratio": r["area_curve"],
                                                               "method": method, "seed": r["seed"]}))
    plots["area_curve"] = pd.concat(plots.pop("_area"), ignore_index=True)
    rel.append({"x": [0.0, 1.0], "y": [0.0, 1.0], "label": "perfect calibration", "color": F.REFERENCE_LINE,
                "style": "dashed"})
    grid = np.asarray(thr["grid"].iloc[0], float)
    area.append({"x": grid, "y": np.ones_like(grid), "label": "no inflation (ratio 1)", "color": F.REFERENCE_LINE,
                 "style": "dashed"})
    rel_chart = F.line_plot(rel, "Reliability diagram", "mean predicted probability", "foreground frequency",
                            ylim=(0.0, 1.0))
    blocks.append(Figure("fig:reliability", "Reliability diagram (validation pixels)",
                         "Fraction of reference-foreground pixels against the mean predicted probability in each "
                         "equal-width probability bin (mean over seeds per method); below the diagonal = "
                         "over-confident foreground.", F.png_bytes(rel_chart), FIGURES["reliability"],
                         F.svg_bytes(rel_chart)))
    area_chart = F.line_plot(area, "Predicted / reference area vs threshold", "tau",
                             "median predicted / reference area")
    blocks.append(Figure("fig:area-vs-tau", "Predicted against reference foreground area across tau",
                         "Median over validation images of predicted / reference foreground area of [P >= tau] "
                         "(mean over seeds per method; dot: mean calibrated tau; dashed grey: no inflation).",
                         F.png_bytes(area_chart), FIGURES["area_vs_tau"], F.svg_bytes(area_chart)))
    return blocks


def epoch_calibrated_figure(logs: pd.DataFrame, fixed_tau: float | None = None) -> Figure:
    """Per-epoch validation Image IoU at each epoch's calibrated tau (mean over seeds per method)."""
    series = []
    for method, part in logs.groupby("method", sort=False):
        mean = part.groupby("epoch")["val_iou_cal"].mean()
        series.append({"x": mean.index.to_numpy(float), "y": mean.to_numpy(float), "label": T.label(method),
                       **F.method_style(method)})
    img = F.line_plot(series, "Validation Image IoU at the per-epoch calibrated tau", "epoch (of the run's own "
                      "schedule)", "val Image IoU at calibrated tau")
    return Figure("fig:training-curves-calibrated", "Training curves at the calibrated tau",
                  "Validation Image IoU per epoch at the tau maximising it at that epoch (mean over seeds per "
                  f"method); compare with the tau = {tau_text(fixed_tau)} curves in the training-curves section.",
                  F.png_bytes(img),
                  FIGURES["training_curves_calibrated"], F.svg_bytes(img))


def ablation_section(inp: Inputs) -> Section:
    sec = Section("Ablations of the geometry refinement")
    m = inp.get("metrics")
    if m is None:
        sec.blocks += inp.need("metrics")
        return sec
    df = m.df
    abl = df[df["method"].isin(T.ABLATIONS)]
    if abl.empty:
        sec.blocks.append(Text("No ablation run is listed in this profile (protocol.runs); the "
                               "warm-start and component tables need them."))
        return sec
    seed = int(abl["seed"].mode().iloc[0])
    groups = test_groups(inp.get("manifest").df) if inp.get("manifest") else sorted(df["group"].unique())
    group = groups[0]
    epochs = {}
    if inp.logs is not None:
        for method, part in inp.logs[inp.logs["seed"] == seed].groupby("method"):
            epochs[method] = int(part.loc[part["epoch"] > 0, "epoch"].nunique())
    sec.blocks.append(Text(f"Mechanistic ablations: seed {seed} on {group} (the first test group), same data, "
                           f"pseudo-labels, architecture and calibration protocol. Single-seed evidence only."))
    for mode in ("calibrated", "fixed"):
        means = T.ablation_means(df, group, seed, mode)
        for tab in (T.warm_start_table(means, epochs, group, seed, mode, inp.fixed_tau),
                    T.component_table(means, group, seed, mode, inp.fixed_tau)):
            if tab is not None:
                sec.blocks.append(tab)
    return sec


def teacher_section(inp: Inputs) -> Section:
    sec = Section("Multi-prompt teacher and reliability gate")
    tmart = inp.get("teacher_metrics")
    if inp.no_masks:
        sec.blocks.append(Text(NOT_COMPUTED.replace("Scores need", "The teacher's scores need")))
        sec.blocks += gate_distribution_blocks(inp)
        return sec
    if tmart is None:
        sec.blocks += inp.need("teacher_metrics")
        return sec
    tm = tmart.df
    extra = tmart.meta.extra or {}
    backend = str(extra.get("teacher_backend", "unknown"))
    note = teacher_note(backend)
    prompts = list(extra.get("prompts") or [])
    base = extra.get("base_source", "prompt_0")
    selected = extra.get("selected_source")
    if backend == "simulated":
        sec.blocks.append(Text("**All teacher numbers in this section describe the teacher SIMULATOR of the "
                               "synthetic benchmark, not SAM 3.**  Two of its findings are true by construction "
                               "and are not agreement with the paper: the six-prompt vote beating single prompts "
                               "(the simulator's errors are mostly prompt-specific, calibrated to the paper's "
                               "prompt table) and the gate separating poor from good pseudo-masks (its breakdown "
                               "on hard images leaves at most one valid prompt, so g = 0 there)."))
    if selected is None:
        sec.blocks.append(Text("No validation image has a reference mask: no validation-selected prompt."))
    groups = list(dict.fromkeys(tm.loc[tm["split"] == "test", "group"]))
    for g in groups:
        sec.blocks.append(T.teacher_prompt_table(teacher_prompt_quality(tm, g, base, selected, prompts), g, note))
    sec.blocks.append(T.teacher_domain_table(teacher_domain_quality(tm), note))
    gates = inp.get("gates")
    if gates is None:
        sec.blocks += inp.need("gates")
    else:
        analyses = [gate_analysis(tm, gates.df, g) for g in groups]
        if len(groups) > 1:
            analyses.append(gate_analysis(tm, gates.df, None))
        sec.blocks.append(T.gate_table(analyses, note))
    return sec


#: the Efficiency section of a project made without its benchmark stage (``distill --no-benchmark``)
BENCHMARK_SKIPPED = ("**The efficiency benchmark was skipped on purpose** (`geodistill distill --no-benchmark`): this "
                     "project's pipeline has no {stage} stage, so the deployed student's speed and memory were not "
                     "measured.  Run distill again without `--no-benchmark` to measure them.")


def stage_left_out(art: Path, stage: str) -> bool:
    """Whether the DVC project of the artifacts folder ``art`` leaves ``stage`` out on purpose: its
    dvc.yaml (beside ``art``) lists stages, but not this one (a distill project made with
    ``--no-benchmark``); False without a readable dvc.yaml."""
    try:
        stages = (yaml.safe_load((Path(art).parent / catalog.DVC_FILE).read_text()) or {}).get("stages")
    except (OSError, yaml.YAMLError, AttributeError):
        return False
    return isinstance(stages, dict) and bool(stages) and stage not in stages


def efficiency_section(inp: Inputs) -> Section:
    sec = Section("Efficiency")
    eff = inp.get("efficiency")
    stage = catalog.ARTIFACTS["efficiency"].stage
    if eff is None and stage_left_out(inp.art, stage):
        sec.blocks.append(Text(BENCHMARK_SKIPPED.format(stage=stage)))
    elif eff is None:
        sec.blocks += inp.need("efficiency")
    else:
        sec.blocks.append(T.efficiency_table(eff.df))
    return sec


def training_section(inp: Inputs, plots: dict) -> Section:
    sec = Section("Training curves")
    logs = inp.logs
    if inp.no_masks:
        sec.blocks.append(Text(NOT_COMPUTED.replace("Scores need", "Validation curves need")))
        if logs is not None and "loss" in logs.columns:
            sec.blocks.append(loss_figure(logs))
        return sec
    if logs is None or "val_iou" not in logs.columns:
        sec.blocks.append(Missing("training logs", "no active checkpoint with a log.parquet under "
                                  f"`{inp.art / 'checkpoints'}` -- produced by the `train` stages."))
        return sec
    cols = [c for c in ("epoch", "val_iou", "val_bf1", "val_iou_cal", "val_tau_cal", "loss", "stage", "method", "seed")
            if c in logs.columns]
    plots["training_curves"] = logs[cols].reset_index(drop=True)
    series = []
    for method, part in logs.groupby("method", sort=False):
        mean = part.groupby("epoch")["val_iou"].mean()
        series.append({"x": mean.index.to_numpy(float), "y": mean.to_numpy(float), "label": T.label(method),
                       **F.method_style(method)})
    img = F.line_plot(series, f"Validation Image IoU during training (tau {tau_text(inp.fixed_tau)})",
                      "epoch (of the run's own schedule)",
                      "val Image IoU")
    sec.blocks.append(Figure("fig:training-curves", "Training curves", "Validation Image IoU per epoch (mean over "
                             "seeds per method; warm-started Stage-II runs count their own epochs from 1).",
                             F.png_bytes(img), FIGURES["training_curves"], F.svg_bytes(img)))
    return sec


# --------------------------------------------------------------------------------------------------
# Figures from images and predictions
# --------------------------------------------------------------------------------------------------
def qualitative_section(inp: Inputs, n_images: int, device="cpu", treatment: str = PROPOSED,
                        control: str = BASELINE) -> Section:
    """Paper Fig. qualitative-results: control vs treatment on the first test group, same seed,
    validation-calibrated thresholds.  Images are chosen by rank of the per-image IoU gain, evenly
    spaced from the largest gain to the largest loss (so failures are shown too)."""
    sec = Section("Qualitative results")
    if inp.no_masks:
        sec.blocks += pseudo_label_panels(inp, n_images, device, (control, treatment))
        return sec
    miss = inp.need("metrics", "thresholds", "images", "reference", "manifest")
    if miss:
        sec.blocks += miss
        return sec
    m = inp.get("metrics").df
    cal = m[m["threshold_mode"] == "calibrated"]
    seeds = sorted(set(cal.loc[cal.method == treatment, "seed"]) & set(cal.loc[cal.method == control, "seed"]))
    if not seeds or n_images <= 0:
        sec.blocks.append(Missing(f"runs of both `{control}` and `{treatment}`",
                                  "the qualitative panels compare them on the same seed."))
        return sec
    seed = seeds[0]
    group = test_groups(inp.get("manifest").df)[0]
    sub = cal[(cal.group == group) & (cal.seed == seed)]
    a = sub[sub.method == control].set_index("image_id")
    b = sub[sub.method == treatment].set_index("image_id")
    common = a.index.intersection(b.index)
    gain = (b.loc[common, "iou"] - a.loc[common, "iou"]).sort_values(ascending=False, kind="mergesort")
    pick = gain.index[np.unique(np.linspace(0, len(gain) - 1, min(n_images, len(gain))).round().astype(int))]
    mdf = inp.get("manifest").df
    rows_idx = np.array([int(np.flatnonzero(mdf["image_id"].to_numpy() == i)[0]) for i in pick])
    images = read_chunk_rows(inp.get("images")["image"], rows_idx)
    gts = read_chunk_rows(inp.get("reference")["mask"], rows_idx).astype(bool)
    preds = {}
    for method in (control, treatment):
        model, _ = load_student(inp.art / "checkpoints" / method / str(seed), device)
        tau = float(sub[sub.method == method]["tau"].iloc[0])
        preds[method] = mask_from_probs(predict_probs(model, images, device=device), tau)  # eq:inference-mask
    rows = []
    for j, iid in enumerate(pick):
        scores = {T.label(mm): f"IoU {r['iou']:.3f}  BF1 {r['bf1']:.3f}"
                  for mm, r in ((control, a.loc[iid]), (treatment, b.loc[iid]))}
        rows.append(F.qualitative_row(images[j], gts[j], {T.label(mm): preds[mm][j] for mm in (control, treatment)},
                                      scores, f"({chr(97 + j)}) {iid}"))
    fig = F.image_grid(rows)
    sec.blocks.append(Figure(
        "fig:qualitative-results", f"{T.label(control)} vs {T.label(treatment)} on {group}",
        f"Seed {seed}, validation-calibrated thresholds. Green: true positives, red: false positives, blue: false "
        f"negatives; yellow: ground-truth contour. Rows ordered from the largest Image IoU gain to the largest loss "
        f"of {T.label(treatment)}; metrics on full frames.", F.png_bytes(fig), FIGURES["qualitative"], F.svg_bytes(fig)))
    return sec


def gate_extremes(g: np.ndarray, n_images: int) -> np.ndarray:
    """Positions into ``g`` of the ``max(1, n_images // 2)`` lowest gates (lowest first) then as many
    highest (highest first), each image once; ties in the given order."""
    k = max(1, n_images // 2)
    order = np.argsort(np.asarray(g, float), kind="mergesort")
    low = order[:k]
    high = [i for i in order[::-1][:k] if i not in set(low)]
    return np.asarray([*low, *high], dtype=np.int64)


def pseudo_label_panels(inp: Inputs, n_images: int, device="cpu", methods: tuple[str, ...] = (BASELINE, PROPOSED)) -> list:
    """Without any mask: the students' masks beside the pseudo-labels they were trained on (the 50 %
    vote M) for the lowest- and the highest-gate training images (:func:`gate_extremes`), at each run's
    threshold (thresholds.parquet: the fixed tau).  The colours and the IoU compare a student with the
    pseudo-label, not with a true mask: agreement with the teacher, not accuracy."""
    miss = [inp.missing[n] for n in ("thresholds", "images", "consensus", "gates", "manifest") if n in inp.missing]
    if miss:
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
    preds, taus = {}, {}
    for method in present:
        model, _ = load_student(inp.art / "checkpoints" / method / str(seed), device)
        taus[method] = float(thr.loc[(thr["method"] == method) & (thr["seed"] == seed), "tau"].iloc[0])
        preds[method] = mask_from_probs(predict_probs(model, images, device=device), taus[method])  # eq:inference-mask
    rows = []
    for j, i in enumerate(rows_idx):
        scores = {T.label(m): f"IoU vs M {image_iou(preds[m][j], voted[j]):.2f}" for m in present}
        rows.append(F.qualitative_row(images[j], voted[j], {T.label(m): preds[m][j] for m in present}, scores,
                                      f"({chr(97 + j)}) g={g[pos[j]]:.2f} {ids[i]}",
                                      reference=("pseudo-label M", "(yellow contour)")))
    fig = F.image_grid(rows)
    n_low = max(1, n_images // 2)
    tau_words = ", ".join(f"{T.label(m)} tau = {taus[m]:g}" for m in present)
    return [Figure(
        "fig:student-vs-pseudo-labels", "Students beside their pseudo-labels (no masks: agreement, not accuracy)",
        f"Seed {seed}; the {min(n_low, len(pos))} training image(s) with the lowest reliability gate g first, then "
        f"the highest ({tau_words}: the fixed threshold).  Yellow contour: the pseudo-label M (the teacher's 50 % "
        "vote the students were trained on), not a true mask.  Green: student and M agree on foreground, red: "
        "student only, blue: M only; IoU vs M is their agreement.  A low-gate row shows where the pseudo-label "
        "is least trusted; only masks (`--val-masks`) say which of the two is right.",
        F.png_bytes(fig), FIGURES["student_vs_pseudo_labels"], F.svg_bytes(fig))]


def gate_distribution_blocks(inp: Inputs) -> list:
    """The reliability gate g of the training images (gates.parquet) as a histogram with one sentence of
    counts; shown where the teacher's scores need masks that are absent."""
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
            Figure("fig:gate-distribution", "Distribution of the reliability gate",
                   "Training images per gate bin (width 0.05); g = c-, v- and area-gate factors multiplied.  "
                   "Computed without masks.", F.png_bytes(img), FIGURES["gate_distribution"],
                   F.svg_bytes(img))]


def loss_figure(logs: pd.DataFrame) -> Figure:
    """The training loss per epoch (mean over seeds per method): what a run without validation masks
    has to show of its training."""
    series = []
    for method, part in logs.groupby("method", sort=False):
        mean = part.groupby("epoch")["loss"].mean()
        series.append({"x": mean.index.to_numpy(float), "y": mean.to_numpy(float), "label": T.label(method),
                       **F.method_style(method)})
    img = F.line_plot(series, "Training loss", "epoch (of the run's own schedule)", "loss")
    return Figure("fig:training-loss", "Training loss", "Training loss per epoch (mean over seeds per method; "
                  "Stage I and Stage II losses differ in their terms, so compare a method with itself).",
                  F.png_bytes(img), FIGURES["training_loss"], F.svg_bytes(img))


def pseudo_target_section(inp: Inputs, n_images: int) -> Section:
    """Paper Fig. pseudo-geometry for training images spread over the gate's range (highest g first)."""
    sec = Section("Pseudo-target construction")
    miss = inp.need("manifest", "images", "teacher", "consensus", "geometry", "gates")
    if miss:
        sec.blocks += miss
        return sec
    mdf = inp.get("manifest").df
    gates = inp.get("gates").df.set_index("image_id")
    train = mdf.index[mdf["split"] == "train"].to_numpy()
    if train.size == 0 or n_images <= 0:
        sec.blocks.append(Text("No training image to show."))
        return sec
    ids = mdf["image_id"].to_numpy()
    g = gates.reindex(ids[train])["g"].to_numpy(float)
    ranked = train[np.argsort(-np.nan_to_num(g, nan=-1), kind="mergesort")]
    pick = np.sort(ranked[np.unique(np.linspace(0, len(ranked) - 1, min(n_images, len(ranked))).round().astype(int))])
    teacher = inp.get("teacher")
    backend = str(teacher.attrs.get("backend", "unknown"))
    prompts = list(teacher.attrs.get("prompts", []))
    images = read_chunk_rows(inp.get("images")["image"], pick)
    tmasks = read_chunk_rows(teacher["masks"], pick)
    scores = read_chunk_rows(teacher["scores"], pick)
    agreement = read_chunk_rows(inp.get("consensus")["agreement"], pick)
    voted = read_chunk_rows(inp.get("consensus")["voted"], pick)
    sdf = read_chunk_rows(inp.get("geometry")["sdf"], pick)
    skel = read_chunk_rows(inp.get("geometry")["skeleton"], pick)
    rows = []
    for j, i in enumerate(pick):
        gr = gates.loc[ids[i]] if ids[i] in gates.index else None
        gate_text = ([f"c={gr['c']:.2f} v={gr['v']:.2f}", f"a={gr['a']:.3f} g={gr['g']:.2f}"]
                     if gr is not None else ["gate: n/a", ""])
        labels = [f"p{k + 1} s={scores[j, k]:.2f}" for k in range(tmasks.shape[1])]
        rows.append(F.pseudo_target_row(images[j], tmasks[j], labels, agreement[j], voted[j], sdf[j], skel[j],
                                        gate_text, str(ids[i])))
    fig = F.image_grid(rows)
    prompt_list = "; ".join(f"p{k + 1} = `{p}`" for k, p in enumerate(prompts))
    sim = " The prompt masks come from the teacher SIMULATOR, not SAM 3." if backend == "simulated" else ""
    sec.blocks.append(Figure(
        "fig:pseudo-geometry", "Multi-prompt pseudo-target construction",
        f"Training images (highest gate g first): the {tmasks.shape[1]} prompt masks with teacher scores s, the "
        f"agreement map A, the 50 % vote M, the normalised SDF D (red inside, blue outside) and the skeleton K; the "
        f"gate's factors c (agreement), v (valid-prompt ratio), a (pseudo area) and g.{sim} Prompts: {prompt_list}.",
        F.png_bytes(fig), FIGURES["pseudo_targets"], F.svg_bytes(fig)))
    return sec


def provenance_section(inp: Inputs) -> Section:
    rows = [[f"`{catalog.ARTIFACTS[n].path}`", a.meta.schema, a.meta.stage, a.fingerprint[:16]] for n, a in inp.found.items()]
    rows += [[f"`{catalog.ARTIFACTS[n].path}`", "--", "--",
              "not computed (no masks)" if inp.no_masks and n in MASK_INPUTS else "missing"] for n in inp.missing]
    return Section("Provenance", [Table("tab:provenance", "Input artifacts", ["Artifact", "Schema", "Stage",
                                                                             "Fingerprint"], rows)])


def build_report(art: str | Path, cfg: dict, profile: str = "", device="cpu",
                 environment: dict | None = None) -> tuple[Report, dict, Inputs]:
    """-> (report, plot tables {name: DataFrame}, opened inputs).  ``environment``: the report machine's
    record (:func:`pipeline.runtime.environment.collect`) for the Environment section (None: not recorded)."""
    inp = load_inputs(art, profile or None)
    plots: dict[str, pd.DataFrame] = {}
    n_qual = int(cfg.get("qualitative_images", 4))
    n_pseudo = int(cfg.get("pseudo_target_images", 3))
    with T.human_trained(inp.run_review):
        sections = build_sections(inp, plots, n_qual, n_pseudo, environment, device)
    title = "GeoDistill-Refine report" + (f" ({profile} profile)" if profile else "")
    return Report(title, sections), plots, inp


def build_sections(inp: Inputs, plots: dict, n_qual: int, n_pseudo: int, environment: dict | None,
                   device="cpu") -> list[Section]:
    """The report's sections in order (labels: :func:`build_report`'s :func:`pipeline.report.tables.human_trained`)."""
    return [
        glossary_section(),
        data_section(inp),
        results_section(inp),
        qualitative_section(inp, n_qual, device),
        threshold_section(inp, plots),
        diagnostics_section(inp, plots),
        teacher_section(inp),
        pseudo_target_section(inp, n_pseudo),
        ablation_section(inp),
        efficiency_section(inp),
        training_section(inp, plots),
        environment_section(environment, inp.runs),
        provenance_section(inp),
    ]
