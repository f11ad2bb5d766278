"""Training methods as data: one declarative table of which loss terms, gating, initialisation, epochs,
data filter and checkpoint-selection rule each ``--method`` uses, plus the pseudo-label filters.

The training loop (``pipeline.training.loop``) reads a :class:`Method` and has no per-method branches of
its own.  The table is also the one source of what each method is in the study -- its label, role,
ablation tables, the reference point of its gains and its place in the tables (:data:`ROLES`,
:data:`PROPOSED`, :data:`BASELINE`, :data:`CONTINUATION`, :data:`STAGE_ONE`): the profiles, the evaluation
and the report derive their lists from it, so adding a method is one row (docs/pipeline.md).  This module is pure Python/numpy (no torch import), so the train stage can decide quickly
whether a (method, seed) is in the active profile.

Methods (paper section in brackets)

=====================  =====  =======  ======================  ===================================
method                 stage  init     objective               data / selection
=====================  =====  =======  ======================  ===================================
plain                  1      scratch  L_raw                   all pseudo-masks; best val IoU
confidence_filtered    1      scratch  L_raw                   pass confidence criterion; best val
afs_control            1      scratch  L_raw on AFS masks      base prompt, vflip-fused, s >= 0.6
geodistill             2      stage1   L_refine (gated)        all; train.stage2_select (last)
gabi                   2      scratch  L_raw + dist + bound.   all; best val IoU; gabi.epochs (30)
full_scratch_10        2      scratch  L_refine (gated)        10 = epochs_stage2 epochs; best val
full_scratch_30        2      scratch  L_refine (gated)        30 = epochs_stage1 + epochs_stage2
sdf_scratch            2      scratch  L_raw + gated SDF       epochs_stage2; best val
sdf_gated              2      stage1   L_raw + gated SDF       train.stage2_select
sdf_skel_gated         2      stage1   + skeleton              train.stage2_select
sdf_area_gated         2      stage1   + area                  train.stage2_select
no_gate                2      stage1   L_refine with g = 1     train.stage2_select
geodistill_adaptive    2      stage1   adaptive (see below)    best val IoU (epoch 0 eligible if r<0.5)
continuation           2      stage1   L_raw only              all; train.stage2_select (last)
supervised_ceiling     1      scratch  L_raw on REFERENCE      train split's manual masks; best val IoU
=====================  =====  =======  ======================  ===================================

Controls the paper lacks (issue 17):

* ``continuation`` -- the budget-matched continuation: GeoDistill-Refine's warm start, Stage-II
  schedule, epochs (``epochs_stage2``, ``lr_stage2``) and selection (``train.stage2_select``) with
  L_raw only (no geometry term, no geometry heads).  GeoDistill-Refine minus this control is the
  geometry effect at a matched training budget; this control minus Plain is the effect of the ten
  extra epochs alone.
* ``supervised_ceiling`` -- NOT annotation-free: the Plain Student's recipe trained on the training
  split's REFERENCE (manual) masks.  It is the one method whose loss sees reference masks (its
  targets come only from :func:`pipeline.training.supervised.ceiling_training_data`); it runs only with
  ``protocol.supervised_ceiling: true``, is labelled "(uses reference masks; not annotation-free)"
  in every table and is never among the annotation-free comparisons (:attr:`Method.annotation_free`).

Decisions where the paper is silent (all documented here and in the params comments):

* Methods trained from random initialisation (Stage I family, ``gabi``, ``*_scratch*``) use the
  Stage-I learning rate ``train.lr_stage1`` and validation-IoU checkpoint selection, like Stage I.
  Warm-started Stage-II methods use ``train.lr_stage2`` and ``train.stage2_select`` (paper: last).
* ``sdf_scratch`` is L_raw + gated SDF from scratch (the warm-start table's "SDF only" row; the gate
  is kept so that it differs from ``sdf_gated`` only in initialisation).
* The quality-adaptive mode (paper "External Validation") computes the pass ratio r of the
  *training* pseudo-labels under the confidence criterion (``train.confidence``):
  r >= ``train.adaptive.ratio_boundary`` (0.5) -> mode ``anchored``: L_refine + w * L_anchor;
  r < 0.5 -> mode ``geometry_only``: the Stage-II pseudo-mask region loss (L_raw) is disabled, the
  geometry terms remain -- and the anchor only with ``train.adaptive.anchor_geometry_only: true``
  (default false: the paper reads as no anchoring in this mode) --, and Stage-II epoch 0 (the Stage-I checkpoint) is a
  selection candidate.  L_anchor is BCE to the frozen Stage-I probabilities
  (:func:`pipeline.losses.anchor_loss`), weight ``train.adaptive.anchor_weight`` (0.1: "weak" --
  an order below the region loss).  Both modes select by validation IoU.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import numpy as np

from pipeline.runtime.errors import InputError

TERMS = ("region", "anchor", "sdf", "dist", "skel", "area", "boundary")

#: What a method is in the study (:attr:`Method.role`); the report, the profiles and the evaluation read
#: it from the table, never from a list of names of their own.
ROLES = {
    "main": "a method of the paper's main comparison (results tables; the paper protocol's runs)",
    "proposed": "the method the paper proposes: a row of the main comparison and the treatment of its headline "
                "comparisons (qualitative panels, the fixed-tau findings, the stability benchmark's gains)",
    "external": "a row of the main comparison outside the paper protocol's runs (the quality-adaptive mode)",
    "control": "a control the paper lacks, run at the main methods' seeds",
    "ablation": "a mechanistic ablation: a row of its ablation tables only (one seed in the protocol)",
}
#: The paper's ablation tables (:attr:`Method.ablation_tables`): a method's rows in them, in table order.
ABLATION_TABLES = {"warm_start": "tab:warm-start-ablation", "component": "tab:component-ablation"}
#: Which methods a reference point's gains cover (:attr:`Method.reference_for`; :func:`gain_treatments`).
GAIN_SCOPES = {
    "annotation_free": "every annotation-free method (the paper's comparison)",
    "warm_started": "the warm-started Stage-II methods (init stage1): its training budget matches theirs",
}


@dataclasses.dataclass(frozen=True)
class Method:
    """Declarative description of one training method.

    ``epochs``: train-param keys whose values are summed ("gabi.epochs" reads ``train.gabi.epochs``).
    ``lr``: train-param key of the initial learning rate.  ``init``: ``scratch`` or ``stage1`` (warm
    start of encoder, decoder and mask head from ``--init``).  ``data``: ``all`` | ``confidence`` |
    ``afs`` (which training pseudo-labels, see the filters below).  ``terms``: loss terms in the
    objective (``region`` = L_raw on the pseudo-mask, ``sdf`` = eq:sdf-loss, ``skel`` =
    eq:skeleton-loss, ``area`` = eq:area-loss, ``dist`` = ungated distance regression, ``boundary`` =
    boundary-weighted BCE, ``anchor`` = weak anchoring to the frozen Stage-I prediction).
    ``gate``: ``g`` (gates.parquet) or ``one`` (g = 1).  ``select``: ``best_val`` | ``stage2``
    (``train.stage2_select``).  ``adaptive``: terms and selection resolved from the pass ratio r.
    ``uses``: train sub-sections the method reads (they enter its fingerprint).  ``data="reference"``
    (the supervised ceiling only, see :data:`SUPERVISED_CEILING`): the region target is the manual mask.
    ``color`` (hex RGB), ``dash`` (a matplotlib line style: solid, dashed, dashdot, dotted) and ``symbol``
    (a matplotlib marker): the method's series in every figure (pipeline.report.figures); no two rows
    share a colour or a symbol, ablations are dashed.

    What the method is in the study (:func:`check_method_table` holds these rules): ``label``, its name in
    every table and figure; ``role``, one of :data:`ROLES`; ``ablation_tables``, the ablation tables
    (:data:`ABLATION_TABLES`) it is a row of; ``reference_for``, the methods whose gains are measured
    against it (:data:`GAIN_SCOPES`; empty: none); ``table_order``, its place in every table of methods
    (smaller first; unique).
    """

    name: str
    stage: int
    init: str
    epochs: tuple[str, ...]
    lr: str
    data: str = "all"
    terms: tuple[str, ...] = ("region",)
    gate: str = "g"
    select: str = "best_val"
    adaptive: bool = False
    uses: tuple[str, ...] = ()
    description: str = ""
    color: str = "#5a5a5a"
    dash: str = "solid"
    symbol: str = "o"
    label: str = ""
    role: str = "main"
    ablation_tables: tuple[str, ...] = ()
    reference_for: str = ""
    table_order: int = 0

    @property
    def annotation_free(self) -> bool:
        """False only for the supervised ceiling: its loss sees reference (manual) masks."""
        return self.data != "reference"

    @property
    def geometry_heads(self) -> bool:
        """Whether the model needs the SDF/skeleton heads (any SDF, distance or skeleton term)."""
        return any(t in self.terms for t in ("sdf", "dist", "skel"))

    @property
    def needs_geometry(self) -> bool:
        """Reads geometry.zarr (SDF/skeleton targets)."""
        return any(t in self.terms for t in ("sdf", "dist", "skel", "boundary"))

    @property
    def needs_gates(self) -> bool:
        """Reads gates.parquet: g_i for the gated terms, a_i for the area term, c_i/n_valid for the
        confidence criterion (confidence filter, adaptive mode)."""
        return bool({"sdf", "skel", "area"} & set(self.terms)) or self.data == "confidence" or self.adaptive


_FULL = ("region", "sdf", "skel", "area")

METHODS: dict[str, Method] = {m.name: m for m in [
    Method("plain", 1, "scratch", ("epochs_stage1",), "lr_stage1",
           description="Stage I only: L_raw on all voted pseudo-masks",
           label="Plain Student", reference_for="annotation_free", ablation_tables=("warm_start",),
           table_order=10, color="#1f77b4", dash="solid", symbol="o"),
    Method("confidence_filtered", 1, "scratch", ("epochs_stage1",), "lr_stage1", data="confidence",
           uses=("confidence",),
           description="plain student on pseudo-labels passing the confidence criterion",
           label="Confidence-Filtered Student", table_order=20,
           color="#2ca02c", dash="solid", symbol="v"),
    Method("afs_control", 1, "scratch", ("epochs_stage1",), "lr_stage1", data="afs", uses=("afs",),
           description="annotation-free-style control: base prompt, image+vflip fused, score filter",
           label="Annotation-Free-style Control", table_order=30,
           color="#9467bd", dash="solid", symbol="^"),
    Method("geodistill", 2, "stage1", ("epochs_stage2",), "lr_stage2", terms=_FULL, select="stage2",
           description="Stage I -> gated SDF + skeleton + area refinement (eq:refine-loss)",
           label="GeoDistill-Refine", role="proposed", ablation_tables=("warm_start", "component"),
           table_order=120, color="#d62728", dash="solid", symbol="D"),
    Method("gabi", 2, "scratch", ("gabi.epochs",), "lr_stage1", terms=("region", "dist", "boundary"),
           uses=("gabi",),
           description="GABI-inspired: joint from scratch, ungated distance regression + boundary BCE",
           label="GABI-inspired Pseudo-Geometry", table_order=40,
           color="#8c564b", dash="solid", symbol="P"),
    Method("full_scratch_10", 2, "scratch", ("epochs_stage2",), "lr_stage1", terms=_FULL,
           description="ablation: full gated geometry from scratch, 10 epochs",
           label="Full geometry, from scratch (10)", role="ablation", ablation_tables=("warm_start",),
           table_order=50, color="#bcbd22", dash="dashed", symbol="<"),
    Method("full_scratch_30", 2, "scratch", ("epochs_stage1", "epochs_stage2"), "lr_stage1", terms=_FULL,
           description="ablation: full gated geometry from scratch, 30 epochs",
           label="Full geometry, from scratch (30)", role="ablation", ablation_tables=("warm_start",),
           table_order=60, color="#17becf", dash="dashed", symbol=">"),
    Method("sdf_scratch", 2, "scratch", ("epochs_stage2",), "lr_stage1", terms=("region", "sdf"),
           description="ablation: L_raw + gated SDF from scratch",
           label="SDF only, from scratch", role="ablation", ablation_tables=("warm_start",), table_order=70,
           color="#000080", dash="dashed", symbol="x"),
    Method("sdf_gated", 2, "stage1", ("epochs_stage2",), "lr_stage2", terms=("region", "sdf"),
           select="stage2", description="ablation: Stage I -> gated SDF only",
           label="Stage I -> gated SDF", role="ablation", ablation_tables=("warm_start", "component"),
           table_order=80, color="#008080", dash="dashed", symbol="+"),
    Method("sdf_skel_gated", 2, "stage1", ("epochs_stage2",), "lr_stage2", terms=("region", "sdf", "skel"),
           select="stage2", description="ablation: Stage I -> gated SDF + skeleton",
           label="Gated SDF + skeleton", role="ablation", ablation_tables=("component",), table_order=90,
           color="#800000", dash="dashed", symbol="*"),
    Method("sdf_area_gated", 2, "stage1", ("epochs_stage2",), "lr_stage2", terms=("region", "sdf", "area"),
           select="stage2", description="ablation: Stage I -> gated SDF + area",
           label="Gated SDF + area", role="ablation", ablation_tables=("component",), table_order=100,
           color="#f032e6", dash="dashed", symbol="h"),
    Method("no_gate", 2, "stage1", ("epochs_stage2",), "lr_stage2", terms=_FULL, gate="one",
           select="stage2", description="ablation: full refinement with g = 1",
           label="SDF + skeleton + area, no gate", role="ablation", ablation_tables=("component",),
           table_order=110, color="#6464ff", dash="dashed", symbol="X"),
    Method("geodistill_adaptive", 2, "stage1", ("epochs_stage2",), "lr_stage2",
           terms=("region", "anchor", "sdf", "skel", "area"), adaptive=True,
           uses=("confidence", "adaptive"),
           description="quality-adaptive external mode (switch on the pass ratio r)",
           label="GeoDistill-Refine (quality-adaptive)", role="external", table_order=130,
           color="#e377c2", dash="solid", symbol="d"),
    Method("continuation", 2, "stage1", ("epochs_stage2",), "lr_stage2", select="stage2",
           description="control: Stage I -> Stage II's schedule, epochs and selection with L_raw only "
                       "(budget-matched, no geometry)",
           label="Budget-matched continuation (Stage II, L_raw only)", role="control",
           reference_for="warm_started", table_order=140,
           color="#ff7f0e", dash="dashdot", symbol="s"),
    Method("supervised_ceiling", 1, "scratch", ("epochs_stage1",), "lr_stage1", data="reference",
           description="NOT annotation-free: the Plain Student's recipe on the training split's REFERENCE masks",
           label="Supervised ceiling (uses reference masks; not annotation-free)", role="control",
           table_order=150, color="#000000", dash="dotted", symbol="p"),
]}

#: The one method whose loss sees reference (manual) masks.  Behind ``protocol.supervised_ceiling``.
SUPERVISED_CEILING = "supervised_ceiling"


#: What every table appends to the label of a run trained with human-corrected masks in its loss
#: (``review.mode: replace`` with ``review.human_targets: true``; pipeline/review/apply.py): like the
#: supervised ceiling, such a run is NOT annotation-free, whatever its method.
HUMAN_TARGETS_LABEL = "(trained on human corrections; not annotation-free)"


def replaces_targets(review: Mapping[str, Any] | None) -> bool:
    """Whether the ``review`` params section puts human-corrected masks into the loss (replace mode)."""
    return bool(review and review.get("corrections") and review.get("mode") == "replace")


def run_annotation_free(method: Method, review: Mapping[str, Any] | None = None) -> bool:
    """Whether a run of ``method`` under the ``review`` params section is annotation-free: the method is
    (:attr:`Method.annotation_free`) and no human-corrected mask replaces a target (:func:`replaces_targets`)."""
    return method.annotation_free and not replaces_targets(review)


def run_label(method: Method, review: Mapping[str, Any] | None = None) -> str:
    """The method's label in a table, with :data:`HUMAN_TARGETS_LABEL` when the run trained on corrections."""
    return method.label if run_annotation_free(method, review) or not method.annotation_free \
        else f"{method.label} {HUMAN_TARGETS_LABEL}"


def check_reference_boundary(methods: Mapping[str, Method]) -> None:
    """The annotation-free boundary of the method table: only :data:`SUPERVISED_CEILING` may train on
    reference masks (``data="reference"``); ValueError naming any other method that asks for them."""
    bad = [m.name for m in methods.values() if not m.annotation_free and m.name != SUPERVISED_CEILING]
    if bad:
        raise ValueError(f"methods {bad} ask for reference-mask targets; only {SUPERVISED_CEILING!r} may")


def check_method_table(methods: Mapping[str, Method]) -> None:
    """The study facts of the table hold together (ValueError naming the method otherwise): a label, a
    role of :data:`ROLES`, ablation tables of :data:`ABLATION_TABLES` (at least one for an ablation), a
    gain scope of :data:`GAIN_SCOPES` or none, unique labels and table orders; and exactly one proposed
    method, one reference point per gain scope and one Stage-I method (:func:`the_method`)."""
    for m in methods.values():
        if not m.label or m.role not in ROLES or not set(m.ablation_tables) <= set(ABLATION_TABLES) \
                or (m.role == "ablation" and not m.ablation_tables) or m.reference_for not in ("", *GAIN_SCOPES):
            raise ValueError(f"method {m.name!r}: label, role, ablation_tables or reference_for not as "
                             f"pipeline.methods.Method documents")
    for field in ("label", "table_order"):
        values = [getattr(m, field) for m in methods.values()]
        if len(set(values)) != len(values):
            raise ValueError(f"two methods share a {field}")
    check_reference_boundary(methods)


check_method_table(METHODS)


def the_method(what: str, test, methods: Mapping[str, Method] = METHODS) -> str:
    """The name of the one method of ``methods`` for which ``test(method)`` holds; ValueError naming
    ``what`` when none or several do (the table must say it once)."""
    found = [m.name for m in methods.values() if test(m)]
    if len(found) != 1:
        raise ValueError(f"the method table must have exactly one {what}; it has {found}")
    return found[0]


#: The method the paper proposes (GeoDistill-Refine): the treatment of the headline comparisons.
PROPOSED = the_method("proposed method", lambda m: m.role == "proposed")
#: The reference point of every annotation-free method's gain (Plain Student: the paper's comparison).
BASELINE = the_method("reference point of every gain", lambda m: m.reference_for == "annotation_free")
#: The budget-matched continuation: the reference point of the warm-started methods' gains (the
#: geometry effect at a matched training budget).
CONTINUATION = the_method("budget-matched control", lambda m: m.reference_for == "warm_started")
#: Stage I of GeoDistill-Refine: L_raw from scratch on every voted pseudo-mask.  Its checkpoint is where
#: every warm-started (``init="stage1"``) method starts, at the same seed.
STAGE_ONE = the_method("Stage-I method", lambda m: m.stage == 1 and m.init == "scratch" and m.data == "all"
                       and m.terms == ("region",))
#: Reference points of a gain, in table order (:func:`gain_treatments`).
GAIN_CONTROLS = tuple(n for n, m in METHODS.items() if m.reference_for)


def methods_with_role(*roles: str) -> list[str]:
    """The methods whose :attr:`Method.role` is one of ``roles``, in the method table's order."""
    return [n for n, m in METHODS.items() if m.role in roles]


def in_table_order(names) -> list[str]:
    """``names`` (distinct) by :attr:`Method.table_order`; names not in the table keep their order, last."""
    names = list(dict.fromkeys(names))
    known = sorted((n for n in names if n in METHODS), key=lambda n: METHODS[n].table_order)
    return known + [n for n in names if n not in METHODS]


def ablation_table_rows(table: str) -> list[str]:
    """The rows of ablation table ``table`` (a key of :data:`ABLATION_TABLES`), in table order."""
    return in_table_order(n for n, m in METHODS.items() if table in m.ablation_tables)


def method_label(name: str) -> str:
    """The display label of method ``name`` (:attr:`Method.label`); a name not in the table as is."""
    return METHODS[name].label if name in METHODS else name


def annotation_free_methods(names) -> list[str]:
    """``names`` without the methods that train on reference masks (unknown names are kept)."""
    return [n for n in names if n not in METHODS or METHODS[n].annotation_free]


def gain_treatments(control: str, names) -> list[str]:
    """The methods of ``names`` compared with ``control`` (a reference point: :data:`GAIN_CONTROLS`), by
    its :attr:`Method.reference_for` (:data:`GAIN_SCOPES`): every annotation-free method against
    :data:`BASELINE`; the warm-started Stage-II methods against :data:`CONTINUATION` (its budget matches
    theirs).  Never the supervised ceiling, never the control itself."""
    free = [n for n in annotation_free_methods(names) if n != control]
    if control in METHODS and METHODS[control].reference_for == "warm_started":
        return [n for n in free if n in METHODS and METHODS[n].init == "stage1"]
    return free


def get_method(name: str) -> Method:
    """The :class:`Method` called ``name``; InputError listing the valid names otherwise."""
    try:
        return METHODS[name]
    except KeyError:
        raise InputError(f"--method {name!r}: expected one of {', '.join(METHODS)}") from None


def _get(cfg: Mapping[str, Any], dotted: str, prefix: str = "train.") -> Any:
    """``cfg``'s value at ``dotted``; InputError naming ``prefix + dotted`` when absent (``cfg``: the
    train section, or with ``prefix=""`` the whole params)."""
    cur: Any = cfg
    for k in dotted.split("."):
        if not isinstance(cur, Mapping) or k not in cur:
            raise InputError(f"params: {prefix}{dotted} missing")
        cur = cur[k]
    return cur


def method_epochs(method: Method, cfg: Mapping[str, Any]) -> int:
    """Number of epochs: the sum of the train params named in ``method.epochs``."""
    total = 0
    for key in method.epochs:
        v = _get(cfg, key)
        if not isinstance(v, int) or isinstance(v, bool) or v < 0:
            raise InputError(f"params: train.{key}={v!r} must be a non-negative integer")
        total += v
    if total < 1:
        raise InputError(f"params: {' + '.join('train.' + k for k in method.epochs)} must be >= 1")
    return total


def method_lr(method: Method, cfg: Mapping[str, Any]) -> float:
    """The method's peak learning rate: ``train.<method.lr>``, times ``train.lr_scale`` for Stage I's rate."""
    v = _get(cfg, method.lr)
    if not isinstance(v, (int, float)) or isinstance(v, bool) or v <= 0:
        raise InputError(f"params: train.{method.lr}={v!r} must be a positive number")
    return float(v) * (float(cfg.get("lr_scale") or 1.0) if method.lr == "lr_stage1" else 1.0)


#: train params every method reads (model, optimiser, L_raw, validation selection, numerics).  The
#: execution knobs that change numerics (``precision``, ``num_threads``) are among them: DVC reruns
#: training when one changes and the checkpoint fingerprint (= the resume-state key) moves with it.
COMMON_KEYS = ("channels", "norm", "bn_momentum", "precise_bn", "batch_size", "weight_decay", "schedule",
               "dice_weight", "pos_weight_max", "loss_eps", "recipe", "precision", "warmup_epochs", "average_last",
               "channels_last", "augment_hflip", "num_threads", "val_bf1_tolerance",
               "decay_fraction", "augment", "augmentation", "ema_decay", "soft_targets", "until", "step_budget",
               "time_budget", "plateau_gain", "plateau_min_epochs", "holdout_fraction", "lr_scale")
#: extra train params per loss term (eq:refine-loss and the baselines' terms).
TERM_KEYS = {
    "region": (),
    "sdf": ("sdf_band", "sdf_base_weight", "lambda_sdf"),
    "skel": ("lambda_skel",),
    "area": ("area_eps", "lambda_area"),
    "dist": ("gabi.lambda_dist",),
    "boundary": ("sdf_band", "gabi.lambda_boundary"),
    "anchor": ("adaptive.anchor_weight",),
}


#: the one key outside ``train.*`` every run reads: the tau of the validation masks in checkpoint
#: selection (eq:inference-mask), the project's one fixed tau (the report's fixed-tau comparisons and
#: the calibrate stage's fallback read the same key)
SELECTION_TAU_KEY = "calibrate.fixed_tau"


def param_keys(method: Method) -> tuple[str, ...]:
    """The dotted params keys a method's run reads -- its ``train.*`` keys and :data:`SELECTION_TAU_KEY`:
    DVC tracks exactly these for its stage and they form the params part of its checkpoint
    fingerprint, so editing ``train.lr_stage2`` reruns the warm-started Stage-II methods only."""
    keys = list(COMMON_KEYS) + list(method.epochs) + [method.lr]
    for t in method.terms:
        keys += TERM_KEYS[t]
    if method.select == "stage2":
        keys.append("stage2_select")
    keys += list(method.uses)
    keys = list(dict.fromkeys(keys))
    # a whole sub-section (``uses``) covers its own keys
    keys = [k for k in keys if not any(k.startswith(u + ".") for u in method.uses)]
    return tuple(f"train.{k}" for k in keys) + (SELECTION_TAU_KEY,)


def fingerprint_params(method: Method, params: Mapping[str, Any]) -> dict:
    """``{dotted key: value}`` of :func:`param_keys` in validated ``params`` (the params part of a
    checkpoint's fingerprint)."""
    return {k: _get(params, k, prefix="") for k in param_keys(method)}


def uses_confidence(method: Method) -> bool:
    """Whether the method evaluates the confidence criterion (the filter, or the adaptive pass ratio r)."""
    return method.data == "confidence" or method.adaptive


def input_artifacts(method: Method, criterion: str | None = None) -> tuple[str, ...]:
    """Catalogue names of the artifacts a method's run reads; ``reference`` serves validation selection only.

    manifest and images always; gates for the gated/area terms and the confidence criterion; teacher
    for the AFS control and the ``mean_score`` confidence criterion; consensus (``voted``) unless AFS
    or the supervised ceiling (whose targets are reference masks); geometry for SDF/skeleton/distance/
    boundary terms.  ``criterion`` is ``train.confidence.criterion``;
    None means either (the superset dvc.yaml tracks, since the criterion is a param).
    """
    names = ["manifest", "images", "reference"]
    if method.needs_gates:
        names.append("gates")
    if method.data == "afs" or (uses_confidence(method) and criterion in (None, "mean_score")):
        names.append("teacher")
    if method.data not in ("afs", "reference"):
        names.append("consensus")
    if method.needs_geometry:
        names.append("geometry")
    return tuple(names)


# --------------------------------------------------------------------------------------------------
# Pseudo-label filters (teacher outputs only -- never reference masks)
# --------------------------------------------------------------------------------------------------
def mean_valid_score(scores: np.ndarray) -> np.ndarray:
    """Mean teacher score over the valid prompts (s_ik > 0, eq:agreement-map's V_i) per image; 0 if none.

    ``scores`` float [N,K] -> float64 [N].
    """
    s = np.asarray(scores, dtype=np.float64)
    valid = s > 0
    n = valid.sum(1)
    return np.where(n > 0, (s * valid).sum(1) / np.maximum(n, 1), 0.0)


def confidence_pass(agreement: np.ndarray, n_valid: np.ndarray, mean_score: np.ndarray | None,
                    criterion: str, threshold: float, min_valid: int) -> np.ndarray:
    """Confidence criterion of the confidence-filtered student (decision; the paper does not state it).

    An image passes when at least ``min_valid`` prompts are valid and its confidence is
    ``>= threshold``, where the confidence is the foreground agreement c_i (eq:foreground-agreement,
    ``criterion="agreement"``) or the mean valid-prompt score (``criterion="mean_score"``).
    Both come from teacher outputs only.  Returns bool [N].
    """
    n_valid = np.asarray(n_valid)
    if criterion == "agreement":
        conf = np.asarray(agreement, dtype=np.float64)
    elif criterion == "mean_score":
        if mean_score is None:
            raise ValueError("criterion 'mean_score' needs mean_score")
        conf = np.asarray(mean_score, dtype=np.float64)
    else:
        raise InputError(f"params: train.confidence.criterion={criterion!r}: expected agreement or mean_score")
    return (n_valid >= int(min_valid)) & (conf >= float(threshold))


def pass_ratio(passed: np.ndarray) -> float:
    """Fraction r of images passing a filter (0 for an empty set)."""
    passed = np.asarray(passed, dtype=bool)
    return float(passed.mean()) if passed.size else 0.0


def adaptive_mode(r: float, boundary: float = 0.5) -> str:
    """Quality-adaptive external mode from the training pass ratio r (paper: External Validation):
    ``"anchored"`` when r >= boundary, else ``"geometry_only"``."""
    return "anchored" if float(r) >= float(boundary) else "geometry_only"


def afs_fuse(mask_image: np.ndarray, mask_vflip: np.ndarray, fusion: str = "intersection") -> np.ndarray:
    """Fuse the base-prompt mask on the image with the one on its vertical flip (flipped back) by their
    agreement: ``intersection`` keeps pixels both views call foreground, ``union`` either."""
    a = np.asarray(mask_image, dtype=bool)
    b = np.asarray(mask_vflip, dtype=bool)
    if fusion == "intersection":
        return a & b
    if fusion == "union":
        return a | b
    raise InputError(f"params: train.afs.fusion={fusion!r}: expected intersection or union")


def afs_keep(score: np.ndarray, threshold: float = 0.60) -> np.ndarray:
    """Images kept by the annotation-free-style control: base-prompt teacher score >= threshold
    (images whose score is below it are dropped)."""
    return np.asarray(score, dtype=np.float64) >= float(threshold)


@dataclasses.dataclass(frozen=True)
class Plan:
    """A method resolved for one run: loss weights of each term, selection rule and candidates.

    ``weights[t]`` multiplies term ``t`` in the objective (absent = not computed).  ``select``:
    ``best_val`` or ``last``.  ``epoch0_eligible``: the initial (warm-start) model is a candidate.
    """

    weights: dict
    select: str
    epoch0_eligible: bool = False
    mode: str = ""


def resolve_plan(method: Method, cfg: Mapping[str, Any], pass_ratio_r: float | None = None) -> Plan:
    """Turn the declarative method and the train params into concrete term weights and selection.

    Region terms weigh 1 (eq:raw-loss inside eq:refine-loss); SDF/skeleton/area use
    ``lambda_sdf/skel/area`` (eq:refine-loss); the GABI terms ``gabi.lambda_dist/lambda_boundary``;
    the anchor ``adaptive.anchor_weight``.  The adaptive method needs ``pass_ratio_r``.
    """
    lam = {"region": 1.0, "sdf": _get(cfg, "lambda_sdf"), "skel": _get(cfg, "lambda_skel"),
           "area": _get(cfg, "lambda_area")}
    if "dist" in method.terms:
        lam["dist"] = _get(cfg, "gabi.lambda_dist")
    if "boundary" in method.terms:
        lam["boundary"] = _get(cfg, "gabi.lambda_boundary")
    if "anchor" in method.terms:
        lam["anchor"] = _get(cfg, "adaptive.anchor_weight")
    weights = {t: float(lam[t]) for t in method.terms}
    if method.select == "stage2":
        sel = _get(cfg, "stage2_select")
        if sel not in ("last", "best_val"):
            raise InputError(f"params: train.stage2_select={sel!r}: expected last or best_val")
    else:
        sel = method.select
    if not method.adaptive:
        return Plan(weights=weights, select=sel)
    if pass_ratio_r is None:
        raise ValueError("the adaptive method needs the pass ratio r")
    mode = adaptive_mode(pass_ratio_r, _get(cfg, "adaptive.ratio_boundary"))
    if mode == "geometry_only":
        weights.pop("region")
        if not _get(cfg, "adaptive.anchor_geometry_only"):
            weights.pop("anchor", None)  # the paper reads as no anchoring in this mode (decision; a param)
        return Plan(weights=weights, select="best_val", epoch0_eligible=True, mode=mode)
    return Plan(weights=weights, select="best_val", epoch0_eligible=False, mode=mode)
