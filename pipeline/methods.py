"""Training methods as data, and the recipe parts, each declared once.

The loss terms, gating, initialisation, epochs, data filter and checkpoint selection of each ``--method`` and
what it is in the study (docs/pipeline.md, "Methods"); the data filters themselves are
:mod:`pipeline.training.filters`.  The training loop has no per-method branch.  Also the recipe parts, each
declared once (:class:`RecipePart`, :data:`PARTS`), and the recipes that bundle them (:data:`RECIPES`).  This
module imports no torch and no pydantic.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Literal, Mapping

from pipeline.runtime.errors import InputError

__all__ = [
    # the method table
    "TERMS", "ROLES", "ABLATION_TABLES", "GAIN_SCOPES", "Method", "METHODS", "SUPERVISED_CEILING",
    "HUMAN_TARGETS_LABEL", "run_annotation_free", "run_label", "check_reference_boundary", "check_method_table",
    "the_method", "PROPOSED", "BASELINE", "CONTINUATION", "STAGE_ONE", "GAIN_CONTROLS", "methods_with_role",
    "in_table_order", "ablation_table_rows",
    # the recipe parts
    "HOMES", "FIRST", "RecipePart", "PARTS", "interleave", "part", "parts_of", "off_value", "recipe_parts",
    "recipe_values", "with_part_fields", "RECIPES", "DEPARTURES", "departures",
    # a method in a run
    "method_label", "annotation_free_methods", "gain_treatments", "get_method", "method_epochs", "method_lr",
    "COMMON_KEYS", "TERM_KEYS", "SELECTION_TAU_KEY", "param_keys", "fingerprint_params", "uses_confidence",
    "input_artifacts", "adaptive_mode", "Plan", "resolve_plan",
]

#: the loss terms a method may use (:attr:`Method.terms`; their params: :data:`TERM_KEYS`)
TERMS = ("region", "anchor", "sdf", "dist", "skel", "area", "boundary")
#: what a method is in the study (:attr:`Method.role`)
ROLES = ("main", "proposed", "external", "control", "ablation")
#: the paper's ablation tables (:attr:`Method.ablation_tables`)
ABLATION_TABLES = {"warm_start": "tab:warm-start-ablation", "component": "tab:component-ablation"}
#: whose gains a reference point measures (:attr:`Method.reference_for`, :func:`gain_treatments`)
GAIN_SCOPES = ("annotation_free", "warm_started")


@dataclasses.dataclass(frozen=True)
class Method:
    """One training method: a row of the method table (:data:`METHODS`).

    ``label``, ``role``, ``ablation_tables``, ``reference_for`` and ``table_order`` place it in the study
    (:func:`check_method_table`); ``color``, ``dash`` and ``symbol`` draw it in every figure.

    Attributes
    ----------
    name : str
        The ``--method`` name.
    stage : int
        The training stage it counts as: 1 or 2.
    init : str
        ``scratch`` | ``stage1`` (warm start from ``--init``, the Stage-I checkpoint).
    epochs : tuple of str
        Train keys whose values are summed into its epochs ("gabi.epochs" = ``train.gabi.epochs``).
    lr : str
        The train key of its peak learning rate.
    data : str
        Its training images and targets: ``all`` | ``confidence`` | ``afs`` | ``reference`` (the supervised
        ceiling's manual masks).
    terms : tuple of str
        Its loss terms, of :data:`TERMS`.
    gate : str
        ``g`` (the reliability gate, eq:reliability-gate) | ``one`` (g = 1).
    select : str
        Its checkpoint selection: ``best_val`` | ``stage2`` (``train.stage2_select`` decides).
    adaptive : bool
        The quality-adaptive mode switch on the pass ratio r (:func:`adaptive_mode`).
    uses : tuple of str
        Train sub-sections it reads (``confidence``, ``afs``, ``gabi``, ``adaptive``).
    description : str
        One line on what it is.
    color : str
        Its colour in every figure.
    dash : str
        Its line style in every figure.
    symbol : str
        Its marker in every figure.
    label : str
        Its name in the report's tables and figures (unique).
    role : str
        What it is in the study, of :data:`ROLES`.
    ablation_tables : tuple of str
        The paper's ablation tables it is a row of, of :data:`ABLATION_TABLES` (an ablation has one at least).
    reference_for : str
        "" or a scope of :data:`GAIN_SCOPES`: whose gains it is the reference point of.
    table_order : int
        Its row in the report's tables (unique; :func:`in_table_order`).
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
        """Whether the model needs the SDF/skeleton heads."""
        return any(t in self.terms for t in ("sdf", "dist", "skel"))

    @property
    def needs_geometry(self) -> bool:
        """Reads geometry.zarr (SDF/skeleton targets)."""
        return any(t in self.terms for t in ("sdf", "dist", "skel", "boundary"))

    @property
    def needs_gates(self) -> bool:
        """Reads gates.parquet (the gated and area terms, the confidence criterion)."""
        return bool({"sdf", "skel", "area"} & set(self.terms)) or self.data == "confidence" or self.adaptive


_FULL = ("region", "sdf", "skel", "area")

METHODS: dict[str, Method] = {m.name: m for m in [
    Method("plain", 1, "scratch", ("epochs_stage1",), "lr_stage1",
           description="Stage I only: L_raw on all voted pseudo-masks", label="Plain Student",
           reference_for="annotation_free", ablation_tables=("warm_start",), table_order=10, color="#1f77b4"),
    Method("confidence_filtered", 1, "scratch", ("epochs_stage1",), "lr_stage1", data="confidence",
           uses=("confidence",), description="plain student on pseudo-labels passing the confidence criterion",
           label="Confidence-Filtered Student", table_order=20, color="#2ca02c", symbol="v"),
    Method("afs_control", 1, "scratch", ("epochs_stage1",), "lr_stage1", data="afs", uses=("afs",),
           description="annotation-free-style control: base prompt, image+vflip fused, score filter",
           label="Annotation-Free-style Control", table_order=30, color="#9467bd", symbol="^"),
    Method("geodistill", 2, "stage1", ("epochs_stage2",), "lr_stage2", terms=_FULL, select="stage2", role="proposed",
           description="Stage I -> gated SDF + skeleton + area refinement (eq:refine-loss)", label="GeoDistill-Refine",
           ablation_tables=("warm_start", "component"), table_order=120, color="#d62728", symbol="D"),
    Method("gabi", 2, "scratch", ("gabi.epochs",), "lr_stage1", terms=("region", "dist", "boundary"), uses=("gabi",),
           description="GABI-inspired: joint from scratch, ungated distance regression + boundary BCE",
           label="GABI-inspired Pseudo-Geometry", table_order=40, color="#8c564b", symbol="P"),
    Method("full_scratch_10", 2, "scratch", ("epochs_stage2",), "lr_stage1", terms=_FULL, role="ablation",
           description="ablation: full gated geometry from scratch, 10 epochs",
           label="Full geometry, from scratch (10)", ablation_tables=("warm_start",), table_order=50,
           color="#bcbd22", dash="dashed", symbol="<"),
    Method("full_scratch_30", 2, "scratch", ("epochs_stage1", "epochs_stage2"), "lr_stage1", terms=_FULL,
           role="ablation", description="ablation: full gated geometry from scratch, 30 epochs",
           label="Full geometry, from scratch (30)", ablation_tables=("warm_start",), table_order=60,
           color="#17becf", dash="dashed", symbol=">"),
    Method("sdf_scratch", 2, "scratch", ("epochs_stage2",), "lr_stage1", terms=("region", "sdf"),
           description="ablation: L_raw + gated SDF from scratch", label="SDF only, from scratch", role="ablation",
           ablation_tables=("warm_start",), table_order=70, color="#000080", dash="dashed", symbol="x"),
    Method("sdf_gated", 2, "stage1", ("epochs_stage2",), "lr_stage2", terms=("region", "sdf"), select="stage2",
           description="ablation: Stage I -> gated SDF only", label="Stage I -> gated SDF", role="ablation",
           ablation_tables=("warm_start", "component"), table_order=80, color="#008080", dash="dashed", symbol="+"),
    Method("sdf_skel_gated", 2, "stage1", ("epochs_stage2",), "lr_stage2", terms=("region", "sdf", "skel"),
           select="stage2", description="ablation: Stage I -> gated SDF + skeleton", label="Gated SDF + skeleton",
           role="ablation", ablation_tables=("component",), table_order=90, color="#800000", dash="dashed", symbol="*"),
    Method("sdf_area_gated", 2, "stage1", ("epochs_stage2",), "lr_stage2", terms=("region", "sdf", "area"),
           select="stage2", description="ablation: Stage I -> gated SDF + area", label="Gated SDF + area",
           role="ablation", ablation_tables=("component",), table_order=100, color="#f032e6", dash="dashed",
           symbol="h"),
    Method("no_gate", 2, "stage1", ("epochs_stage2",), "lr_stage2", terms=_FULL, gate="one", select="stage2",
           description="ablation: full refinement with g = 1", label="SDF + skeleton + area, no gate", role="ablation",
           ablation_tables=("component",), table_order=110, color="#6464ff", dash="dashed", symbol="X"),
    Method("geodistill_adaptive", 2, "stage1", ("epochs_stage2",), "lr_stage2",
           terms=("region", "anchor", "sdf", "skel", "area"), adaptive=True, uses=("confidence", "adaptive"),
           description="quality-adaptive external mode (switch on the pass ratio r)", role="external",
           label="GeoDistill-Refine (quality-adaptive)", table_order=130, color="#e377c2", symbol="d"),
    Method("continuation", 2, "stage1", ("epochs_stage2",), "lr_stage2", select="stage2", role="control",
           description="control: Stage I -> Stage II's schedule, epochs and selection with L_raw only "
                       "(budget-matched, no geometry)", label="Budget-matched continuation (Stage II, L_raw only)",
           reference_for="warm_started", table_order=140, color="#ff7f0e", dash="dashdot", symbol="s"),
    Method("supervised_ceiling", 1, "scratch", ("epochs_stage1",), "lr_stage1", data="reference",
           description="NOT annotation-free: the Plain Student's recipe on the training split's REFERENCE masks",
           label="Supervised ceiling (uses reference masks; not annotation-free)", role="control",
           table_order=150, color="#000000", dash="dotted", symbol="p"),
]}

#: the one method whose loss sees reference (manual) masks, behind ``protocol.supervised_ceiling``
SUPERVISED_CEILING = "supervised_ceiling"
#: appended to the label of a run with human-corrected masks in its loss (``review.mode: replace``)
HUMAN_TARGETS_LABEL = "(trained on human corrections; not annotation-free)"


def run_annotation_free(method: Method, review: Mapping[str, Any] | None = None) -> bool:
    """Tell whether a run is annotation-free: the method is, and ``review`` puts no human correction in its loss.

    Parameters
    ----------
    method : Method
        The run's method.
    review : Mapping or None, optional
        The params ``review`` section the run read (None: no review).

    Returns
    -------
    bool
        False for the supervised ceiling, and for a run whose ``review.mode`` is ``replace`` with corrections.
    """
    replaces = bool(review and review.get("corrections") and review.get("mode") == "replace")
    return method.annotation_free and not replaces


def run_label(method: Method, review: Mapping[str, Any] | None = None) -> str:
    """Return the method's label in a table, with :data:`HUMAN_TARGETS_LABEL` when the run trained on corrections.

    Parameters
    ----------
    method : Method
        The run's method.
    review : Mapping or None, optional
        The params ``review`` section the run read (None: no review).

    Returns
    -------
    str
        :attr:`Method.label`, extended when an annotation-free method's run was not (:func:`run_annotation_free`).
    """
    return method.label if run_annotation_free(method, review) or not method.annotation_free \
        else f"{method.label} {HUMAN_TARGETS_LABEL}"


def check_reference_boundary(methods: Mapping[str, Method]) -> None:
    """Check that no method but :data:`SUPERVISED_CEILING` trains on reference masks.

    Parameters
    ----------
    methods : Mapping
        Name -> :class:`Method` (a method table).

    Raises
    ------
    ValueError
        Naming the other methods whose ``data`` is ``reference``.
    """
    bad = [m.name for m in methods.values() if not m.annotation_free and m.name != SUPERVISED_CEILING]
    if bad:
        raise ValueError(f"methods {bad} ask for reference-mask targets; only {SUPERVISED_CEILING!r} may")


def check_method_table(methods: Mapping[str, Method]) -> None:
    """Check that the methods' study facts hold together.

    Each has a label, a role of :data:`ROLES`, ablation tables of :data:`ABLATION_TABLES` (one at least for an
    ablation) and a scope of :data:`GAIN_SCOPES` or none; labels and table orders are unique; the reference
    boundary holds (:func:`check_reference_boundary`).

    Parameters
    ----------
    methods : Mapping
        Name -> :class:`Method` (a method table).

    Raises
    ------
    ValueError
        Naming the method, or the field two methods share.
    """
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
    """Return the one method for which ``test`` holds.

    Parameters
    ----------
    what : str
        What the method is, for the error (``"proposed method"``).
    test : callable
        ``test(method) -> bool``.
    methods : Mapping, optional
        The method table (default :data:`METHODS`).

    Returns
    -------
    str
        The method's name.

    Raises
    ------
    ValueError
        None or several methods pass ``test`` (naming ``what``).
    """
    found = [m.name for m in methods.values() if test(m)]
    if len(found) != 1:
        raise ValueError(f"the method table must have exactly one {what}; it has {found}")
    return found[0]


#: the paper's proposed method (GeoDistill-Refine)
PROPOSED = the_method("proposed method", lambda m: m.role == "proposed")
#: the reference point of every annotation-free method's gain
BASELINE = the_method("reference point of every gain", lambda m: m.reference_for == "annotation_free")
#: the reference point of the warm-started methods' gains (the same training budget)
CONTINUATION = the_method("budget-matched control", lambda m: m.reference_for == "warm_started")
#: where every warm-started method starts, at the same seed
STAGE_ONE = the_method("Stage-I method", lambda m: m.stage == 1 and m.init == "scratch" and m.data == "all"
                       and m.terms == ("region",))
#: the methods that are a reference point of some gain (:attr:`Method.reference_for`)
GAIN_CONTROLS = tuple(n for n, m in METHODS.items() if m.reference_for)


def methods_with_role(*roles: str) -> list[str]:
    """List the methods whose role is one of ``roles``, in the method table's order.

    Parameters
    ----------
    *roles : str
        Roles of :data:`ROLES`.

    Returns
    -------
    list of str
        Method names.
    """
    return [n for n, m in METHODS.items() if m.role in roles]


def in_table_order(names) -> list[str]:
    """Sort ``names`` by :attr:`Method.table_order`.

    Parameters
    ----------
    names : iterable of str
        Method names (a repeat counts once).

    Returns
    -------
    list of str
        The distinct names, known ones by table order, then unknown ones in their order.
    """
    names = list(dict.fromkeys(names))
    known = sorted((n for n in names if n in METHODS), key=lambda n: METHODS[n].table_order)
    return known + [n for n in names if n not in METHODS]


def ablation_table_rows(table: str) -> list[str]:
    """List the rows of ablation table ``table``, in table order.

    Parameters
    ----------
    table : str
        A key of :data:`ABLATION_TABLES`.

    Returns
    -------
    list of str
        The names of the methods that are its rows.
    """
    return in_table_order(n for n, m in METHODS.items() if table in m.ablation_tables)


# ------------------------------------------------------------------------------------------------ recipe parts
# A recipe part is a training knob whose value comes from ``train.recipe`` unless params.yaml sets it.  Its
# :class:`RecipePart` declaration is the one place that names it: the params schema's field (type, range, doc line;
# :func:`pipeline.params.with_recipe_parts`), the paper recipe's value (the part's "off" value), whether every run's
# fingerprint tracks it (:data:`COMMON_KEYS`), its departure label in the report tables (:data:`DEPARTURES`) and
# where a run reads it (a field of ``pipeline.training.settings.Settings`` or of ``pipeline.losses.LossConstants``)
# all derive from it.  Adding a part touches its declaration here and the code that consumes it (docs/pipeline.md,
# "How to extend").  They live in this torch-free module because the schema, the method table and the losses all
# read them.

#: where a run reads a part: a field of ``Settings`` or of ``LossConstants`` of the same name, or "" = its consumer
#: reads the validated section itself (a part that is transformed first: the epochs, the augmentation spec)
HOMES = ("settings", "losses", "")
#: a part's ``schema_after`` / ``common_after`` that places it first
FIRST = "^"


@dataclasses.dataclass(frozen=True)
class RecipePart:
    """One recipe part, declared once.

    Attributes
    ----------
    key : str
        The dotted params key, ``section.name`` (``train.bootstrap_beta``).
    type : Any
        The value's type as the schema checks it (``float``, ``bool``, a ``Literal``); the schema field is
        ``type | None``, None taking the recipe's value.
    off : Any
        The paper recipe's value: where the part changes nothing (for a lever, its "off" value).  Outside Stage I,
        a ``stage_one`` part takes this value.
    doc : str
        The schema's description (params.yaml's comment), without the "recipe part:" prefix the schema adds.
    bounds : Mapping
        Pydantic bounds of the value (``ge``, ``gt``, ``le``, ``lt``); empty = none.
    departure : str
        Non-empty for a part that departs from the paper's loss when not ``off``: its name in every report table,
        formatted with the value ``v`` (:func:`pipeline.methods.departures`).
    stage_one : bool
        The part applies to Stage I only; other stages read ``off``.
    home : str
        One of :data:`HOMES`: where a run reads the value.
    common : bool
        Every method reads it, so every run's fingerprint holds it (:data:`pipeline.methods.COMMON_KEYS`); False
        for a part only some methods read (the Stage-I and Stage-II epochs: :attr:`pipeline.methods.Method.epochs`).
    schema_after : str
        The section's field this part follows in the schema (params.yaml's order): "" = the section's end,
        :data:`FIRST` = its start (:func:`interleave`).
    common_after : str
        The ``COMMON_KEYS`` key it follows (the order of the DAG's tracked params), as ``schema_after``.
    reads_agreement : bool
        When not ``off`` (in the stages it applies to), the run's region input is the agreement map A
        (eq:agreement-map) instead of the voted mask (:func:`pipeline.training.inputs.agreement_target`).
    """

    key: str
    type: Any
    off: Any
    doc: str
    bounds: Mapping[str, float] = dataclasses.field(default_factory=dict)
    departure: str = ""
    stage_one: bool = False
    home: str = ""
    common: bool = True
    schema_after: str = ""
    common_after: str = ""
    reads_agreement: bool = False

    def __post_init__(self):
        """Refuse a declaration whose ``home`` is not one of :data:`HOMES` or whose key is not section.name."""
        if self.home not in HOMES:
            raise ValueError(f"recipe part {self.key}: home {self.home!r} is not one of {HOMES}")
        if self.key.count(".") != 1:
            raise ValueError(f"recipe part {self.key}: the key must be section.name")

    @property
    def section(self) -> str:
        """The params section (``train``)."""
        return self.key.split(".")[0]

    @property
    def name(self) -> str:
        """The key within its section (``bootstrap_beta``)."""
        return self.key.split(".")[1]

    @property
    def description(self) -> str:
        """The schema field's description: the "recipe part" prefix, then :attr:`doc`.

        The prefix says Stage I for a ``stage_one`` part and, outside ``train``, that ``train.recipe`` sets it.
        """
        where = ", Stage I" if self.stage_one else "" if self.section == "train" else " (train.recipe)"
        return f"recipe part{where}: {self.doc}"

    def departs(self, value: Any) -> bool:
        """Whether ``value`` departs from the paper's loss (False for a part that is no departure).

        Parameters
        ----------
        value : Any
            A recorded value of the part.

        Returns
        -------
        bool
            ``departure`` is set and ``value`` is not :attr:`off`.
        """
        return bool(self.departure) and value != self.off

    def value_for(self, cfg: Mapping[str, Any], stage_one: bool) -> Any:
        """Return the part's value in a run: ``cfg``'s, or :attr:`off` outside Stage I for a Stage-I part.

        Parameters
        ----------
        cfg : Mapping
            The validated section (recipe parts filled in).
        stage_one : bool
            Whether the run is Stage I.

        Returns
        -------
        Any
            The value.
        """
        return cfg[self.name] if stage_one or not self.stage_one else self.off


_FRACTION = {"ge": 0, "le": 1}
#: every recipe part, in declaration order (the order of :func:`recipe_parts`)
PARTS: tuple[RecipePart, ...] = (
    RecipePart("train.precision", Literal["fp32", "bf16", "auto"], "auto",
               "fp32 | bf16 | auto (bf16 autocast where the CPU/GPU supports it: host-dependent)", home="settings",
               schema_after="recipe", common_after="recipe"),
    RecipePart("train.warmup_epochs", int, 0, "linear learning-rate warm-up over this many epochs (0 = none)",
               {"ge": 0}, home="settings", schema_after="precision", common_after="precision"),
    RecipePart("train.average_last", int, 0, "final model = mean weights of the last K epochs with BN statistics "
               "recomputed (0 = the method's selection rule)", {"ge": 0}, home="settings",
               schema_after="warmup_epochs", common_after="warmup_epochs"),
    RecipePart("train.batch_size", int, 4, "images per optimizer step", {"ge": 1}, home="settings",
               schema_after="precise_bn", common_after="precise_bn"),
    RecipePart("train.epochs_stage1", int, 20, "Stage-I epochs", {"ge": 0}, common=False,
               schema_after="weight_decay"),
    RecipePart("train.epochs_stage2", int, 10, "Stage-II epochs", {"ge": 0}, common=False,
               schema_after="lr_stage1"),
    RecipePart("train.schedule", Literal["cosine", "constant", "wsd"], "cosine",
               "learning rate after the warm-up (paper gives initial rates only): cosine to 0 | constant | wsd = "
               "constant, then linear to 0 over the last decay_fraction of the steps", home="settings",
               schema_after="lr_stage2", common_after="weight_decay"),
    RecipePart("train.augment", bool, False, "target-consistent augmentation (train.augmentation; "
               "pipeline.augment); replaces augment_hflip when on", schema_after="augment_hflip",
               common_after="decay_fraction"),
    RecipePart("train.ema_decay", float, 0.0, "final model = exponential moving average of the weights (this decay "
               "per optimizer step) with BN statistics recomputed; 0 = off", {"ge": 0, "lt": 1}, home="settings",
               schema_after="average_last", common_after="augmentation"),
    RecipePart("train.soft_targets", bool, False, "the region target is the agreement map A (eq:agreement-map) "
               "instead of the voted mask M^T in eq:raw-loss -- a departure from the paper, named in every table",
               departure="agreement-map targets", home="losses", schema_after="ema_decay",
               common_after="ema_decay", reads_agreement=True),
    RecipePart("train.until", Literal["epochs", "plateau"], "epochs", "epochs = train epochs_stage1 epochs | "
               "plateau = stop the stable phase when the validation IoU stops improving (train.plateau_gain) or the "
               "step budget is spent, then decay (docs/student.md); epochs_stage1 caps the run", stage_one=True,
               home="settings", schema_after="validate_low_res", common_after="soft_targets"),
    RecipePart("train.lr_scale", float, 1.0, "multiplies train.lr_stage1, Stage I's peak learning rate", {"gt": 0},
               schema_after="soft_targets", common_after="holdout_fraction"),
    RecipePart("train.low_res_fraction", float, 0.0, "the first round(this x epochs_stage1) epochs train at half the "
               "side, the last at full side (a resolution schedule; until: plateau scores the later ones; "
               "docs/decisions.md); 0 = none", {"ge": 0, "lt": 1}, stage_one=True, schema_after="ignore_band",
               common_after="lr_scale"),
    RecipePart("train.bootstrap_beta", float, 1.0, "soft bootstrapped targets (Reed et al. 2015): eq:raw-loss's "
               "target is beta M + (1 - beta) P, P the student's own detached probability; 1 = the paper's M -- "
               "below 1 a departure from eq:raw-loss, named in every table", {"gt": 0, "le": 1},
               departure="bootstrapped targets, beta {v:g}", stage_one=True, home="losses",
               schema_after="lr_scale", common_after="validate_low_res"),
    RecipePart("train.ignore_band", float, 0.0, "pixels whose agreement A (eq:agreement-map) lies within this of "
               "1/2, where the prompts split, leave eq:raw-loss (weight 0); 0 = none (the paper) -- a departure from "
               "eq:raw-loss, named in every table", {"ge": 0, "le": 0.5}, departure="ignore band {v:g}",
               stage_one=True, home="losses", schema_after="bootstrap_beta", common_after="bootstrap_beta",
               reads_agreement=True),
    RecipePart("train.agreement_weight", float, 0.0, "each pixel's weight in eq:raw-loss is |2A(x) - 1|^gamma, A "
               "the agreement map (eq:agreement-map): pixels where the prompts split count less, unanimous ones "
               "fully; gamma this value, 0 = every pixel weight 1 (the paper) -- a departure from eq:raw-loss, "
               "named in every table", {"ge": 0}, departure="agreement-weighted loss, gamma {v:g}",
               stage_one=True, home="losses", schema_after="low_res_fraction", common_after="ignore_band",
               reads_agreement=True),
    RecipePart("train.expand_branches", bool, False, "RepVGG branches: each 3x3 convolution trains beside a 1x1 "
               "convolution and, where input and output channels match, the identity, each with its own BatchNorm, "
               "folded into the plain TinyUNet at each stage's end; the deployed network and the loss stay the "
               "paper's; needs norm: batch (docs/decisions.md)", home="settings", schema_after="norm",
               common_after="norm"),
    RecipePart("calibrate.tau_rule", Literal["argmax", "plateau", "smooth"], "argmax",
               "argmax of the validation IoU curve | plateau = centre of the near-optimal plateau | smooth = argmax "
               "of the smoothed curve (pipeline.thresholds)", schema_after=FIRST, common=False),
)

_BY_KEY = {p.key: p for p in PARTS}
if len(_BY_KEY) != len(PARTS):
    raise ValueError("two recipe parts share a key")


def interleave(keys, placed: Mapping[str, str]) -> list[str]:
    """Insert each of ``placed`` after the key it names in ``keys`` (recursively: a part may follow a part).

    Parameters
    ----------
    keys : iterable of str
        The fixed keys, in order.
    placed : Mapping
        Key to insert -> the key it follows; :data:`FIRST` = first, "" = last (in ``placed``'s order).

    Returns
    -------
    list of str
        Every key once.

    Raises
    ------
    ValueError
        A key follows a key that is neither fixed nor placed.
    """
    out: list[str] = []

    def put(k: str) -> None:
        out.append(k)
        for p, after in placed.items():
            if after == k:
                put(p)

    for p, after in placed.items():
        if after == FIRST:
            put(p)
    for k in keys:
        put(k)
    for p, after in placed.items():
        if after == "":
            put(p)
    missing = [p for p in placed if p not in out]
    if missing:
        raise ValueError(f"recipe parts {missing} follow a key that does not exist")
    return out


def part(key: str) -> RecipePart:
    """Return the declaration of recipe part ``key``.

    Parameters
    ----------
    key : str
        A dotted key (``train.bootstrap_beta``).

    Returns
    -------
    RecipePart
        Its declaration.

    Raises
    ------
    KeyError
        ``key`` is not a recipe part.
    """
    return _BY_KEY[key]


def parts_of(section: str, home: str | None = None) -> tuple[RecipePart, ...]:
    """List the parts of one params section, in declaration order; with ``home``, only those read there.

    Parameters
    ----------
    section : str
        A params section (``train``, ``calibrate``).
    home : str or None, optional
        One of :data:`HOMES`, or None (default) for every part of the section.

    Returns
    -------
    tuple of RecipePart
        The parts.
    """
    return tuple(p for p in PARTS if p.section == section and (home is None or p.home == home))


def off_value(key: str) -> Any:
    """Return the paper recipe's value of part ``key``: where it is off.

    Parameters
    ----------
    key : str
        A dotted key.

    Returns
    -------
    Any
        :attr:`RecipePart.off`.

    Raises
    ------
    KeyError
        ``key`` is not a recipe part.
    """
    return part(key).off


def recipe_parts() -> list[str]:
    """List the dotted keys of every recipe part (``train.precision``, ``calibrate.tau_rule``, ...), by section.

    Returns
    -------
    list of str
        The keys, the sections in first-declared order.
    """
    return [p.key for s in dict.fromkeys(p.section for p in PARTS) for p in parts_of(s)]


def recipe_values(**changes: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """Build a recipe: section -> part -> value, each part at its :attr:`RecipePart.off` unless ``changes`` sets it.

    Parameters
    ----------
    **changes : Mapping
        Per section, the parts that differ from the paper recipe.

    Returns
    -------
    dict
        The whole recipe.

    Raises
    ------
    KeyError
        A change names no recipe part.
    """
    out = {s: {p.name: p.off for p in parts_of(s)} for s in dict.fromkeys(p.section for p in PARTS)}
    for sec, values in changes.items():
        for k, v in values.items():
            part(f"{sec}.{k}")  # KeyError naming an unknown part
            out[sec][k] = v
    return out


def with_part_fields(base: type, home: str, *, defaults: bool = False) -> type:
    """Make a frozen dataclass of ``base``'s fields and a field for each ``train`` part read at ``home``.

    Each part's field is named as the part; the docstring's Attributes section is extended with the parts' doc
    lines.

    Parameters
    ----------
    base : type
        A frozen dataclass whose docstring ends with its Attributes section.
    home : str
        One of :data:`HOMES` but "": ``settings`` or ``losses``.
    defaults : bool, optional
        Give each part field the part's :attr:`RecipePart.off` as its default (``base``'s fields must then have
        defaults too).

    Returns
    -------
    type
        The dataclass, named as ``base`` without its leading underscore, in ``base``'s module.
    """
    parts = parts_of("train", home)
    fields = [(p.name, p.type, dataclasses.field(default=p.off)) if defaults else (p.name, p.type) for p in parts]
    name = base.__name__.lstrip("_")
    doc = (base.__doc__ or "").rstrip() + "".join(
        f"\n    {p.name} : {getattr(p.type, '__name__', 'str')}\n        ``{p.key}``"
        f"{' (Stage I; ' + repr(p.off) + ' elsewhere)' if p.stage_one else ''}: {p.doc}." for p in parts) + "\n    "
    cls = dataclasses.make_dataclass(name, fields, bases=(base,), frozen=True, namespace={"__doc__": doc})
    cls.__module__, cls.__qualname__ = base.__module__, name
    return cls


_STRONG = {"precision": "fp32", "warmup_epochs": 2, "average_last": 4, "batch_size": 8, "epochs_stage1": 80,
           "epochs_stage2": 20, "schedule": "wsd", "augment": True}
#: recipe -> section -> part -> value; a part left null takes ``train.recipe``'s value (docs/decisions.md)
RECIPES: dict[str, dict[str, dict[str, Any]]] = {
    "paper": recipe_values(),
    "stable": recipe_values(train={"precision": "fp32", "average_last": 5}, calibrate={"tau_rule": "smooth"}),
    "strong": recipe_values(train=_STRONG, calibrate={"tau_rule": "smooth"}),
    "plateau": recipe_values(train={**_STRONG, "epochs_stage1": 100, "until": "plateau"},
                             calibrate={"tau_rule": "smooth"}),
    # the speedrun's winner (docs/student.md): the first 160 of at most 220 epochs at half the side, the same
    # training cost as plateau's 100 epochs at full side
    "progressive": recipe_values(train={**_STRONG, "epochs_stage1": 220, "low_res_fraction": 8 / 11,
                                        "until": "plateau"}, calibrate={"tau_rule": "smooth"}),
}


#: recipe parts that depart from eq:raw-loss: dotted params key -> (whether a recorded value departs, its name in a
#: table, formatted with the value ``v``), from the declarations (:data:`PARTS`)
DEPARTURES: dict[str, tuple[Callable[[Any], bool], str]] = {p.key: (p.departs, p.departure) for p in PARTS
                                                               if p.departure}


def departures(recorded: Mapping[str, Any]) -> list[str]:
    """List the departures from eq:raw-loss that a run's recorded params hold (:data:`DEPARTURES`), in order.

    Parameters
    ----------
    recorded : Mapping
        Dotted params key -> the value the run recorded; a key it did not record (an older run) departs from
        nothing.

    Returns
    -------
    list of str
        Each departure's name in a table, formatted with its value.
    """
    return [name.format(v=recorded[k]) for k, (on, name) in DEPARTURES.items()
            if recorded.get(k) is not None and on(recorded[k])]


def method_label(name: str) -> str:
    """Return the display label of method ``name``.

    Parameters
    ----------
    name : str
        A method name.

    Returns
    -------
    str
        :attr:`Method.label`; an unknown name as is.
    """
    return METHODS[name].label if name in METHODS else name


def annotation_free_methods(names) -> list[str]:
    """Drop the methods that train on reference masks from ``names``.

    Parameters
    ----------
    names : iterable of str
        Method names.

    Returns
    -------
    list of str
        ``names`` in order, less the supervised ceiling; unknown names are kept.
    """
    return [n for n in names if n not in METHODS or METHODS[n].annotation_free]


def gain_treatments(control: str, names) -> list[str]:
    """List the methods of ``names`` that are compared with reference point ``control``.

    Every annotation-free method against :data:`BASELINE`, the warm-started ones against :data:`CONTINUATION`;
    never the control itself.

    Parameters
    ----------
    control : str
        A reference point (:data:`GAIN_CONTROLS`).
    names : iterable of str
        The methods run.

    Returns
    -------
    list of str
        The treatments, in the order of ``names``.
    """
    free = [n for n in annotation_free_methods(names) if n != control]
    if control in METHODS and METHODS[control].reference_for == "warm_started":
        return [n for n in free if n in METHODS and METHODS[n].init == "stage1"]
    return free


def get_method(name: str) -> Method:
    """Return the :class:`Method` called ``name``.

    Parameters
    ----------
    name : str
        A ``--method`` name.

    Returns
    -------
    Method
        Its row of :data:`METHODS`.

    Raises
    ------
    InputError
        No method has that name (listing the valid ones).
    """
    try:
        return METHODS[name]
    except KeyError:
        raise InputError(f"--method {name!r}: expected one of {', '.join(METHODS)}") from None


def _get(cfg: Mapping[str, Any], dotted: str, prefix: str = "train.") -> Any:
    """Read key ``dotted`` of ``cfg``; InputError naming ``prefix + dotted`` when it is missing."""
    cur: Any = cfg
    for k in dotted.split("."):
        if not isinstance(cur, Mapping) or k not in cur:
            raise InputError(f"params: {prefix}{dotted} missing")
        cur = cur[k]
    return cur


def method_epochs(method: Method, cfg: Mapping[str, Any]) -> int:
    """Return a method's epochs: the sum of the train params named in ``method.epochs``.

    Parameters
    ----------
    method : Method
        The method.
    cfg : Mapping
        The validated ``train`` section.

    Returns
    -------
    int
        The epochs, >= 1.

    Raises
    ------
    InputError
        The sum is below 1 (naming the keys); a key is missing.
    """
    total = sum(int(_get(cfg, key)) for key in method.epochs)
    if total < 1:
        raise InputError(f"params: {' + '.join('train.' + k for k in method.epochs)} must be >= 1")
    return total


def method_lr(method: Method, cfg: Mapping[str, Any]) -> float:
    """Return a method's peak learning rate: ``train.<method.lr>``, times ``train.lr_scale`` for Stage I's rate.

    Parameters
    ----------
    method : Method
        The method.
    cfg : Mapping
        The validated ``train`` section.

    Returns
    -------
    float
        The peak learning rate.
    """
    return float(_get(cfg, method.lr)) * (float(_get(cfg, "lr_scale")) if method.lr == "lr_stage1" else 1.0)


#: train params every method reads; ``precision`` and ``num_threads`` change numerics, so they are among them; the
#: recipe parts every method reads are placed by their declarations (:attr:`RecipePart.common_after`)
COMMON_KEYS = tuple(interleave(
    ("channels", "norm", "bn_momentum", "precise_bn", "weight_decay", "dice_weight", "pos_weight_max", "loss_eps",
     "recipe", "channels_last", "augment_hflip", "num_threads", "val_bf1_tolerance", "decay_fraction",
     "augmentation", "step_budget", "time_budget", "plateau_gain", "plateau_min_epochs", "plateau_min_steps",
     "holdout_fraction", "validate_low_res"),
    {p.name: p.common_after for p in parts_of("train") if p.common}))
#: extra train params per loss term; the last key of a term is its weight (:func:`resolve_plan`)
TERM_KEYS = {"region": (), "sdf": ("sdf_band", "sdf_base_weight", "lambda_sdf"), "skel": ("lambda_skel",),
             "area": ("area_eps", "lambda_area"), "dist": ("gabi.lambda_dist",),
             "boundary": ("sdf_band", "gabi.lambda_boundary"), "anchor": ("adaptive.anchor_weight",)}
#: the one key outside ``train.*`` every run reads: the tau of checkpoint selection, the project's fixed tau
SELECTION_TAU_KEY = "calibrate.fixed_tau"


def param_keys(method: Method) -> tuple[str, ...]:
    """List the dotted params keys a run of ``method`` reads: what DVC tracks for its stage and its fingerprint holds.

    Parameters
    ----------
    method : Method
        The method.

    Returns
    -------
    tuple of str
        :data:`COMMON_KEYS`, its epochs and learning rate, its terms' keys (:data:`TERM_KEYS`), its selection
        and sub-sections, each under ``train.``; then :data:`SELECTION_TAU_KEY`.
    """
    keys = [*COMMON_KEYS, *method.epochs, method.lr, *(k for t in method.terms for k in TERM_KEYS[t]),
            *(["stage2_select"] if method.select == "stage2" else []), *method.uses]
    # a whole sub-section (``uses``) covers its own keys
    keys = [k for k in dict.fromkeys(keys) if not any(k.startswith(u + ".") for u in method.uses)]
    return tuple(f"train.{k}" for k in keys) + (SELECTION_TAU_KEY,)


def fingerprint_params(method: Method, params: Mapping[str, Any]) -> dict:
    """Collect the values of a run's params keys (:func:`param_keys`): what its fingerprint holds.

    Parameters
    ----------
    method : Method
        The method.
    params : Mapping
        Validated params.

    Returns
    -------
    dict
        ``{dotted key: value}``.
    """
    return {k: _get(params, k, prefix="") for k in param_keys(method)}


def uses_confidence(method: Method) -> bool:
    """Tell whether the method evaluates the confidence criterion (the filter, or the adaptive pass ratio r).

    Parameters
    ----------
    method : Method
        The method.

    Returns
    -------
    bool
        Its data is ``confidence`` or it is adaptive.
    """
    return method.data == "confidence" or method.adaptive


def input_artifacts(method: Method, criterion: str | None = None) -> tuple[str, ...]:
    """List the catalogue names of the artifacts a run of ``method`` reads.

    Parameters
    ----------
    method : Method
        The method.
    criterion : str or None, optional
        ``train.confidence.criterion``; None (default): either (the superset dvc.yaml tracks).

    Returns
    -------
    tuple of str
        ``manifest``, ``images``, ``reference`` (validation selection only), then those of ``gates``,
        ``teacher``, ``consensus`` and ``geometry`` the method needs.
    """
    wanted = {"gates": method.needs_gates,
              "teacher": method.data == "afs" or (uses_confidence(method) and criterion in (None, "mean_score")),
              "consensus": method.data not in ("afs", "reference"), "geometry": method.needs_geometry}
    return ("manifest", "images", "reference", *(name for name, needed in wanted.items() if needed))


def adaptive_mode(r: float, boundary: float = 0.5) -> str:
    """Choose the quality-adaptive mode from the training pass ratio r.

    Parameters
    ----------
    r : float
        The share of training images passing the confidence criterion.
    boundary : float, optional
        ``train.adaptive.ratio_boundary`` (:func:`resolve_plan` passes the params' value; the default is the
        paper's).

    Returns
    -------
    str
        ``anchored`` when r >= boundary, else ``geometry_only``.
    """
    return "anchored" if float(r) >= float(boundary) else "geometry_only"


@dataclasses.dataclass(frozen=True)
class Plan:
    """A method resolved for one run (:func:`resolve_plan`).

    Attributes
    ----------
    weights : dict
        Loss term -> its weight (eq:refine-loss); a term absent is not computed.
    select : str
        The checkpoint selection: ``best_val`` | ``last``.
    epoch0_eligible : bool
        Whether the initial (warm-start) model is a candidate.
    mode : str
        The quality-adaptive mode (:func:`adaptive_mode`); "" for other methods.
    """

    weights: dict
    select: str
    epoch0_eligible: bool = False
    mode: str = ""


def resolve_plan(method: Method, cfg: Mapping[str, Any], pass_ratio_r: float | None = None) -> Plan:
    """Resolve a method for one run: its term weights and its selection rule.

    Parameters
    ----------
    method : Method
        The method.
    cfg : Mapping
        The validated ``train`` section.
    pass_ratio_r : float or None, optional
        The training pass ratio r; the adaptive method needs it (:func:`adaptive_mode`).

    Returns
    -------
    Plan
        Weights: region 1, the others their eq:refine-loss or baseline lambda (the last key of
        :data:`TERM_KEYS`); the adaptive method's mode drops the region term (and, unless
        ``train.adaptive.anchor_geometry_only``, the anchor) in ``geometry_only``.

    Raises
    ------
    ValueError
        The adaptive method without ``pass_ratio_r``.
    """
    weights = {t: 1.0 if t == "region" else float(_get(cfg, TERM_KEYS[t][-1])) for t in method.terms}
    select = _get(cfg, "stage2_select") if method.select == "stage2" else method.select
    if not method.adaptive:
        return Plan(weights=weights, select=select)
    if pass_ratio_r is None:
        raise ValueError("the adaptive method needs the pass ratio r")
    mode = adaptive_mode(pass_ratio_r, _get(cfg, "adaptive.ratio_boundary"))
    if mode == "geometry_only":
        weights.pop("region")
        if not _get(cfg, "adaptive.anchor_geometry_only"):
            weights.pop("anchor", None)
    return Plan(weights=weights, select="best_val", epoch0_eligible=mode == "geometry_only", mode=mode)
