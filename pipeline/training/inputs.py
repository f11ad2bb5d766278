"""What a training run reads, torch-free, from opened artifacts or an artifacts directory.

Pseudo-targets for training, reference masks for validation (and for the supervised ceiling only), and human
corrections.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from pipeline import catalog
from pipeline.artifacts.lineage import require_same_run
from pipeline.artifacts.store import open_artifact
from pipeline.augment import GeometryConstants, recompute_geometry
from pipeline.evaluation.inference import REVIEW_MODE_KEY, corrected_validation, load_student, require_mode
from pipeline.geometry import area_ratio
from pipeline.methods import PARTS, SUPERVISED_CEILING, Method, get_method, input_artifacts, uses_confidence
from pipeline.training.filters import afs_fuse, afs_keep, confidence_pass, mean_valid_score, pass_ratio
from pipeline.params import section
from pipeline.runtime.errors import ArtifactError, InputError
from pipeline.training.streaming import LazyRows, MappedRows, RowSource, row_means, select_rows

__all__ = ["MODES", "MODE_KEY", "TrainData", "ValData", "read_rows", "load_inputs", "replace_targets", "load_init",
           "MethodInputs", "open_method"]

#: how the corrected artifact enters a run (:mod:`pipeline.review.apply` says what each means)
MODES = ("validate", "replace")
MODE_KEY = REVIEW_MODE_KEY


@dataclasses.dataclass
class TrainData:
    """A method's training rows, in manifest order, as arrays or row sources.

    Attributes
    ----------
    image_ids : list of str
        The rows' image ids.
    images : numpy.ndarray or RowSource
        uint8 [N, R, R, 3].
    mask : numpy.ndarray or RowSource
        The region target [N, R, R]: the voted mask M^T (bool), the agreement map A (float32), a fused AFS mask,
        or a reference mask for the supervised ceiling.
    area : numpy.ndarray
        a_i = (1 / HW) sum_x M_i^T(x) (eq:pseudo-area), float32 [N].
    gate : numpy.ndarray
        g_i (eq:reliability-gate), float32 [N] in [0, 1]; 1 where the method applies no gate.
    sdf : numpy.ndarray or RowSource or None
        The pseudo signed distance target D^T [N, R, R] (eq:sdf-target); None without geometry.
    skeleton : numpy.ndarray or RowSource or None
        The skeleton target K^T [N, R, R]; None without geometry.
    stats : dict
        The filter's outcome (rows, pass ratios, corrections applied), recorded with the run.
    geometry : GeometryConstants
        The constants ``sdf`` and ``skeleton`` were computed with: an augmented rescale recomputes them alike.
    """

    image_ids: list
    images: np.ndarray | RowSource
    mask: np.ndarray | RowSource
    area: np.ndarray
    gate: np.ndarray
    sdf: np.ndarray | RowSource | None = None
    skeleton: np.ndarray | RowSource | None = None
    stats: dict = dataclasses.field(default_factory=dict)
    geometry: GeometryConstants = dataclasses.field(default_factory=GeometryConstants)

    def __len__(self) -> int:  # noqa: D105 -- the rows
        return len(self.image_ids)

    def subset(self, sel: np.ndarray, **changes) -> TrainData:
        """Select rows, nothing read from disk.

        Parameters
        ----------
        sel : numpy.ndarray
            Row positions.
        **changes
            Fields replaced in the result (``stats=...``).

        Returns
        -------
        TrainData
            The rows ``sel``, with ``changes``.
        """
        rows = {f: select_rows(getattr(self, f), sel) for f in ("images", "mask", "sdf", "skeleton")
                if getattr(self, f) is not None}
        return dataclasses.replace(self, image_ids=[self.image_ids[k] for k in sel], area=self.area[sel],
                                   gate=self.gate[sel], **{**rows, **changes})


@dataclasses.dataclass
class ValData:
    """Validation images and their reference masks (``split == "val"`` rows with a mask), in memory.

    Attributes
    ----------
    image_ids : list of str
        The rows' image ids.
    images : numpy.ndarray
        uint8 [V, R, R, 3].
    masks : numpy.ndarray
        Reference masks, bool [V, R, R].
    """

    image_ids: list
    images: np.ndarray
    masks: np.ndarray

    def __len__(self) -> int:  # noqa: D105 -- the rows
        return len(self.image_ids)


def _check_order(art, ids: list, what: str) -> None:
    got = getattr(art, "attrs", {}).get("image_ids")
    if got is not None and list(got) != list(ids):
        raise ArtifactError(f"{art.path}: image order differs from the manifest ({what}); "
                            "rerun the stages after prepare")


def read_rows(art, name: str, idx: np.ndarray) -> np.ndarray:
    """Read rows of one array of an opened artifact (:class:`LazyRows`).

    Parameters
    ----------
    art : Artifact
        An opened zarr artifact.
    name : str
        The array's name.
    idx : numpy.ndarray
        Row indices.

    Returns
    -------
    numpy.ndarray
        The rows, in ``idx``'s order.
    """
    return np.asarray(LazyRows(art[name], idx))


def training_inputs(method: Method, cfg: Mapping[str, Any]) -> tuple[str, ...]:
    """List the artifacts :func:`training_data` reads for ``method`` (never ``reference``)."""
    return tuple(n for n in input_artifacts(method, cfg["confidence"]["criterion"]) if n != "reference")


def _train_rows(manifest) -> tuple[list, np.ndarray]:
    """Manifest image ids (all rows) and the indices of the ``split == "train"`` rows."""
    df = manifest.df
    train_idx = np.flatnonzero((df["split"] == "train").to_numpy())
    if len(train_idx) == 0:
        raise InputError(f"{manifest.path}: no rows with split == 'train'")
    return df["image_id"].astype(str).tolist(), train_idx


def _gate_table(gates, train_ids: list):
    """gates.parquet rows of the training images, indexed by image id, in ``train_ids`` order."""
    gdf = gates.df.assign(image_id=gates.df["image_id"].astype(str)).set_index("image_id")
    missing = [i for i in train_ids if i not in gdf.index]
    if missing:
        raise ArtifactError(f"{gates.path}: no gate row for {len(missing)} training images (e.g. {missing[0]})")
    return gdf.loc[train_ids]


def agreement_target(method: Method, cfg: Mapping[str, Any]) -> bool:
    """Tell whether ``method``'s region target is the agreement map A (eq:agreement-map), not M^T.

    A is read instead of the voted mask M^T (eq:majority-vote) where a part declared with ``reads_agreement``
    (:data:`pipeline.methods.PARTS`) is on in ``method``'s stage: ``train.soft_targets`` (A is the target), or
    Stage I's ``train.ignore_band`` or ``train.agreement_weight`` (M^T = [A >= 1/2] is the target, A says which
    pixels leave the loss or how much each counts).
    """
    return any(p.value_for(cfg, method.stage == 1) != p.off for p in PARTS if p.reads_agreement)


def training_data(method: Method, cfg: Mapping[str, Any], inputs: Mapping[str, Any]) -> TrainData:
    """Read the pseudo-targets of the training rows ``method``'s data filter keeps, from the opened ``inputs``.

    ``inputs`` are named by artifact; a ``reference`` among them is refused.
    """
    if "reference" in inputs:
        raise ValueError("training_data: reference masks never enter training (use validation_data)")
    if not method.annotation_free:
        raise ValueError(f"training_data: --method {method.name} trains on reference masks; "
                         f"its targets come only from pipeline.training.inputs.ceiling_training_data")
    missing = [n for n in training_inputs(method, cfg) if n not in inputs]
    if missing:
        raise ValueError(f"training_data: --method {method.name} needs the artifacts {missing}")
    ids, train_idx = _train_rows(inputs["manifest"])
    for name in ("images", "teacher", "consensus", "geometry"):
        if name in inputs:
            _check_order(inputs[name], ids, name)
    train_ids = [ids[i] for i in train_idx]
    gates_df = _gate_table(inputs["gates"], train_ids) if "gates" in inputs else None
    stats: dict[str, Any] = {"n_train_rows": int(len(train_idx))}
    keep = np.ones(len(train_idx), dtype=bool)
    if method.data == "afs":
        mask, keep, stats["afs_pass_ratio"] = _afs_targets(inputs["teacher"], train_idx, cfg["afs"])
    elif agreement_target(method, cfg):  # A (eq:agreement-map): the target, or where the prompts split
        mask = LazyRows(inputs["consensus"]["agreement"], train_idx, np.float32)
    else:
        mask = LazyRows(inputs["consensus"]["voted"], train_idx, bool)
    if uses_confidence(method):  # the pass ratio r wherever the method evaluates the criterion
        c = cfg["confidence"]
        score = (mean_valid_score(read_rows(inputs["teacher"], "scores", train_idx)) if c["criterion"] == "mean_score"
                 else None)
        passed = confidence_pass(gates_df["c"].to_numpy(), gates_df["n_valid"].to_numpy(), score, c["criterion"],
                                 float(c["threshold"]), int(c["min_valid"]))
        stats["confidence_pass_ratio"] = pass_ratio(passed)
        if method.data == "confidence":
            keep &= passed
    sel = np.flatnonzero(keep)
    if len(sel) == 0:
        raise InputError(f"--method {method.name}: no training image passes the method's filter "
                         f"(train.{'afs' if method.data == 'afs' else 'confidence'}); loosen it")
    rows = train_idx[sel]
    mask = select_rows(mask, sel)
    data = TrainData(
        image_ids=[train_ids[i] for i in sel], images=LazyRows(inputs["images"]["image"], rows), mask=mask,
        area=gates_df["a"].to_numpy(np.float32)[sel] if gates_df is not None else row_means(mask),  # eq:pseudo-area
        gate=gate_values(method, gates_df, sel), stats=stats)
    if method.needs_geometry:
        data.sdf = LazyRows(inputs["geometry"]["sdf"], rows, np.float32)
        data.skeleton = LazyRows(inputs["geometry"]["skeleton"], rows, bool)
        data.geometry = geometry_constants(inputs["geometry"])
    stats["n_train"] = len(data)
    return data


def geometry_constants(geometry) -> GeometryConstants:
    """Read the ``geometry.*`` constants recorded in geometry.zarr's params (the defaults where it records none)."""
    params = getattr(getattr(geometry, "meta", None), "params", None) or {}
    nested = params.get("geometry") if isinstance(params.get("geometry"), Mapping) else {}
    keys = {"quantile": "sdf_quantile", "min_scale": "sdf_min_scale", "min_distance": "skeleton_min_distance"}
    d = GeometryConstants()
    # unvalidated: the params geometry.zarr recorded (an older artifact records fewer keys)
    return GeometryConstants(**{f: float(params.get(f"geometry.{k}", nested.get(k, getattr(d, f))))
                                for f, k in keys.items()})


def gate_values(method: Method, gates_df, sel: np.ndarray) -> np.ndarray:
    """Per-image gate g_i (eq:reliability-gate) of the selected rows; 1 for ``gate="one"`` or without gates."""
    if method.gate == "one" or gates_df is None:
        return np.ones(len(sel), dtype=np.float32)
    g = gates_df["g"].to_numpy(np.float32)[sel]
    if not np.all(np.isfinite(g)) or g.min(initial=0) < 0 or g.max(initial=0) > 1:
        raise ArtifactError("gates.parquet: column g must be finite and in [0, 1]")
    return g


def _afs_targets(teacher, train_idx, a: Mapping[str, Any]) -> tuple[MappedRows, np.ndarray, float]:
    """AFS control (``train.afs``): the base prompt's masks fused with their vflip's, the rows kept, the pass ratio."""
    if "vflip_masks" not in teacher or "vflip_scores" not in teacher:
        raise InputError(f"{teacher.path}: no vflip_masks/vflip_scores; the afs_control method needs "
                         f"teacher.vflip_base_prompt: true")
    prompts = list(teacher.attrs.get("prompts") or [])
    base = a["base_prompt"]
    if base not in prompts:
        raise InputError(f"params: train.afs.base_prompt={base!r} is not one of {teacher.path}'s prompts {prompts}")
    k = prompts.index(base)
    rows = np.sort(train_idx)
    afs_fuse(np.zeros(1, bool), np.zeros(1, bool), a["fusion"])  # a bad train.afs.fusion fails here, not mid-epoch
    fused = MappedRows(lambda masks, vflip_masks: afs_fuse(masks[:, k], vflip_masks, a["fusion"]),
                       [LazyRows(teacher["masks"], rows, bool), LazyRows(teacher["vflip_masks"], rows, bool)],
                       bool, teacher["vflip_masks"].shape[1:])
    scores = np.asarray(teacher["scores"].get_orthogonal_selection((rows, k)), dtype=np.float64)
    keep = afs_keep(scores, float(a["score_threshold"]))
    return fused, keep, pass_ratio(keep)


def validation_rows(manifest) -> np.ndarray:
    """Find the manifest's ``split == "val"`` rows (the only rows whose reference masks are read)."""
    return np.flatnonzero((manifest.df["split"] == "val").to_numpy())


def validation_data(manifest, images, reference) -> ValData | None:
    """Read the validation images and reference masks of the ``split == "val"`` rows with a mask (None: none)."""
    ids = manifest.df["image_id"].astype(str).tolist()
    val_idx = validation_rows(manifest)
    if len(val_idx) == 0:
        return None
    _check_order(reference, ids, "reference")
    val_idx = val_idx[read_rows(reference, "has_mask", val_idx).astype(bool)]
    if len(val_idx) == 0:
        return None
    return ValData(image_ids=[ids[i] for i in val_idx], images=read_rows(images, "image", val_idx),
                   masks=read_rows(reference, "mask", val_idx).astype(bool))


def require_supervised_ceiling(method: Method) -> None:
    """ValueError unless ``method`` is the supervised ceiling, the only method trained on reference masks."""
    if method.name != SUPERVISED_CEILING or method.annotation_free:
        raise ValueError(f"--method {method.name}: reference masks enter a loss only for {SUPERVISED_CEILING!r} "
                         f"(annotation-free methods train on pseudo-targets: pipeline.training.inputs.training_data)")


def ceiling_training_data(method: Method, inputs: Mapping[str, Any], reference) -> TrainData:
    """Read the supervised ceiling's training rows with their REFERENCE masks (NOT annotation-free).

    The one place such masks enter a loss.  ``inputs``: opened ``manifest`` and ``images``.
    """
    require_supervised_ceiling(method)
    ids, train_idx = _train_rows(inputs["manifest"])
    for art in (inputs["images"], reference):
        _check_order(art, ids, art.meta.schema)
    n_rows = int(len(train_idx))
    train_idx = train_idx[read_rows(reference, "has_mask", train_idx).astype(bool)]
    if len(train_idx) == 0:
        raise InputError(f"{reference.path}: no training image has a reference mask; "
                         f"the supervised ceiling needs them")
    mask = LazyRows(reference["mask"], train_idx, bool)
    data = TrainData(image_ids=[ids[i] for i in train_idx], images=LazyRows(inputs["images"]["image"], train_idx),
                     mask=mask, area=row_means(mask), gate=np.ones(len(mask), dtype=np.float32),
                     stats={"n_train_rows": n_rows, "targets": "reference masks (NOT annotation-free)"})
    data.stats["n_train"] = len(data)
    return data


def load_inputs(artifacts: str | Path, spec: Method, cfg: Mapping[str, Any], review: Mapping[str, Any] | None = None
                ) -> tuple[TrainData, ValData | None, list]:
    """Read everything a run of ``spec`` trains and validates on.

    Parameters
    ----------
    artifacts : str or Path
        The artifacts folder.
    spec : Method
        The run's method (:data:`pipeline.methods.METHODS`).
    cfg : Mapping
        The validated ``train:`` section (the method's filter and target settings).
    review : Mapping, optional
        The validated ``review:`` section: with ``corrections`` set, the ``corrected`` artifact is applied in its
        ``mode`` (:data:`MODES`).

    Returns
    -------
    tuple
        ``(TrainData, ValData or None, the opened artifacts)``; the artifacts are the run's lineage.

    Raises
    ------
    ArtifactError
        Inputs from different runs of a stage, or an image order that differs from the manifest's.
    InputError
        No training row, none passing the method's filter, or corrections that leave nothing to train on.
    """

    def opened(name: str):
        lineage.append(open_artifact(catalog.path(name, artifacts), name))
        return lineage[-1]

    lineage: list = []
    inputs = {name: opened(name) for name in training_inputs(spec, cfg)}
    # outputs of one stage must come from one run (a kill between geometry.zarr and gates.parquet)
    require_same_run(*lineage)
    reference = None
    if spec.annotation_free:
        data = training_data(spec, cfg, inputs)
    else:
        reference = opened("reference")
        require_same_run(*lineage)
        data = ceiling_training_data(spec, inputs, reference)
    corrected = None
    if review and review.get("corrections") and spec.annotation_free:
        corrected = opened("corrected")
        data = apply_to_training(data, corrected, review["mode"])
    val = None
    if len(validation_rows(inputs["manifest"])):
        if reference is None:
            reference = opened("reference")
            require_same_run(*lineage)
        val = validation_data(inputs["manifest"], inputs["images"], reference)
    if corrected is not None and review["mode"] == "validate":
        val = apply_to_validation(val, corrected, inputs["images"])
    return data, val, lineage


class PatchedRows(RowSource):
    """The rows of ``base`` with those in ``patch`` (position -> row) replaced, read like any row source."""

    def __init__(self, base, patch: Mapping[int, np.ndarray]):
        self.base = base
        self.patch = dict(patch)
        self.dtype = np.dtype(base.dtype)

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self.base.shape)

    def select(self, sel) -> PatchedRows:
        pos = np.arange(len(self))[sel]
        return PatchedRows(select_rows(self.base, pos), {k: self.patch[p] for k, p in enumerate(pos)
                                                         if p in self.patch})

    def read(self, key) -> np.ndarray:
        pos = np.arange(len(self))[key]
        out = np.array(self.base[pos], dtype=self.dtype)
        for k, p in enumerate(pos):
            if int(p) in self.patch:
                out[k] = self.patch[int(p)]
        return out


def _positions(data: TrainData, ids: list[str]) -> dict[int, str]:
    want = set(ids)
    return {k: iid for k, iid in enumerate(data.image_ids) if iid in want}


def apply_to_training(data: TrainData, corrected, mode: str) -> TrainData:
    """Apply the opened ``corrected`` artifact to ``data`` in ``mode``.

    ``validate`` drops the corrected images, ``replace`` trains on their corrected masks
    (:func:`replace_targets`).
    """
    require_mode(corrected, mode)
    ids = list(corrected.attrs["image_ids"])
    by_id = dict(zip(ids, np.asarray(corrected["mask"], dtype=bool)))
    pos = _positions(data, ids)
    stats = {**data.stats, "corrections_mode": mode, "human_corrections": len(pos),
             "human_corrections_not_applied": len(ids) - len(pos)}
    if mode != "validate":
        return replace_targets(data, by_id, stats)
    sel = np.flatnonzero([k not in pos for k in range(len(data))])
    if not len(sel):
        raise InputError(f"{corrected.path}: every training image is corrected; {MODE_KEY}=validate would "
                         f"leave nothing to train on")
    out = data.subset(sel, stats=stats)
    out.stats["n_train"] = len(out)
    return out


def replace_targets(data: TrainData, masks: Mapping[str, np.ndarray], stats: Mapping[str, Any] | None = None
                    ) -> TrainData:
    """Train the images in ``masks`` on those masks (NOT annotation-free).

    The region target is replaced, g = 1, and a and the geometry targets are recomputed; images ``data`` lacks
    are left out.

    Parameters
    ----------
    data : TrainData
        The training rows.
    masks : Mapping
        ``{image id: bool [R, R]}``.
    stats : Mapping, optional
        The stats to start from (None: ``data.stats``).

    Returns
    -------
    TrainData
        A new value, its ``stats`` saying how many targets were replaced.
    """
    pos = _positions(data, list(masks))
    stats = dict(data.stats if stats is None else stats)
    stats.setdefault("human_corrections", len(pos))
    new = {k: np.asarray(masks[iid], bool) for k, iid in pos.items()}
    area, gate = np.array(data.area, copy=True), np.array(data.gate, copy=True)
    for k, m in new.items():
        area[k], gate[k] = area_ratio(m), 1.0
    fields = {"mask": PatchedRows(_as_rows(data.mask), new), "area": area, "gate": gate}
    if data.sdf is not None and new:
        geo = {k: recompute_geometry(m, data.geometry) for k, m in new.items()}
        fields["sdf"] = PatchedRows(_as_rows(data.sdf), {k: g[0] for k, g in geo.items()})
        fields["skeleton"] = PatchedRows(_as_rows(data.skeleton), {k: g[1] for k, g in geo.items()})
    stats.update(annotation_free=False,
                 targets=f"voted masks, {len(pos)} replaced by human corrections (NOT annotation-free)")
    return dataclasses.replace(data, stats=stats, **fields)


def apply_to_validation(val: ValData | None, corrected, images) -> ValData:
    """Append the corrected images, read from ``images``, and their masks to ``val`` (None: no validation masks)."""
    ids, imgs, masks = corrected_validation(corrected, images)
    if val is None:
        return ValData(image_ids=ids, images=imgs, masks=masks)
    return ValData(image_ids=list(val.image_ids) + ids, images=np.concatenate([val.images, imgs]),
                   masks=np.concatenate([val.masks, masks]))


def _as_rows(x) -> RowSource:
    """Wrap ``x`` as a row source (an array too, so that :class:`PatchedRows` reads it alike)."""
    return x if isinstance(x, RowSource) else LazyRows(np.asarray(x), np.arange(len(x)))


def load_init(path: str | Path) -> tuple[dict, Any]:
    """Open a Stage-I checkpoint for a warm start.

    Parameters
    ----------
    path : str or Path
        The checkpoint folder (``--init``).

    Returns
    -------
    tuple
        ``(mask-path state dict, its artifact for the lineage)``.

    Raises
    ------
    ArtifactError
        ``path`` holds no checkpoint, or one that does not open.
    """
    p = Path(path)
    if not (p / catalog.META_FILE).exists():
        raise ArtifactError(f"--init {p}: not a checkpoint directory (run train_plain first)")
    art = open_artifact(p, "checkpoint")
    model, _ = load_student(p)
    return model.mask_path_state_dict(), art


@dataclasses.dataclass(frozen=True)
class MethodInputs:
    """What every seed of one method reads, opened once (:func:`open_method`).

    Attributes
    ----------
    spec : Method
        The method.
    stage : int
        Its stage (1 or 2).
    cfg : dict
        The validated ``train:`` section.
    data : TrainData
        The training rows.
    val : ValData or None
        The validation rows.
    inputs : tuple
        The artifacts read, for the lineage.
    context : Any
        The stage's context: ``context.meta(schema, inputs, params=..., **extra)`` stamps a checkpoint.
    """

    spec: Any
    stage: int
    cfg: dict
    data: Any
    val: Any
    inputs: tuple
    context: Any


def open_method(params: Mapping[str, Any], stage: int, method: str, artifacts: str | Path,
                context: Any) -> MethodInputs:
    """Check a method against ``--stage`` and the params, then open what its runs read.

    Parameters
    ----------
    params : Mapping
        The validated params.
    stage : int
        The stage asked for (``--stage``).
    method : str
        The method's name (``--method``).
    artifacts : str or Path
        The artifacts folder.
    context : Any
        The stage's context (kept in the result, stamps the checkpoints).

    Returns
    -------
    MethodInputs
        The method, its settings, arrays and lineage.

    Raises
    ------
    InputError
        The method belongs to the other stage, or trains on reference masks while
        ``protocol.supervised_ceiling`` is off; or an input the reader refuses.
    """
    cfg = section(params, "train")
    spec = get_method(method)
    if spec.stage != stage:
        raise InputError(f"--stage {stage}: method {method!r} belongs to --stage {spec.stage}")
    if not spec.annotation_free and not params["protocol"][SUPERVISED_CEILING]:
        raise InputError(f"--method {method}: trains on reference masks (not annotation-free); "
                         f"needs params protocol.{SUPERVISED_CEILING}: true")
    data, val, inputs = load_inputs(artifacts, spec, cfg, review=section(params, "review"))
    return MethodInputs(spec, stage, cfg, data, val, tuple(inputs), context)
