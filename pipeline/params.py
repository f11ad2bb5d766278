"""The typed params schema: every knob of the pipeline, its default (the paper's value) and its bounds, once.

Every stage validates the whole params file at start (:func:`load_params`); a bad value or an unknown key
is one InputError line naming the key.  Library code reads the paper's constants from ``PAPER``.
"""

from __future__ import annotations

import copy
import re
from pathlib import Path
from typing import Annotated, Any, Iterable, Literal, Mapping

import yaml
from pydantic import (AfterValidator, BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, create_model,
                      field_validator, model_serializer, model_validator)

from pipeline.engine_table import BENCHMARK_VARIANTS, engine_name  # pure Python: the engine names, one list
from pipeline.runtime.errors import InputError
from pipeline.methods import METHODS, PROPOSED, STAGE_ONE  # pure Python, no torch: this module stays torch-free
from pipeline.methods import RECIPES, interleave, parts_of, recipe_parts  # each recipe part, declared once
from pipeline.teacher_table import SIMULATED, TEACHER_ENGINES, load, teacher_spec  # pure Python: the teacher names, one table

__all__ = ["RECIPES", "DEFAULT_PARAMS", "SOURCES", "SPLITS", "AUTO_BIT_DEPTH", "BIT_DEPTHS", "PAPER_PROMPTS",
           "unresolved", "INT8_CALIBRATIONS", "INT8_WEIGHT_BITS", "Params", "PAPER", "validate", "validate_section",
           "deep_merge", "parse_override", "get_path", "read_yaml_mapping", "PROFILE_KEY", "load_params", "section",
           "require"]

DEFAULT_PARAMS = "params.yaml"


class _Loader(yaml.SafeLoader):
    """YAML with YAML 1.2's numbers: ``1e-4`` (no dot) is a float, not PyYAML's string."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
    |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
    |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
    |[-+]?[0-9][0-9_]*(?::[0-5]?[0-9])+\.[0-9_]*
    |[-+]?\.(?:inf|Inf|INF)
    |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."))


def load_yaml(text: str):
    """Parse YAML like ``yaml.safe_load``, with scientific notation read as numbers (:class:`_Loader`)."""
    return yaml.load(text, Loader=_Loader)


class _Section(BaseModel):
    """Strict: no type coercion (``"1e-4"`` is not a number), finite numbers only, unknown keys rejected."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, validate_default=True)


PositiveInt = Annotated[int, Field(ge=1)]


def _f(default, description: str = "", **bounds):
    return Field(default, description=description, **bounds)


def _must(test, message: str) -> AfterValidator:
    """Build a field check: ValueError ``message`` where ``test(value)`` fails."""
    def check(v):
        if not test(v):
            raise ValueError(message)
        return v
    return AfterValidator(check)


_FRACTION_RANGE = _must(lambda v: 0 < v[0] < v[1] <= 1, "must be [lo, hi] with 0 < lo < hi <= 1")
_POSITIVE_RANGE = _must(lambda v: 0 < v[0] <= v[1], "must be [lo, hi] with 0 < lo <= hi")


class SyntheticParams(_Section):
    """The embedded synthetic benchmark: a SpaceSense-Bench-like spacecraft-disjoint split."""

    train_spacecraft: int = _f(9, "training identities", ge=1, le=10000)
    train_views: int = _f(30, "views per training identity", ge=1, le=100000)
    val_spacecraft: int = _f(3, "validation identities", ge=0, le=10000)
    val_views: int = _f(20, "views per validation identity", ge=0, le=100000)
    test_groups: Annotated[list[str], _must(lambda v: all(g and g.isidentifier() for g in v) and len(set(v)) == len(v),
                                            "must be distinct names (letters, digits, _)")] = _f(
        ["KCP", "CVI", "HJM"], "test group names", min_length=0)
    test_spacecraft_per_group: int = _f(3, ge=0, le=10000)
    test_views: int = _f(20, ge=0, le=100000)
    tiny_probability: float = _f(0.15, "approach shots (mask area mostly < 0.1 % of the frame)", ge=0, le=1)
    tiny_range: Annotated[list[float], _FRACTION_RANGE] = _f(
        [0.0003, 0.002], "apparent size range of tiny views (frame fraction)", min_length=2, max_length=2)
    regular_range: Annotated[list[float], _FRACTION_RANGE] = _f(
        [0.005, 0.6], "apparent size range of other views", min_length=2, max_length=2)
    hard_case_probability: float = _f(0.35, "glare | flare | underexposed | noise | blur", ge=0, le=1)
    background_weights: Annotated[list[float], _must(lambda v: all(x >= 0 for x in v) and sum(v) > 0,
                                                     "must be 3 non-negative weights with a positive sum")] = _f(
        [0.45, 0.35, 0.2], "stars, earth limb, dark lab", min_length=3, max_length=3)


SOURCES = ("synthetic", "spacesense", "spark", "speedplus", "tango", "folder")
#: the evaluate stage's gain intervals (docs/intervals.md)
SEED_IMAGE_T, SEED_BOOTSTRAP, SEED_CLUSTER_T = GAIN_INTERVALS = ("seed_image_t", "seed_bootstrap", "seed_cluster_t")
SPLITS = ("train", "val", "test")
AUTO_BIT_DEPTH = "auto"
BIT_DEPTHS = (AUTO_BIT_DEPTH, 10, 12, 14, 16)


class DataParams(_Section):
    source: Literal[SOURCES] = _f("synthetic")
    root: str | None = _f(None, "dataset root for real sources")
    protocol: str | None = _f(None, "protocol file (data_manifests/...); null = the source's default")
    domain: str | None = _f(None, "speedplus: lightbox | sunlamp | synthetic")
    resolution: int = _f(384, "working resolution (square), the paper's 384x384", ge=16, le=4096)
    seed: int = _f(2026, "synthetic identities and views; seeded sampling for real protocols", ge=0)
    skip_bad: bool = _f(False, "true: leave bad files out and list them in skipped_files.parquet")
    max_pixels: int = _f(2**26, "refuse images above width x height pixels, read from the file header before "
                                "decoding (2**26: 8192 x 8192)", ge=1)
    bit_depth: Literal[BIT_DEPTHS] = _f(
        AUTO_BIT_DEPTH, "bits a 16-bit frame's sensor fills: auto = the file's own (full range, value / 257; a warning "
                        "when a frame uses under 1/8 of it); 10/12/14/16 = value * 255 / (2**bits - 1), clipped")
    letterbox: bool = _f(False, "false: squash each frame to the square working resolution (the paper); true: pad it "
                                "to a square with black first (aspect ratio kept), predictions cropped back exactly")
    cache_dir: str | None = _f(".cache/decode", "decode cache, outside DVC outs (not fingerprinted)")
    synthetic: SyntheticParams = Field(default_factory=SyntheticParams)
    contact_sheet_images: int = _f(16, ge=0, le=256)

    @model_validator(mode="after")
    def _root(self):
        if self.source != "synthetic" and not self.root:
            raise ValueError(f"data.root is required for data.source={self.source!r}")
        return self


PAPER_PROMPTS = ["spacecraft", "satellite", "space probe", "space vehicle", "spacecraft with rigid body and appendages",
                 "artificial object in space with panels and antennas"]


class TeacherParams(_Section):
    backend: str = _f(  # one of pipeline.teacher_table.TEACHER_TABLE, registered ones included
        SIMULATED, "simulated (SIMULATOR of the synthetic benchmark only) | sam3 | imported")
    prompts: list[str] = _f(PAPER_PROMPTS, "eq:prompt-set, fixed order p1..p6", min_length=1)
    base_prompt_index: int = _f(0, "the annotation-free-style control's single prompt", ge=0)
    vflip_base_prompt: bool = _f(True, "also run the base prompt on the vertically flipped image (AFS control)")
    splits: list[Literal[SPLITS]] = _f(list(SPLITS), min_length=1)
    checkpoint: str | None = _f(None, "sam3: local SAM 3 directory (save_pretrained layout)")
    imported_dir: str | None = _f(None, "imported: directory in the documented layout")
    dtype: Literal["auto", "fp32", "bf16"] = _f(
        "auto", "sam3: auto = bf16 on CUDA (fp32+TF32 without bf16); on CPU bf16 with AMX, or avx512_bf16 on AMD, "
        "else fp32")
    engine: Literal[TEACHER_ENGINES] = _f(
        "auto", "sam3: how the bf16 CPU path runs; auto = oneDNN-fused MLPs with AMX, OpenVINO's attention with "
        "avx512_bf16 on AMD, else torch")
    batch_size: int = _f(0, "images per SAM 3 forward; 0 = from free GPU memory (2 on a CPU)", ge=0, le=4096)
    compile: bool = _f(False, "sam3: torch.compile the vision encoder on CUDA (pays after warm-up)")
    score_threshold: float = _f(0.3, "sam3: queries scoring <= this are no candidate", ge=0, le=1)
    mask_threshold: float = _f(0.5, "sam3: binarise the chosen query's mask probability", ge=0, le=1)
    seed: int = _f(0, "simulated teacher (SIMULATOR) seed", ge=0)
    cache_dir: str = _f(".cache/teacher", "content-addressed cache outside DVC outs")
    options: dict[str, Any] = _f({}, "a plug-in backend's own settings, checked by its spec's model (written only "
                                     "when set)")

    @model_validator(mode="after")
    def _base(self):
        if self.base_prompt_index >= len(self.prompts):
            raise ValueError(f"teacher.base_prompt_index={self.base_prompt_index} but only {len(self.prompts)} prompts")
        for i, p in enumerate(self.prompts):
            if not p.strip():
                raise ValueError(f"teacher.prompts[{i}]={p!r} must be a non-empty string")
        if len({p.strip().lower() for p in self.prompts}) != len(self.prompts):
            raise ValueError(f"teacher.prompts has duplicates: {self.prompts}")
        for key in teacher_spec(self.backend).settings:  # each backend's required settings (teacher_table)
            if not getattr(self, key):
                raise ValueError(f"teacher.{key} is required for backend {self.backend}")
        return self

    @field_validator("backend")
    @classmethod
    def _known(cls, v: str) -> str:
        teacher_spec(v)  # ValueError naming the backends
        return v

    @field_validator("options")
    @classmethod
    def _options(cls, v: dict, info: ValidationInfo) -> dict:
        """Validate the backend's own settings through its spec's model (``TeacherSpec.options``); none without one."""
        if "backend" not in info.data:  # refused already
            return v
        model = teacher_spec(info.data["backend"]).options
        if model is None and v:
            raise ValueError(f"backend {info.data['backend']} takes none (set teacher.backend to the plug-in's name too)")
        return validate(v, f"backend {info.data['backend']}", load(model)) if model is not None else v

    @model_serializer(mode="wrap")
    def _unset_options_unwritten(self, dump):
        """Leave out the ``options`` key while it is empty.

        So params.yaml, label.json and the fingerprints of the built-in backends stay as they were.
        """
        out = dump(self)
        if not out.get("options"):
            out.pop("options", None)
        return out


class ConsensusParams(_Section):
    vote_threshold: float = _f(0.5, "eq:majority-vote: M = [A >= 0.5]; a tie is foreground", ge=0, le=1)


class GeometryParams(_Section):
    sdf_quantile: float = _f(0.95, "eq:sdf-target: s = q_0.95(|D~|)", ge=0, le=1)
    sdf_min_scale: float = _f(1e-6, "eq:sdf-target: s = 1 when q < this", ge=0)
    skeleton_min_distance: float = _f(1.0, "drop skeleton points with d_in <= this (px)", ge=0)
    n_prompts: int = _f(6, "eq:valid-prompt-ratio denominator; must equal the teacher's prompt count", ge=1)
    conf_offset: float = _f(0.35, "eq:confidence-gate", ge=0, lt=1)
    valid_offset: float = _f(0.20, "eq:validity-gate", ge=0, lt=1)
    area_temperature: float = _f(0.9, "eq:area-gate", gt=0)
    area_floor: float = _f(0.05, "eq:area-gate lower clip", ge=0, le=1)
    eps: float = _f(1e-6, ge=0)


class ConfidenceParams(_Section):
    criterion: Literal["agreement", "mean_score"] = _f("agreement", "eq:foreground-agreement c_i | mean valid score")
    threshold: float = _f(0.80, ge=0, le=1)
    min_valid: int = _f(2, ge=0)


class AfsParams(_Section):
    base_prompt: str = _f("spacecraft", "the single prompt (looked up in teacher.zarr attrs.prompts)")
    score_threshold: float = _f(0.60, "drop images whose base-prompt score is below this", ge=0, le=1)
    fusion: Literal["intersection", "union"] = _f("intersection", "of the image and flipped-view masks")


class GabiParams(_Section):
    epochs: int = _f(30, ge=1)
    lambda_dist: float = _f(0.002, "ungated L1 distance-field regression", ge=0)
    lambda_boundary: float = _f(0.05, "BCE inside the pseudo-boundary band |D^T| <= sdf_band", ge=0)


class AdaptiveParams(_Section):
    ratio_boundary: float = _f(0.5, "r >= this: anchored; below: geometry_only", ge=0, le=1)
    anchor_weight: float = _f(0.1, "weight of BCE(Z, frozen Stage-I probabilities)", ge=0)
    anchor_geometry_only: bool = _f(False, "keep the weak anchor in geometry_only mode (paper: no anchoring)")


def with_recipe_parts(fields: type[_Section], section: str) -> type[_Section]:
    """Build a section model: ``fields``'s fields with ``section``'s recipe parts placed among them.

    The recipe parts are those of :data:`pipeline.methods.PARTS`; each is ``type | None``, defaulting to None (the
    recipe's value), with its declared bounds and doc line.

    Parameters
    ----------
    fields : type
        A section model holding the section's other fields, in params.yaml's order (its validators are not kept:
        subclass the result to add them).
    section : str
        The params section whose recipe parts to add.

    Returns
    -------
    type
        A pydantic model to subclass.
    """
    parts = {p.name: p for p in parts_of(section)}
    specs = {k: (info.annotation, copy.copy(info)) for k, info in fields.model_fields.items()}
    specs |= {n: (p.type | None, Field(None, description=p.description, **p.bounds)) for n, p in parts.items()}
    order = interleave(fields.model_fields, {n: p.schema_after for n, p in parts.items()})
    return create_model(f"_{fields.__name__.strip('_')}WithParts", __base__=_Section, __module__=__name__,
                        **{k: specs[k] for k in order})


def fill_recipe(data, section: str, recipe: str):
    """Set every absent or None recipe part of raw section ``data`` to ``recipe``'s value.

    Anything else (not a mapping, an unknown recipe) is returned as is, for the schema to name.
    """
    if not isinstance(data, Mapping) or recipe not in RECIPES:
        return data
    out = dict(data)
    for k, v in RECIPES[recipe].get(section, {}).items():
        if out.get(k) is None:
            out[k] = v
    return out


def unresolved(values: Mapping[str, Any], raw: Mapping[str, Any]) -> dict:
    """Set the recipe parts that ``raw`` left null back to None in validated ``values``, as params.yaml shows them.

    Parameters
    ----------
    values : Mapping
        Validated params (every recipe part resolved to its recipe's value).
    raw : Mapping
        The params as written, before validation.

    Returns
    -------
    dict
        A deep copy of ``values`` with each recipe part (:func:`pipeline.methods.recipe_parts`) that ``raw``
        leaves absent or null set to None.
    """
    out = copy.deepcopy(dict(values))
    for dotted in recipe_parts():
        sec, key = dotted.split(".")
        if (raw.get(sec) or {}).get(key) is None:
            out[sec][key] = None
    return out


class AugmentParams(_Section):
    """Target-consistent augmentation (pipeline.augment) when ``train.augment`` is on."""

    hflip: float = _f(0.5, "probability of a left-right flip", ge=0, le=1)
    vflip: float = _f(0.5, "probability of an up-down flip", ge=0, le=1)
    rot90: bool = _f(True, "a uniformly drawn multiple of 90 degrees (square images; 180 otherwise)")
    scale_probability: float = _f(0.5, "probability of a scale/crop jitter", ge=0, le=1)
    scale_range: Annotated[list[float], _POSITIVE_RANGE] = _f(
        [0.75, 1.33], "zoom factor range (log-uniform; < 1 zooms out, padding black)", min_length=2, max_length=2)
    photometric_probability: float = _f(0.8, "probability of the photometric part", ge=0, le=1)
    brightness: float = _f(0.15, "additive brightness shift up to this (fraction of full scale)", ge=0, le=1)
    contrast: float = _f(0.3, "contrast factor in [1/(1+x)..1+x] about the image mean", ge=0, le=10)
    gamma: float = _f(0.3, "gamma in [1/(1+x), 1+x] (log-uniform)", ge=0, le=10)
    glare_probability: float = _f(0.15, "probability of a saturated glare spot", ge=0, le=1)
    flare_probability: float = _f(0.0, "probability of a lens flare: a bright source, maybe off the frame, with ghost "
                                  "discs along a line through it (albumentations' RandomSunFlare model; "
                                  "docs/decisions.md); 0 = none", ge=0, le=1)
    exposure_range: Annotated[list[float], _POSITIVE_RANGE] = _f(
        [1.0, 1.0], "exposure gain range (log-uniform), applied before the other photometric changes; < 1 "
        "underexposes; [1, 1] = none", min_length=2, max_length=2)
    blur_probability: float = _f(0.2, "probability of a Gaussian blur", ge=0, le=1)
    blur_sigma: float = _f(1.5, "largest blur sigma (px)", ge=0, le=50)
    noise_std: float = _f(0.03, "largest Gaussian sensor-noise std (fraction of full scale)", ge=0, le=1)


class _TrainFields(_Section):
    """``train``'s fields that are no recipe part (:class:`TrainParams` adds those)."""

    channels: list[PositiveInt] = _f([24, 48, 96], "TinyUNet encoder widths", min_length=1)
    norm: Literal["batch", "group"] = _f("batch", "TinyUNet normalisation: batch (paper) | group (GroupNorm, "
                                         "8 channels per group: no batch statistics)")
    bn_momentum: float = _f(0.1, "BatchNorm running-statistics momentum (PyTorch's; paper silent)", gt=0, le=1)
    precise_bn: bool = _f(False, "re-estimate BN running statistics over the training set before each "
                                 "validation (precise BN; not in the paper)")
    weight_decay: float = _f(1e-4, ge=0)
    lr_stage1: float = _f(5e-4, gt=0)
    lr_stage2: float = _f(1e-4, gt=0)
    decay_fraction: float = _f(0.2, "schedule wsd: share of the optimizer steps in the decay phase", gt=0, le=1)
    dice_weight: float = _f(0.2, "eq:raw-loss", ge=0)
    pos_weight_max: float = _f(500.0, "eq:positive-weight clip", gt=0)
    sdf_band: float = _f(0.55, "eq:pseudo-boundary-band", gt=0)
    sdf_base_weight: float = _f(0.15, "eq:sdf-weight", ge=0)
    area_eps: float = _f(1e-5, "eq:area-error", gt=0)
    loss_eps: float = _f(1e-6, gt=0)
    lambda_sdf: float = _f(0.002, "eq:refine-loss", ge=0)
    lambda_skel: float = _f(0.001, "eq:refine-loss", ge=0)
    lambda_area: float = _f(0.05, "eq:refine-loss", ge=0)
    stage2_select: Literal["last", "best_val"] = _f("last", "paper: the last Stage-II epoch")
    recipe: Literal[tuple(RECIPES)] = _f("paper", "training recipe: a bundle of the parts marked 'recipe part' "
                                                  "(docs/stability.md); an explicit part value wins")
    validate_low_res: bool = _f(False, "Stage I with low_res_fraction: validate after the half-side epochs too "
                                       "(the full validation curve, for studies). Off: no rule or selection reads "
                                       "them -- until: plateau scores full-side epochs, a weight average or the "
                                       "last epoch is kept -- so they are skipped and logged as NaN; the weights "
                                       "are the same (docs/decisions.md)")
    step_budget: int = _f(0, "Stage I with until: plateau: optimizer steps at most, warm-up and decay included "
                             "(0 = none; distill --time writes it)", ge=0)
    time_budget: str | None = _f(None, "what distill --time converted into train.step_budget (a record; not read "
                                       "by training)")
    time_cap_factor: float = _f(4.0, "distill --time: when the time allows the whole Stage-I run at more epochs, "
                                      "raise train.epochs_stage1 up to this multiple of it (the resolution "
                                      "schedule scales with it; until: plateau may still stop sooner). 4 = the "
                                      "largest measured (docs/student.md, four times the steps at 128^2); 1 = the "
                                      "cap never moves", ge=1)
    time_raised_from: int = _f(0, "what train.epochs_stage1 was before distill --time raised it (a record; 0 = "
                                  "not raised; not read by training)", ge=0)
    plateau_gain: float = _f(0.005, "until: plateau: the stable phase stops when its second half gains less "
                                    "than this validation Image IoU over its first half", ge=0)
    plateau_min_epochs: int = _f(8, "until: plateau: stable epochs before the rule may stop", ge=2)
    plateau_min_steps: int = _f(256, "until: plateau: optimizer steps of scored epochs before the rule may stop, "
                                     "so that few training images (few steps an epoch) do not stop the run on a "
                                     "window shorter than its noise (256: the 8 epochs of the benchmark's 270 "
                                     "images at batch 8; docs/decisions.md); 0 = epochs only", ge=0)
    holdout_fraction: float = _f(0.1, "until: plateau without validation masks: share of the pseudo-labelled "
                                      "training images held out and scored against their vote", gt=0, lt=1)
    channels_last: bool = _f(True)
    augment_hflip: bool = _f(False, "the paper states no augmentation")
    augmentation: AugmentParams = Field(default_factory=AugmentParams)
    num_threads: int = _f(0, "torch CPU threads (changes numerics: tracked and in the resume key); "
                             "0 = torch default", ge=0)
    val_bf1_tolerance: float = _f(2, "Boundary F1 tolerance (px) of the validation tie-break", ge=0)
    confidence: ConfidenceParams = Field(default_factory=ConfidenceParams)
    afs: AfsParams = Field(default_factory=AfsParams)
    gabi: GabiParams = Field(default_factory=GabiParams)
    adaptive: AdaptiveParams = Field(default_factory=AdaptiveParams)


class TrainParams(with_recipe_parts(_TrainFields, "train")):
    """The ``train`` section: :class:`_TrainFields` and the recipe parts of :data:`pipeline.methods.PARTS`."""

    @model_validator(mode="before")
    @classmethod
    def _recipe_parts(cls, data):
        return fill_recipe(data, "train", data.get("recipe", "paper") if isinstance(data, Mapping) else "paper")

    @model_validator(mode="after")
    def _branches_fold_through_batch_norm(self):
        if self.expand_branches and self.norm != "batch":
            raise ValueError(f"train.expand_branches needs train.norm: batch (each branch's BatchNorm folds into "
                             f"its convolution; {self.norm} normalisation does not fold)")
        return self

    @model_validator(mode="after")
    def _plateau_decay(self):
        if self.until == "plateau" and self.decay_fraction >= 1:
            raise ValueError("train.decay_fraction must be < 1 under until: plateau (its decay is f / (1 - f) of "
                             "the stable phase)")
        return self


class ProtocolParams(_Section):
    """Which (method, seed) training runs exist in the DAG; a warm-started method needs Stage I at its seed."""

    runs: dict[str, list[int]] = _f({STAGE_ONE: [42], PROPOSED: [42]}, "method -> seeds; [] = no run")
    supervised_ceiling: bool = _f(False, "allow runs of supervised_ceiling: trained on REFERENCE masks, "
                                         "NOT annotation-free (a ceiling for the student recipe)")
    seeds_per_stage: int = _f(1, "training runs of a method per DVC stage, trained one after another in one "
                                 "process: 1 = a stage per (method, seed), train_<method>@<seed> (what geodistill "
                                 "run spreads over workers); n > 1 = groups of n seeds (rerun geodistill dag after "
                                 "editing runs)", ge=1, le=1000)

    @field_validator("runs")
    @classmethod
    def _runs(cls, v):
        for m, seeds in v.items():
            if m not in METHODS:
                raise ValueError(f"unknown method {m!r} (one of {', '.join(METHODS)})")
            if len(set(seeds)) != len(seeds):
                raise ValueError(f"{m}: seeds must be distinct")
            if METHODS[m].init == "stage1":
                missing = sorted(set(seeds) - set(v.get(STAGE_ONE, [])))
                if missing:
                    raise ValueError(f"{m} warm-starts from {STAGE_ONE}, which has no run for seed(s) {missing}")
        return {m: list(v.get(m, [])) for m in METHODS}

    @model_validator(mode="after")
    def _ceiling_flag(self):
        gated = [m for m, seeds in self.runs.items() if seeds and not METHODS[m].annotation_free]
        if gated and not self.supervised_ceiling:
            raise ValueError(f"protocol.runs lists {gated}, which train on reference masks (not annotation-free); "
                             f"set protocol.supervised_ceiling: true to allow them")
        return self


class _CalibrateFields(_Section):
    """``calibrate``'s fields that are no recipe part."""

    plateau_tolerance: float = _f(0.005, "tau_rule plateau: taus within this much mean IoU of the best", ge=0, le=1)
    smooth_halfwidth: int = _f(5, "tau_rule smooth: moving-average half-width in grid points", ge=0, le=1000)
    grid_start: float = _f(0.05, ge=0, le=1)
    grid_stop: float = _f(0.95, ge=0, le=1)
    grid_step: float = _f(0.01, ge=1e-6, le=1)
    fixed_tau: float = _f(0.5, "eq:inference-mask fallback / fixed-threshold comparisons", ge=0, le=1)
    reliability_bins: int = _f(10, "equal-width probability bins of the validation reliability diagram and ECE",
                               ge=2, le=1000)


class CalibrateParams(with_recipe_parts(_CalibrateFields, "calibrate")):
    """The ``calibrate`` section: :class:`_CalibrateFields` and its recipe part (``tau_rule``)."""

    @model_validator(mode="before")
    @classmethod
    def _recipe_parts(cls, data):
        return fill_recipe(data, "calibrate", "paper")

    @model_validator(mode="after")
    def _grid(self):
        if self.grid_stop < self.grid_start:
            raise ValueError("calibrate.grid_stop must be >= calibrate.grid_start")
        return self


class EvaluateParams(_Section):
    bf1_tolerance: float = _f(2, "Boundary F1 tolerance (px)", ge=0)
    small_region_max_fraction: float = _f(0.01, "small-region IoU: GT components under 1 % of the frame", ge=0, le=1)
    tiny_target_max_fraction: float = _f(0.002, "size split: a tiny target covers under 0.2 % of the frame",
                                         ge=0, le=1)
    bootstrap_resamples: int = _f(10000, ge=1)
    bootstrap_seed: int = _f(0, ge=0)
    ci: float = _f(0.95, ge=0.5, le=0.999)
    interval: Literal[GAIN_INTERVALS] = _f(
        SEED_IMAGE_T, "gain CIs (docs/intervals.md): seed_image_t = the effect on these test spacecraft (seeds + "
        "images within spacecraft, t); seed_cluster_t = on spacecraft like these (C - 1 df: wide with 3); "
        "seed_bootstrap = the former seed-aware bootstrap (no stated estimand)")


class ReportParams(_Section):
    qualitative_images: int = _f(4, ge=0, le=64)
    pseudo_target_images: int = _f(3, ge=0, le=64)


INT8_CALIBRATIONS = ("percentile", "minmax")
INT8_WEIGHT_BITS = (7, 8)


class DeployParams(_Section):
    export_method: str = _f(PROPOSED)
    export_seed: int = _f(42)
    opset: int = _f(17, "ONNX opset", ge=9, le=30)
    parity_atol: float = _f(1e-4, "export parity: max |logit difference| vs PyTorch", ge=0)
    benchmark_warmup: int = _f(5, ge=0)
    benchmark_iters: int = _f(30, "batch-1 latency = median of this many calls", ge=1)
    benchmark_batches: list[PositiveInt] = _f([1, 4, 16], "throughput = best images/s over these", min_length=1)
    benchmark_resolution: int | None = _f(None, "null = the deploy bundle's working resolution", ge=8)
    benchmark_variants: list[str] = _f(BENCHMARK_VARIANTS, min_length=1)
    int8_calibration_images: int = _f(64, "training-split images (no masks) for int8 activation ranges", ge=1)
    int8_calibration: Literal[INT8_CALIBRATIONS] = _f("percentile")
    int8_percentile: float = _f(99.999, gt=50, le=100)
    int8_weight_bits: Literal[INT8_WEIGHT_BITS] = _f(7, "int8 weight range: 7 = [-64, 64], no u8*s8 pair sum "
                                                     "saturates int16 on CPUs without VNNI, so every x86 CPU gives "
                                                     "the same masks; 8 = [-127, 127], those masks only on VNNI/AMX CPUs")
    int8_min_mask_iou: float = _f(0.9, "below this mean int8-vs-PyTorch mask IoU the bundle ships fp32 only "
                                       "(deploy.json and contract.json say why)", ge=0, le=1)
    target_latency_ms: float = _f(40, "CPU target at 384x384, batch 1 (reported, never asserted)", ge=0)
    target_resolution: int = _f(384, "the size the latency target is judged at", ge=1)
    target_iou_drop: float = _f(0.005, "a fast path may lose at most this much validation Image IoU", ge=0)

    @field_validator("benchmark_variants")
    @classmethod
    def _variants(cls, v):
        v = list(dict.fromkeys(map(engine_name, v)))  # an old name -> its engine (ENGINE_ALIASES)
        bad = [x for x in v if x not in BENCHMARK_VARIANTS]
        if bad:
            raise ValueError(f"unknown variant(s) {bad} (one of {', '.join(BENCHMARK_VARIANTS)})")
        return v


class ReviewParams(_Section):
    """Masks a person corrected (``geodistill review import``) and how the DAG uses them (null: not at all)."""

    corrections: str | None = _f(None, "a corrections artifact (geodistill review import --out); null = none")
    mode: Literal["validate", "replace"] = _f(
        "validate", "validate: the corrected training images leave training and become validation masks "
                    "(the student stays annotation-free) | replace: they replace those images' voted masks "
                    "in training (NOT annotation-free; needs human_targets: true)")
    human_targets: bool = _f(False, "allow mode replace: human-corrected masks enter the loss, so the students "
                                    "are NOT annotation-free (labelled so, like protocol.supervised_ceiling)")
    top: int = _f(50, "stage review_export: how many training images to export for a person to check "
                      "(artifacts/review: ranked.csv, Label Studio and CVAT imports)", ge=1)
    ranking: Literal["combined", "gate", "disagreement"] = _f(
        "combined", "stage review_export: the ranking (pipeline.review.ranking; combined: mean percentile rank "
                    "of 1 - g and h | gate | disagreement)")

    @model_validator(mode="after")
    def _replace_flag(self):
        if self.corrections and self.mode == "replace" and not self.human_targets:
            raise ValueError("mode replace trains on human-corrected masks (not annotation-free); "
                             "set review.human_targets: true to allow it")
        return self


class Params(_Section):
    """The whole params file."""

    @model_validator(mode="before")
    @classmethod
    def _recipe_parts(cls, data):
        """Recipe parts of other sections follow ``train.recipe``."""
        if not isinstance(data, Mapping):
            return data
        train = data.get("train")
        recipe = train.get("recipe", "paper") if isinstance(train, Mapping) else "paper"
        return {**data, "calibrate": fill_recipe(data.get("calibrate") or {}, "calibrate", recipe)}

    profile: str = _f("paper", "name of the profile this file was generated from (report folder)")
    data: DataParams = Field(default_factory=DataParams)
    teacher: TeacherParams = Field(default_factory=TeacherParams)
    consensus: ConsensusParams = Field(default_factory=ConsensusParams)
    geometry: GeometryParams = Field(default_factory=GeometryParams)
    train: TrainParams = Field(default_factory=TrainParams)
    protocol: ProtocolParams = Field(default_factory=ProtocolParams)
    calibrate: CalibrateParams = Field(default_factory=CalibrateParams)
    evaluate: EvaluateParams = Field(default_factory=EvaluateParams)
    report: ReportParams = Field(default_factory=ReportParams)
    deploy: DeployParams = Field(default_factory=DeployParams)
    review: ReviewParams = Field(default_factory=ReviewParams)

    @model_validator(mode="after")
    def _cross(self):
        if self.geometry.n_prompts != len(self.teacher.prompts):
            raise ValueError(f"geometry.n_prompts={self.geometry.n_prompts} must equal the "
                             f"{len(self.teacher.prompts)} teacher.prompts")
        # the export stage reads this run's checkpoint: refused here in one line, not by dvc repro at the end
        method, seed = self.deploy.export_method, self.deploy.export_seed
        trained = self.protocol.runs.get(method, [])
        if seed not in trained:
            raise ValueError(f"deploy.export_seed={seed}: protocol.runs has no {method} run with this seed "
                             f"(its seeds: {trained}); set deploy.export_seed to one of them")
        return self


PAPER = Params()


def validate(raw: Mapping[str, Any], origin: str = "params", model: type[BaseModel] = Params) -> dict:
    """Validate a whole params mapping (or one section's, with its ``model``) and fill in the defaults.

    Parameters
    ----------
    raw : Mapping
        The params as read (a whole file, or one section).
    origin : str
        What the error line names first (the file, or ``params: SECTION``).
    model : type of pydantic.BaseModel
        The schema: :class:`Params` for a whole file, a section's model for one section.

    Returns
    -------
    dict
        The effective params (defaults filled in, recipe parts resolved).

    Raises
    ------
    pipeline.runtime.errors.InputError
        On the first bad value or unknown key, one line naming ``origin`` and the dotted key.
    """
    try:
        return model.model_validate(dict(raw)).model_dump(mode="python")
    except ValidationError as err:
        e = err.errors()[0]
    key = ".".join(str(p) for p in e["loc"])
    msg = "unknown key" if e["type"] == "extra_forbidden" else e["msg"].removeprefix("Value error, ")
    # a whole section's (or mapping's) value is too long to repeat; its validator's message names the key
    shown = "" if e["type"] in ("extra_forbidden", "missing") or isinstance(e.get("input"), Mapping) \
        else f"={e.get('input')!r}"
    raise InputError(f"{origin}: {key}{shown}: {msg}" if key else f"{origin}: {msg}")


def validate_section(name: str, cfg: Mapping[str, Any]) -> dict:
    """Validate one section on its own (library entry points called outside a stage).

    Parameters
    ----------
    name : str
        The section's key in :class:`Params` (``"train"``, ``"deploy"``, ...).
    cfg : Mapping
        The section's raw values.

    Returns
    -------
    dict
        The section's effective values (defaults filled in).

    Raises
    ------
    pipeline.runtime.errors.InputError
        From :func:`validate`, naming ``params: NAME`` and the bad key.
    """
    return validate(cfg, f"params: {name}", Params.model_fields[name].annotation)


def deep_merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict:
    """Merge ``over`` into a copy of ``base``, mapping by mapping.

    ``protocol.runs`` (the key ``runs``) is replaced whole, not merged: a profile's runs are the runs.

    Parameters
    ----------
    base : Mapping
        The values overridden.
    over : Mapping
        The overriding values; a nested mapping merges into ``base``'s mapping at the same key.

    Returns
    -------
    dict
        A new mapping; neither argument is changed.
    """
    out = copy.deepcopy(dict(base))
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping) and k != "runs":
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def parse_override(item: str) -> tuple[list[str], Any]:
    """Parse one ``--set`` override: ``"train.epochs_stage1=3"`` -> (["train", "epochs_stage1"], 3).

    Parameters
    ----------
    item : str
        ``key.path=value``; the value is parsed as YAML (YAML 1.2 numbers: ``1e-4`` is a float).

    Returns
    -------
    tuple of (list of str, object)
        The key path and the parsed value.

    Raises
    ------
    pipeline.runtime.errors.InputError
        When ``item`` has no ``=``, an empty key or a value that is not valid YAML.
    """
    if "=" not in item:
        raise InputError(f"--set {item!r}: expected key.path=value")
    key, _, raw = item.partition("=")
    key = key.strip()
    if not key:
        raise InputError(f"--set {item!r}: empty key")
    try:
        value = load_yaml(raw)
    except yaml.YAMLError:
        raise InputError(f"--set {item!r}: value is not valid YAML") from None
    return key.split("."), value


def set_path(d: dict, keys: list[str], value: Any) -> None:
    """Set ``d[k1][k2]...[kn] = value``, creating (or replacing non-mapping) intermediate levels."""
    for k in keys[:-1]:
        if not isinstance(d.get(k), dict):
            d[k] = {}
        d = d[k]
    d[keys[-1]] = value


def get_path(d: Mapping[str, Any], dotted: str) -> Any:
    """Read the value at a dotted key path (``"train.epochs_stage1"``).

    Parameters
    ----------
    d : Mapping
        Nested mappings (params).
    dotted : str
        The key path, levels joined by ``.``.

    Returns
    -------
    object
        The value there (a missing key raises KeyError).
    """
    cur: Any = d
    for k in dotted.split("."):
        cur = cur[k]
    return cur


def read_yaml_mapping(path: str | Path, what: str = "params file") -> dict:
    """Read a YAML file whose top level is a mapping (params, protocol files).

    Parameters
    ----------
    path : str or Path
        The file.
    what : str
        What the file is, for the error line (``"params file"``).

    Returns
    -------
    dict
        Its top-level mapping (an empty file reads as ``{}``).

    Raises
    ------
    pipeline.runtime.errors.InputError
        Naming the file when it is missing, is not valid YAML or is not a mapping at the top level.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: {what} not found")
    try:
        raw = load_yaml(path.read_text()) or {}
    except yaml.YAMLError as e:
        raise InputError(f"{path}: invalid YAML ({str(e).splitlines()[0]})") from None
    if not isinstance(raw, dict):
        raise InputError(f"{path}: {what} must be a mapping at the top level")
    return raw


#: the override key that names a profile: only the commands that switch profile accept it
PROFILE_KEY = "profile"


def load_params(path: str | Path = DEFAULT_PARAMS, overrides: Iterable[str] = (),
                base: Mapping[str, Any] | None = None) -> dict:
    """Load and validate the params of ``path`` (or of raw ``base``, ``path`` naming it) with ``--set`` overrides.

    ``--set profile=NAME`` is refused: only the commands that switch profile read profiles.

    Parameters
    ----------
    path : str or Path
        The params file (default :data:`DEFAULT_PARAMS`); with ``base`` it only names the params in errors.
    overrides : iterable of str
        ``key.path=value`` overrides (:func:`parse_override`), applied in order over the file.
    base : Mapping, optional
        Raw params to use instead of reading ``path``.

    Returns
    -------
    dict
        The effective params (:func:`validate`).

    Raises
    ------
    pipeline.runtime.errors.InputError
        When an override sets :data:`PROFILE_KEY`; also from :func:`parse_override`, :func:`read_yaml_mapping`
        and :func:`validate`.
    """
    parsed = [parse_override(o) for o in overrides]
    if any(keys == [PROFILE_KEY] for keys, _ in parsed):
        raise InputError(f"--set {PROFILE_KEY}=...: this command reads its params file ({path}); "
                         f"switch profile with `geodistill profile NAME`")
    raw = read_yaml_mapping(path) if base is None else copy.deepcopy(dict(base))
    for keys, value in parsed:
        set_path(raw, keys, value)
    return validate(raw, str(path) if not parsed else f"{path} (with --set)")


def section(params: Mapping[str, Any], name: str) -> dict:
    """Copy one section out of validated params.

    Parameters
    ----------
    params : Mapping
        Validated params.
    name : str
        The section's key.

    Returns
    -------
    dict
        A deep copy of the section.

    Raises
    ------
    pipeline.runtime.errors.InputError
        When ``params`` has no mapping at ``name``.
    """
    if not isinstance(params.get(name), Mapping):
        raise InputError(f"params: section {name!r} missing")
    return copy.deepcopy(dict(params[name]))


def require(cfg: Mapping[str, Any], key: str, where: str, *, kind: type | tuple = object,
            lo: float | None = None, hi: float | None = None) -> Any:
    """Read ``cfg[key]``, checked for type and range (for mappings the schema does not cover).

    Parameters
    ----------
    cfg : Mapping
        The mapping read.
    key : str
        The key required in it.
    where : str
        The mapping's dotted place, for the error line (``where.key``).
    kind : type or tuple of type
        The accepted type(s); ``object`` accepts any.  A bool is refused where a number is asked for.
    lo, hi : float, optional
        Inclusive bounds; None leaves that side open.

    Returns
    -------
    object
        The value, unchanged.

    Raises
    ------
    pipeline.runtime.errors.InputError
        Naming ``where.key`` when it is missing, of the wrong type or out of ``[lo, hi]``.
    """
    if key not in cfg:
        raise InputError(f"params: {where}.{key} missing")
    v = cfg[key]
    if kind is not object and not isinstance(v, kind) or (isinstance(v, bool) and kind in (int, float, (int, float))):
        raise InputError(f"params: {where}.{key}={v!r} has the wrong type")
    if lo is not None and v < lo or hi is not None and v > hi:
        raise InputError(f"params: {where}.{key}={v!r} out of range [{lo}, {hi}]")
    return v
