"""Student training: Stage I silhouette learning, Stage II gated geometry refinement, and every
comparison method of :mod:`pipeline.methods` -- one loop, driven by the declarative method table.

Data boundary (the paper's "annotation-free" rule, kept visible here)
  * :func:`load_training_data` builds every training batch source from *pseudo-targets only*:
    images.zarr, consensus.zarr (``voted`` = M^T), geometry.zarr (D^T, K^T), gates.parquet (g_i, a_i),
    teacher.zarr (the confidence filter and the AFS control) and manifest.parquet (split).  It never
    opens reference.zarr.
  * :func:`validation_reference` is the ONLY reader of reference.zarr and returns masks of
    ``split == "val"`` rows only; they serve checkpoint selection (validation Image IoU, Boundary F1
    tie-break, tau = 0.5) and never reach a loss.

Schedule and numerics (decisions; the paper gives AdamW, batch 4, weight decay 1e-4 and the initial
learning rates only)
  * learning rate: ``train.schedule`` = ``cosine`` (per optimizer step, from the initial rate to 0)
    or ``constant``;
  * every epoch visits all training images once in a seeded order (``numpy`` generator seeded with
    ``[seed, epoch]``, so a resumed run sees the same order); the last batch may be smaller;
  * channels_last memory format and bf16 autocast where supported (``train.precision``); losses are
    always computed in float32 from the logits;
  * Stage-II warm start: encoder, decoder and mask head copied from the Stage-I checkpoint, SDF and
    skeleton heads freshly initialised from ``torch.manual_seed(seed)``.

Resilience
  * after every epoch the full state (model incl. geometry heads, optimizer, scheduler, torch RNG,
    epoch, log so far, best state) is written atomically to ``<resume_dir>/state.pt``; a rerun with
    the same resume directory (the checkpoint fingerprint) continues after the last finished epoch
    and produces the same weights as an uninterrupted run; a finished state makes a rerun instant;
  * a non-finite loss raises :class:`pipeline.errors.TrainingDiverged` naming epoch, step and term;
    nothing is written for that epoch.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import math
import os
import time
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import torch

from pipeline import losses
from pipeline.artifacts import Artifact, open_artifact, read_chunk_rows
from pipeline.errors import ArtifactError, InputError, TrainingDiverged
from pipeline.methods import (Method, Plan, afs_fuse, afs_keep, confidence_pass, mean_valid_score,
                              method_epochs, method_lr, pass_ratio, resolve_plan)

log = logging.getLogger(__name__)

#: loss-term columns of the training log (NaN where a method does not use the term)
LOG_TERMS = ("bbce", "dice", "raw", "sdf", "dist", "skel", "area", "boundary", "anchor")
LOG_COLUMNS = ("epoch", "stage", "loss", *LOG_TERMS, "val_iou", "val_bf1", "lr", "seconds")
STATE_FILE = "state.pt"
STATE_VERSION = 1


# --------------------------------------------------------------------------------------------------
# Data: pseudo-targets for training, reference masks for validation only
# --------------------------------------------------------------------------------------------------
@dataclasses.dataclass
class TrainData:
    """Training arrays, in memory, for the rows a method trains on (manifest order).

    ``mask`` is the region pseudo-target (M^T, or the AFS-fused base-prompt mask); ``sdf``/``skeleton``
    the pseudo-geometry targets (None when the method does not read geometry.zarr); ``area`` a_i and
    ``gate`` g_i per image (g = 1 for ``gate="one"`` methods).  ``stats`` records the filter outcome.
    """

    image_ids: list
    images: np.ndarray
    mask: np.ndarray
    area: np.ndarray
    gate: np.ndarray
    sdf: np.ndarray | None = None
    skeleton: np.ndarray | None = None
    stats: dict = dataclasses.field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.image_ids)


@dataclasses.dataclass
class ValData:
    """Validation images and their reference masks (split == "val" rows with a mask only)."""

    image_ids: list
    images: np.ndarray
    masks: np.ndarray

    def __len__(self) -> int:
        return len(self.image_ids)


def _check_order(art: Artifact, ids: list, what: str) -> None:
    got = art.attrs.get("image_ids") if hasattr(art, "attrs") else None
    if got is not None and list(got) != list(ids):
        raise ArtifactError(f"{art.path}: image order differs from the manifest ({what}); rerun the stages after prepare")


def _rows(art, name: str, idx: np.ndarray) -> np.ndarray:
    arr = art[name]
    if len(idx) == 0:
        return np.zeros((0, *arr.shape[1:]), dtype=arr.dtype)
    return read_chunk_rows(arr, idx)


def load_manifest(artifacts: str | Path):
    """The manifest table artifact (schema ``manifest``)."""
    return open_artifact(Path(artifacts) / "manifest.parquet", "manifest")


def load_training_data(artifacts: str | Path, method: Method, cfg: Mapping[str, Any],
                       manifest=None) -> tuple[TrainData, list[Artifact]]:
    """Read the pseudo-targets of the ``split == "train"`` rows a method trains on.

    Reads images.zarr and, per the method: consensus.zarr (``voted``), geometry.zarr, gates.parquet
    and teacher.zarr.  Applies the method's data filter (confidence criterion or AFS score filter)
    and records the pass ratio r in ``stats``.  Never opens reference.zarr.
    Returns the data and the list of artifacts read (for the checkpoint's lineage).
    """
    root = Path(artifacts)
    manifest = manifest if manifest is not None else load_manifest(root)
    df = manifest.df
    ids = df["image_id"].astype(str).tolist()
    train_idx = np.flatnonzero((df["split"] == "train").to_numpy())
    if len(train_idx) == 0:
        raise InputError(f"{manifest.path}: no rows with split == 'train'")
    train_ids = [ids[i] for i in train_idx]
    inputs: list[Artifact] = [manifest]

    images = open_artifact(root / "images.zarr", "images")
    _check_order(images, ids, "images")
    inputs.append(images)

    gates_df = None
    if method.needs_gates:
        gates = open_artifact(root / "gates.parquet", "gates")
        inputs.append(gates)
        gdf = gates.df.assign(image_id=gates.df["image_id"].astype(str)).set_index("image_id")
        missing = [i for i in train_ids if i not in gdf.index]
        if missing:
            raise ArtifactError(f"{gates.path}: no gate row for {len(missing)} training images (e.g. {missing[0]})")
        gates_df = gdf.loc[train_ids]

    teacher = None
    uses_confidence = method.data == "confidence" or method.adaptive
    if method.data == "afs" or (uses_confidence and (cfg.get("confidence") or {}).get("criterion") == "mean_score"):
        teacher = open_artifact(root / "teacher.zarr", "teacher")
        _check_order(teacher, ids, "teacher")
        inputs.append(teacher)

    stats: dict[str, Any] = {"n_train_rows": int(len(train_idx))}
    keep = np.ones(len(train_idx), dtype=bool)
    if method.data == "afs":
        mask, keep, r = _afs_targets(teacher, train_idx, cfg)
        stats["afs_pass_ratio"] = r
    else:
        consensus = open_artifact(root / "consensus.zarr", "consensus")
        _check_order(consensus, ids, "consensus")
        inputs.append(consensus)
        mask = _rows(consensus, "voted", train_idx).astype(bool)
    if method.data == "confidence" or method.adaptive:
        passed = _confidence_pass(gates_df, teacher, train_idx, cfg)
        stats["confidence_pass_ratio"] = pass_ratio(passed)
        if method.data == "confidence":
            keep &= passed

    sel = np.flatnonzero(keep)
    if len(sel) == 0:
        raise InputError(f"--method {method.name}: no training image passes the method's filter "
                         f"(train.{'afs' if method.data == 'afs' else 'confidence'}); loosen it")
    rows = train_idx[sel]
    data = TrainData(
        image_ids=[train_ids[i] for i in sel],
        images=_rows(images, "image", rows),
        mask=mask[sel],
        area=(gates_df["a"].to_numpy(np.float32)[sel] if gates_df is not None
              else mask[sel].reshape(len(sel), -1).mean(1).astype(np.float32)),
        gate=gate_values(method, gates_df, sel),
        stats=stats,
    )
    if method.needs_geometry:
        geometry = open_artifact(root / "geometry.zarr", "geometry")
        _check_order(geometry, ids, "geometry")
        inputs.append(geometry)
        data.sdf = _rows(geometry, "sdf", rows).astype(np.float32)
        data.skeleton = _rows(geometry, "skeleton", rows).astype(bool)
    stats["n_train"] = len(data)
    return data, inputs


def gate_values(method: Method, gates_df, sel: np.ndarray) -> np.ndarray:
    """Per-image gate g_i (eq:reliability-gate) for the selected rows; exactly 1 for ``gate="one"``
    methods (the ``no_gate`` ablation) and for methods that read no gates."""
    if method.gate == "one" or gates_df is None:
        return np.ones(len(sel), dtype=np.float32)
    g = gates_df["g"].to_numpy(np.float32)[sel]
    if not np.all(np.isfinite(g)) or g.min(initial=0) < 0 or g.max(initial=0) > 1:
        raise ArtifactError("gates.parquet: column g must be finite and in [0, 1]")
    return g


def _confidence_pass(gates_df, teacher, train_idx, cfg) -> np.ndarray:
    c = cfg.get("confidence") or {}
    criterion = c.get("criterion", "agreement")
    mean_score = mean_valid_score(_rows(teacher, "scores", train_idx)) if criterion == "mean_score" else None
    return confidence_pass(gates_df["c"].to_numpy(), gates_df["n_valid"].to_numpy(), mean_score,
                           criterion, float(c.get("threshold", 0.8)), int(c.get("min_valid", 1)))


def _afs_targets(teacher, train_idx, cfg) -> tuple[np.ndarray, np.ndarray, float]:
    """AFS control targets: base prompt on the image and on its vertical flip (flipped back, stored by
    the teacher stage as ``vflip_masks``), fused by agreement; keep images with base score >= threshold."""
    a = cfg.get("afs") or {}
    if "vflip_masks" not in teacher or "vflip_scores" not in teacher:
        raise InputError(f"{teacher.path}: no vflip_masks/vflip_scores; the afs_control method needs "
                         f"teacher.vflip_base_prompt: true")
    prompts = list(teacher.attrs.get("prompts") or [])
    base = a.get("base_prompt", "spacecraft")
    if base not in prompts:
        raise InputError(f"params: train.afs.base_prompt={base!r} is not one of {teacher.path}'s prompts {prompts}")
    k = prompts.index(base)
    rows = np.sort(train_idx)  # manifest order (flatnonzero is sorted already)
    img_masks = np.asarray(teacher["masks"].get_orthogonal_selection((rows, k)), dtype=bool)
    flip_masks = _rows(teacher, "vflip_masks", rows).astype(bool)
    scores = np.asarray(teacher["scores"].get_orthogonal_selection((rows, k)), dtype=np.float64)
    fused = afs_fuse(img_masks, flip_masks, a.get("fusion", "intersection"))
    keep = afs_keep(scores, float(a.get("score_threshold", 0.60)))
    return fused, keep, pass_ratio(keep)


def validation_reference(artifacts: str | Path, manifest=None) -> tuple[ValData | None, list[Artifact]]:
    """Validation images + reference masks for checkpoint selection -- the ONLY reader of reference.zarr.

    Returns only rows with ``split == "val"`` and ``has_mask``; None (and no input) when there are none.
    Reference masks of any other split are never read.
    """
    root = Path(artifacts)
    manifest = manifest if manifest is not None else load_manifest(root)
    df = manifest.df
    ids = df["image_id"].astype(str).tolist()
    val_idx = np.flatnonzero((df["split"] == "val").to_numpy())
    if len(val_idx) == 0:
        return None, []
    reference = open_artifact(root / "reference.zarr", "reference")
    _check_order(reference, ids, "reference")
    has = _rows(reference, "has_mask", val_idx).astype(bool) if len(val_idx) else np.zeros(0, bool)
    val_idx = val_idx[has]
    if len(val_idx) == 0:
        return None, [reference]
    images = open_artifact(root / "images.zarr", "images")
    val = ValData(image_ids=[ids[i] for i in val_idx], images=_rows(images, "image", val_idx),
                  masks=_rows(reference, "mask", val_idx).astype(bool))
    return val, [reference]


# --------------------------------------------------------------------------------------------------
# Objective
# --------------------------------------------------------------------------------------------------
def compute_terms(weights: Mapping[str, float], outputs: Mapping[str, torch.Tensor],
                  batch: Mapping[str, torch.Tensor], cfg: Mapping[str, Any]) -> dict[str, torch.Tensor]:
    """The loss terms a plan uses and the weighted total ``loss`` (float32 scalars).

    ``region`` = L_raw = BBCE + dice_weight * Dice (eq:raw-loss, logged as ``raw``, ``bbce``, ``dice``),
    ``sdf`` eq:sdf-loss, ``skel`` eq:skeleton-loss, ``area`` eq:area-loss (each gated by
    ``batch["gate"]`` once, inside the term), ``dist``/``boundary`` the GABI-inspired terms,
    ``anchor`` the weak Stage-I anchoring.  With the geodistill weights this equals
    :func:`pipeline.losses.refine_loss` (eq:refine-loss).
    """
    pmax = float(cfg.get("pos_weight_max", losses.PAPER_POS_WEIGHT_MAX))
    band = float(cfg.get("sdf_band", losses.PAPER_SDF_BAND))
    eps = float(cfg.get("loss_eps", losses.PAPER_EPS))
    z = outputs["mask"].float()
    p = torch.sigmoid(z)
    t: dict[str, torch.Tensor] = {}
    if "region" in weights:
        t["bbce"] = losses.balanced_bce(z, batch["mask"], None, pmax)
        t["dice"] = losses.dice_loss(p, batch["mask"])
        t["raw"] = t["bbce"] + float(cfg.get("dice_weight", losses.PAPER_DICE_WEIGHT)) * t["dice"]
    if "sdf" in weights:
        t["sdf"] = losses.sdf_loss(outputs["sdf"], batch["sdf"], batch["gate"], band,
                                   float(cfg.get("sdf_base_weight", losses.PAPER_SDF_BASE_WEIGHT)), eps)
    if "dist" in weights:
        t["dist"] = losses.distance_regression_loss(outputs["sdf"], batch["sdf"])
    if "skel" in weights:
        t["skel"] = losses.skeleton_loss(outputs["skeleton"], batch["skeleton"], batch["gate"], pmax)
    if "area" in weights:
        t["area"] = losses.area_loss(p, batch["area"], batch["gate"],
                                     float(cfg.get("area_eps", losses.PAPER_AREA_EPS)), eps)
    if "boundary" in weights:
        t["boundary"] = losses.boundary_weighted_bce(z, batch["mask"], batch["sdf"], band, eps)
    if "anchor" in weights:
        t["anchor"] = losses.anchor_loss(z, batch["anchor"])
    total = z.new_zeros(())
    for name, w in weights.items():
        total = total + float(w) * t["raw" if name == "region" else name]
    t["loss"] = total
    return t


# --------------------------------------------------------------------------------------------------
# Training loop
# --------------------------------------------------------------------------------------------------
@dataclasses.dataclass
class TrainResult:
    """The selected model (eval mode, CPU), the training log and what was selected and why."""

    model: Any
    log: Any  # pandas.DataFrame (schema training_log)
    selected_epoch: int
    info: dict


def _autocast(device: torch.device, dtype):
    if dtype is None:
        import contextlib

        return contextlib.nullcontext()
    return torch.autocast(device_type=device.type, dtype=dtype)


def _lr_lambda(schedule: str, total_steps: int) -> Callable[[int], float]:
    if schedule == "constant":
        return lambda step: 1.0
    if schedule == "cosine":
        return lambda step: 0.5 * (1.0 + math.cos(math.pi * min(step, total_steps) / max(total_steps, 1)))
    raise InputError(f"params: train.schedule={schedule!r}: expected cosine or constant")


def build_model(method: Method, cfg: Mapping[str, Any], seed: int, init_state: Mapping | None = None):
    """TinyUNet for a method: random init from ``torch.manual_seed(seed)``, or (``init="stage1"``)
    the Stage-I mask path copied from ``init_state``; then fresh geometry heads (seeded) if needed."""
    from pipeline.model import TinyUNet

    torch.manual_seed(int(seed))
    model = TinyUNet(channels=tuple(cfg.get("channels", (24, 48, 96))))
    if method.init == "stage1":
        if init_state is None:
            raise InputError(f"--method {method.name}: needs --init (the Stage-I checkpoint)")
        try:
            model.load_state_dict(init_state, strict=True)
        except RuntimeError as e:
            raise InputError(f"--init: checkpoint does not match train.channels ({str(e).splitlines()[0][:120]})") from None
        torch.manual_seed(int(seed))
    if method.geometry_heads:
        model.add_geometry_heads()
    return model


def _tensors(data: TrainData, device: torch.device, anchor: np.ndarray | None) -> dict[str, torch.Tensor]:
    """Whole training set as tensors (uint8 images NHWC, targets), on ``device``, once per run."""
    t = {"image": torch.from_numpy(np.ascontiguousarray(data.images)),
         "mask": torch.from_numpy(np.ascontiguousarray(data.mask)),
         "area": torch.from_numpy(np.ascontiguousarray(data.area, dtype=np.float32)),
         "gate": torch.from_numpy(np.ascontiguousarray(data.gate, dtype=np.float32))}
    if data.sdf is not None:
        t["sdf"] = torch.from_numpy(np.ascontiguousarray(data.sdf, dtype=np.float32))
        t["skeleton"] = torch.from_numpy(np.ascontiguousarray(data.skeleton))
    if anchor is not None:
        t["anchor"] = torch.from_numpy(np.ascontiguousarray(anchor, dtype=np.float32))
    return {k: v.to(device) for k, v in t.items()}


def _batch(t: Mapping[str, torch.Tensor], idx: torch.Tensor, flip: torch.Tensor | None,
           channels_last: bool) -> dict[str, torch.Tensor]:
    """One batch: images uint8 NHWC -> float [B,3,H,W] in [0,1] (NHWC strides = channels_last),
    pixel targets [B,1,H,W] float, per-sample ``area``/``gate`` [B]."""
    x = t["image"][idx].permute(0, 3, 1, 2).float().div_(255.0)
    x = x.contiguous(memory_format=torch.channels_last if channels_last else torch.contiguous_format)
    b = {"x": x, "area": t["area"][idx], "gate": t["gate"][idx]}
    for k in ("mask", "sdf", "skeleton", "anchor"):
        if k in t:
            b[k] = t[k][idx].unsqueeze(1).float()
    if flip is not None and bool(flip.any()):
        for k in ("x", "mask", "sdf", "skeleton", "anchor"):
            if k in b:
                b[k] = torch.where(flip.view(-1, 1, 1, 1), b[k].flip(-1), b[k])
    return b


def validate(model, val: ValData | None, device, precision: str = "fp32", channels_last: bool = True,
             tau: float = 0.5, tolerance: float = 2) -> tuple[float, float]:
    """Mean validation Image IoU and Boundary F1 of ``[P >= tau]`` against the reference masks
    (``pipeline.metrics``); (nan, nan) without validation data.  Leaves the model in train mode."""
    if val is None or len(val) == 0:
        return float("nan"), float("nan")
    from pipeline.inference import predict_probs
    from pipeline.metrics import boundary_f1, image_ious

    probs = predict_probs(model, val.images, device=device, batch_size=16, precision=precision,
                          channels_last=channels_last)
    model.train()
    pred = probs >= tau
    iou = float(np.mean(image_ious(pred, val.masks)))
    bf1 = float(np.mean([boundary_f1(p, g, tolerance) for p, g in zip(pred, val.masks)]))
    return iou, bf1


def _save_state(resume_dir: Path, state: dict) -> None:
    resume_dir.mkdir(parents=True, exist_ok=True)
    tmp = resume_dir / f".{STATE_FILE}.tmp-{os.getpid()}"
    torch.save(state, tmp)
    os.replace(tmp, resume_dir / STATE_FILE)


def _load_state(resume_dir: Path | None, run_key: dict) -> dict | None:
    if resume_dir is None or not (resume_dir / STATE_FILE).exists():
        return None
    try:
        state = torch.load(resume_dir / STATE_FILE, map_location="cpu", weights_only=False)
    except Exception as e:  # a state cut off by a kill during torch.save cannot happen (os.replace),
        log.warning("ignoring unreadable resume state %s (%s)", resume_dir, type(e).__name__)
        return None
    if state.get("version") != STATE_VERSION or state.get("run_key") != run_key:
        log.warning("ignoring resume state %s from a different run", resume_dir)
        return None
    return state


def _cpu_state(model) -> dict:
    return {k: v.detach().to("cpu", copy=True) for k, v in model.state_dict().items()}


def train(method: Method, cfg: Mapping[str, Any], data: TrainData, val: ValData | None, seed: int, *,
          init_state: Mapping | None = None, device="cpu", resume_dir: str | Path | None = None,
          callback: Callable[[int, dict], None] | None = None, show_progress: bool = True) -> TrainResult:
    """Train one (method, seed) run and return the selected model and its log.

    ``init_state``: Stage-I mask-path state dict for warm-started methods.  ``resume_dir``: where the
    per-epoch state lives (None: no resume).  ``callback(epoch, row)`` runs after each epoch's state
    is saved (tests use it to interrupt a run).  Raises TrainingDiverged on a non-finite loss.
    """
    import pandas as pd

    from pipeline.device import autocast_dtype
    from pipeline.progress import progress

    device = torch.device(device)
    if int(cfg.get("num_threads", 0) or 0) > 0:
        torch.set_num_threads(int(cfg["num_threads"]))
    epochs = method_epochs(method, cfg)
    lr = method_lr(method, cfg)
    batch_size = int(cfg.get("batch_size", 4))
    if batch_size < 1:
        raise InputError(f"params: train.batch_size={batch_size} must be >= 1")
    precision = str(cfg.get("precision", "auto"))
    amp = autocast_dtype(device, precision)
    channels_last = bool(cfg.get("channels_last", True))
    tol = float(cfg.get("val_bf1_tolerance", 2))
    plan: Plan = resolve_plan(method, cfg, data.stats.get("confidence_pass_ratio"))

    model = build_model(method, cfg, seed, init_state)
    anchor = None
    if "anchor" in plan.weights:
        from pipeline.inference import predict_probs

        frozen = build_model(dataclasses.replace(method, terms=("region",)), cfg, seed, init_state)
        anchor = predict_probs(frozen, data.images, device=device, precision=precision,
                               channels_last=channels_last)
    model = model.to(device)
    if channels_last:
        model = model.to(memory_format=torch.channels_last)
    model.train()
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=float(cfg.get("weight_decay", 1e-4)))
    steps_per_epoch = max(1, math.ceil(len(data) / batch_size))
    sched = torch.optim.lr_scheduler.LambdaLR(opt, _lr_lambda(str(cfg.get("schedule", "cosine")),
                                                              epochs * steps_per_epoch))
    tensors = _tensors(data, device, anchor)

    run_key = {"method": method.name, "seed": int(seed), "epochs": epochs, "n_train": len(data),
               "train_ids": list(data.image_ids)}
    resume_dir = Path(resume_dir) if resume_dir is not None else None
    rows: list[dict] = []
    best: dict | None = None
    start = 1
    state = _load_state(resume_dir, run_key)
    if state is not None:
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        sched.load_state_dict(state["scheduler"])
        torch.set_rng_state(state["torch_rng"])
        rows, best, start = list(state["log"]), state["best"], int(state["epoch"]) + 1
        log.info("resuming %s seed %s after epoch %d from %s", method.name, seed, start - 1, resume_dir)

    def consider(epoch: int, row: dict, eligible: bool) -> None:
        nonlocal best
        if not eligible:
            return
        if plan.select == "last" or val is None or len(val) == 0:
            best = {"epoch": epoch, "score": None, "state": _cpu_state(model)}
            return
        score = (row["val_iou"], row["val_bf1"])
        if best is None or best["score"] is None or score > tuple(best["score"]):
            best = {"epoch": epoch, "score": score, "state": _cpu_state(model)}

    def empty_row(epoch: int) -> dict:
        return {"epoch": epoch, "stage": method.stage, "loss": float("nan"),
                **{k: float("nan") for k in LOG_TERMS}, "lr": float("nan")}

    if start == 1 and not rows and method.init == "stage1":
        # epoch 0 = the warm start itself: logged for every Stage-II method, a selection candidate
        # only where the plan says so (quality-adaptive geometry_only mode)
        t0 = time.perf_counter()
        row = empty_row(0)
        row["val_iou"], row["val_bf1"] = validate(model, val, device, precision, channels_last, tolerance=tol)
        row["seconds"] = time.perf_counter() - t0
        rows.append(row)
        consider(0, row, plan.epoch0_eligible)

    total = (epochs - start + 1) * steps_per_epoch
    bar = progress(total=total, desc=f"train {method.name} s{seed}") if show_progress and total > 0 else None
    last_val = rows[-1]["val_iou"] if rows else float("nan")
    for epoch in range(start, epochs + 1):
        t0 = time.perf_counter()
        lr_epoch = opt.param_groups[0]["lr"]
        order = np.random.default_rng([int(seed), epoch]).permutation(len(data))
        flips = (np.random.default_rng([int(seed), epoch, 1]).random(len(data)) < 0.5
                 if cfg.get("augment_hflip", False) else None)
        sums: dict[str, torch.Tensor] = {}
        for step, s in enumerate(range(0, len(data), batch_size)):
            idx_np = order[s:s + batch_size]
            idx = torch.from_numpy(idx_np).to(device)
            flip = torch.from_numpy(flips[idx_np]).to(device) if flips is not None else None
            b = _batch(tensors, idx, flip, channels_last)
            with _autocast(device, amp):
                out = model.forward_train(b["x"])
            terms = compute_terms(plan.weights, out, b, cfg)
            loss_value = float(terms["loss"].detach())
            if not math.isfinite(loss_value):
                bad = [k for k, v in terms.items() if k != "loss" and not torch.isfinite(v).all()]
                raise TrainingDiverged(f"{method.name} seed {seed}: non-finite loss at epoch {epoch}, "
                                       f"step {step + 1} (terms: {', '.join(bad) or 'loss'}); "
                                       f"no checkpoint written -- lower the learning rate or check the inputs")
            opt.zero_grad(set_to_none=True)
            terms["loss"].backward()
            opt.step()
            sched.step()
            n = len(idx_np)
            for k, v in terms.items():
                sums[k] = sums.get(k, 0.0) + v.detach().float() * n
            if bar is not None:
                bar.update(1)
                bar.set_postfix(epoch=epoch, loss=f"{loss_value:.4f}", val_iou=f"{last_val:.3f}", refresh=False)
        # a finite loss can still leave non-finite weights after the last step (e.g. an inf gradient)
        if not all(bool(torch.isfinite(p).all()) for p in model.parameters()):
            raise TrainingDiverged(f"{method.name} seed {seed}: non-finite weights after epoch {epoch}; "
                                   f"no checkpoint written -- lower the learning rate or check the inputs")
        row = empty_row(epoch)
        for k, v in sums.items():
            row["loss" if k == "loss" else k] = float(v) / len(data)
        row["lr"] = float(lr_epoch)
        row["val_iou"], row["val_bf1"] = validate(model, val, device, precision, channels_last, tolerance=tol)
        row["seconds"] = time.perf_counter() - t0
        last_val = row["val_iou"]
        rows.append(row)
        consider(epoch, row, plan.select == "best_val" or epoch == epochs)
        if resume_dir is not None:
            _save_state(resume_dir, {"version": STATE_VERSION, "run_key": run_key, "epoch": epoch,
                                     "model": _cpu_state(model), "optimizer": copy.deepcopy(opt.state_dict()),
                                     "scheduler": sched.state_dict(), "torch_rng": torch.get_rng_state(),
                                     "log": rows, "best": best})
        if callback is not None:
            callback(epoch, row)
    if bar is not None:
        bar.close()

    if best is None:  # cannot happen with epochs >= 1; kept as a guard against a silent wrong pick
        raise RuntimeError("no checkpoint candidate")
    model.load_state_dict(best["state"])
    model = model.to("cpu").to(memory_format=torch.contiguous_format).eval()
    log_df = pd.DataFrame(rows, columns=list(LOG_COLUMNS))
    selection = plan.select if (val is not None and len(val)) or plan.select == "last" else "last (no validation masks)"
    info = {"selected_epoch": int(best["epoch"]), "selection": selection, "epochs": epochs, "lr": lr,
            "mode": plan.mode, "loss_weights": dict(plan.weights), "epoch0_eligible": plan.epoch0_eligible,
            "autocast": str(amp).replace("torch.", "") if amp is not None else "fp32",
            "channels_last": channels_last, **data.stats}
    return TrainResult(model=model, log=log_df, selected_epoch=int(best["epoch"]), info=info)


def load_init(path: str | Path) -> tuple[dict, Artifact]:
    """Stage-I checkpoint for a warm start: (mask-path state dict, its artifact for the lineage)."""
    from pipeline.inference import is_active_run, load_student

    p = Path(path)
    if not (p / "meta.json").exists():
        raise ArtifactError(f"--init {p}: not a checkpoint directory (run train_stage1 first)")
    if not is_active_run(p):
        raise InputError(f"--init {p}: is an inactive run marker; add its method/seed to protocol.active_*")
    art = open_artifact(p, "checkpoint")
    model, _ = load_student(p)
    return model.mask_path_state_dict(), art
