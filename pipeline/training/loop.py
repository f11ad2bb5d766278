"""Student training: Stage I, Stage II and every comparison method of :mod:`pipeline.methods` in one loop.

The loop is driven by the method table.  Arrays in (:class:`TrainData`; reference masks only in
:class:`ValData`, for selection), model and log out; it opens no file.  Schedule, numerics and resumption:
docs/decisions.md, "Training".
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import logging
import math
import tempfile
import time
from typing import Any, Callable, Mapping

import numpy as np
import torch

from pipeline import losses
from pipeline.augment import GeometryConstants, augment_batch, soft_region
from pipeline.runtime.device import autocast, autocast_dtype, reuse_freed_memory
from pipeline.runtime.errors import InputError, TrainingDiverged
from pipeline.evaluation.inference import predict_probs
from pipeline.methods import Method, Plan, resolve_plan
from pipeline.metrics import boundary_f1, image_ious
from pipeline.model import (TinyUNet, count_parameters, expand_branches, fold_branches, model_options,
                            recompute_bn_stats)
from pipeline.params import PAPER
from pipeline.runtime.progress import progress
from pipeline.training.averaging import average_update, ema_update, in_average
from pipeline.training.checkpointing import Checkpointer
from pipeline.training.inputs import TrainData, ValData
from pipeline.training.schedule import (PLATEAU_Z, decay_epochs, decay_steps, holdout, low_resolution, lr_lambda,
                                        over_budget, plateau_reached, plateau_window, stable_cap, steps_per_epoch,
                                        until_lambda)
from pipeline.training.settings import Settings
from pipeline.training.streaming import LazyRows, RowSource, prefetch, spill_rows
from pipeline.thresholds import EPOCH_TAU_GRID, calibrate_threshold, mask_from_probs

__all__ = ["LOG_TERMS", "LOG_COLUMNS", "TIMING_COLUMNS", "BUDGET_PARAMS", "STATE_VERSION", "ANCHOR_BATCH",
           "TrainData", "ValData", "TrainResult", "build_model", "validation_scores", "validate", "validation_read",
           "epoch_batches_in_order", "select", "train", "take_rows", "make_batch", "augmented_batch", "setup_run",
           "train_epoch"]

log = logging.getLogger(__name__)

#: loss-term columns of the training log (NaN where a method does not use the term)
LOG_TERMS = ("bbce", "dice", "raw", "sdf", "dist", "skel", "area", "boundary", "anchor")
#: ``val_iou``/``val_bf1`` at the selection tau; ``val_iou_cal`` at ``val_tau_cal``, the epoch's best tau (a diagnostic)
LOG_COLUMNS = ("epoch", "stage", "loss", *LOG_TERMS, "val_iou", "val_bf1", "val_iou_cal", "val_tau_cal", "lr")
#: wall-clock columns: out of the log, so that a rerun under SOURCE_DATE_EPOCH writes a byte-identical checkpoint
TIMING_COLUMNS = ("epoch", "seconds")
#: params that only bound a ``train.until: plateau`` run: a run under another budget resumes the same state
BUDGET_PARAMS = ("train.step_budget", "train.time_budget")
#: the layout of the resume state (:func:`train`'s checkpointer): a state of another version is not resumed
STATE_VERSION = 1


def build_model(method: Method, cfg: Mapping[str, Any], seed: int, init_state: Mapping | None = None, *,
                expand: bool = False):
    """Build the TinyUNet a method trains: seeded, or the Stage-I mask path of ``init_state``.

    The global torch RNG is seeded with ``seed`` before the mask path is built and, for a warm-started method,
    again after ``init_state`` is loaded, so its geometry heads (added where the method has them) are fresh and
    seeded rather than following the discarded initialisation's draws.  With ``expand``
    (``train.expand_branches``) the RepVGG branches come last (:func:`pipeline.model.expand_branches`): the plain
    model's draws are those of a run without them, and a warm-started model re-expands with branches at zero, so
    it starts as the (folded) Stage-I checkpoint.

    Parameters
    ----------
    method : pipeline.methods.Method
        The method: ``init == "stage1"`` loads ``init_state``; ``geometry_heads`` adds the SDF and skeleton
        heads.
    cfg : Mapping
        The ``train`` params section: ``channels`` and the model options (:func:`pipeline.model.model_options`).
    seed : int
        Seeds the global torch RNG (a side effect that the run's later draws follow).
    init_state : Mapping or None
        The Stage-I model's state dict (the mask path), for a warm-started method; ignored otherwise.
    expand : bool
        Give every 3x3 convolution RepVGG's training branches (zero at the start of a warm-started method).

    Returns
    -------
    pipeline.model.TinyUNet
        On the CPU, in train mode; with ``expand``, holding branches that :func:`pipeline.model.fold_branches`
        folds.

    Raises
    ------
    pipeline.runtime.errors.InputError
        A warm-started method without ``init_state``, or an ``init_state`` that does not match
        ``train.channels`` (strict loading).
    """
    torch.manual_seed(int(seed))
    model = TinyUNet(channels=tuple(cfg["channels"]), **model_options(cfg))
    if method.init == "stage1":
        if init_state is None:
            raise InputError(f"--method {method.name}: needs --init (the Stage-I checkpoint)")
        try:
            model.load_state_dict(init_state, strict=True)
        except RuntimeError as e:
            detail = str(e).splitlines()[0][:120]
            raise InputError(f"--init: checkpoint does not match train.channels ({detail})") from None
        torch.manual_seed(int(seed))
    if method.geometry_heads:
        model.add_geometry_heads()
    if expand:
        expand_branches(model, zero_init=method.init == "stage1")
    return model


def _tensors(data: TrainData, device: torch.device, anchor: np.ndarray | RowSource | None
             ) -> dict[str, torch.Tensor | RowSource]:
    """Put the training set per key, once per run: arrays as tensors on ``device``, row sources left on disk."""
    arrays = {"image": (data.images, None), "mask": (data.mask, None), "area": (data.area, np.float32),
              "gate": (data.gate, np.float32)}
    if data.sdf is not None:
        arrays.update(sdf=(data.sdf, np.float32), skeleton=(data.skeleton, None))
    if anchor is not None:
        arrays["anchor"] = (anchor, np.float32)
    return {k: v if isinstance(v, RowSource) else torch.from_numpy(np.ascontiguousarray(v, dtype=dt)).to(device)
            for k, (v, dt) in arrays.items()}


def _streaming(t: Mapping[str, torch.Tensor | RowSource]) -> bool:
    """Whether some training arrays are read from disk per batch."""
    return any(isinstance(v, RowSource) for v in t.values())


def take_rows(v: torch.Tensor | RowSource, idx: torch.Tensor) -> torch.Tensor:
    """Return ``v[idx]`` on ``idx``'s device (a row source's rows read from disk).

    Parameters
    ----------
    v : torch.Tensor or pipeline.training.streaming.RowSource
        Rows in memory, or on disk.
    idx : torch.Tensor
        Row indices (int64).

    Returns
    -------
    torch.Tensor
        The rows, on ``idx``'s device.
    """
    if isinstance(v, RowSource):
        return torch.from_numpy(v[idx.cpu().numpy()]).to(idx.device)
    return v[idx]


def make_batch(t: Mapping[str, torch.Tensor], idx: torch.Tensor, flip: torch.Tensor | None,
           channels_last: bool) -> dict[str, torch.Tensor]:
    """Build one batch: images float [B,3,H,W] in [0,1], pixel targets float [B,1,H,W], ``area``, ``gate`` [B].

    Parameters
    ----------
    t : Mapping
        The run's tensors: ``image`` uint8 [N,H,W,3], the pixel targets [N,H,W] and ``area``, ``gate`` [N].
    idx : torch.Tensor
        The rows of the batch.
    flip : torch.Tensor or None
        bool [B]: flip those images and their targets left-right; None: no flip.
    channels_last : bool
        Lay the images out channels-last (``train.channels_last``).

    Returns
    -------
    dict of str to torch.Tensor
        ``x``, ``area``, ``gate`` and the targets the run has (``mask``, ``sdf``, ``skeleton``, ``anchor``).
    """
    x = take_rows(t["image"], idx).permute(0, 3, 1, 2).float().div_(255.0)
    x = x.contiguous(memory_format=torch.channels_last if channels_last else torch.contiguous_format)
    b = {"x": x, "area": t["area"][idx], "gate": t["gate"][idx]}
    for k in ("mask", "sdf", "skeleton", "anchor"):
        if k in t:
            b[k] = take_rows(t[k], idx).unsqueeze(1).float()
    if flip is not None:  # None when no image flips: deciding that here would sync the device
        for k in ("x", "mask", "sdf", "skeleton", "anchor"):
            if k in b:
                b[k] = torch.where(flip.view(-1, 1, 1, 1), b[k].flip(-1), b[k])
    return b


def augmented_batch(run: _Run, idx: np.ndarray, epoch: int) -> dict[str, torch.Tensor]:
    """Build the batch of rows ``idx``, each image augmented with the seed ``[seed, epoch, row]``.

    Parameters
    ----------
    run : _Run
        The run (:func:`setup_run`), with ``train.augment`` on.
    idx : numpy.ndarray
        The rows of the batch.
    epoch : int
        The epoch (part of each image's augmentation seed).

    Returns
    -------
    dict of str to torch.Tensor
        The batch as :func:`make_batch` builds it, from the augmented images and targets.
    """
    idx_dev = torch.from_numpy(idx).to(run.device)
    rows = {k: take_rows(v, idx_dev).cpu().numpy() for k, v in run.tensors.items()}
    images = rows.pop("image")
    images, targets = augment_batch(images, rows,
                                    [[run.seed, epoch, int(i)] for i in idx], run.settings.augment,
                                    run.geometry)
    dev = {"image": torch.from_numpy(images).to(run.device),
           **{k: torch.from_numpy(np.ascontiguousarray(v)).to(run.device) for k, v in targets.items()}}
    return make_batch(dev, torch.arange(len(idx), device=run.device), None, run.settings.channels_last)


def _has_val(val: ValData | None) -> bool:
    """Tell whether there are validation images."""
    return val is not None and len(val) > 0


def validation_scores(model, val: ValData | None, device, *, precision: str, channels_last: bool,
                      tolerance: float, tau: float = PAPER.calibrate.fixed_tau,
                      calibrated: bool = True) -> dict[str, float]:
    """Score the model on the validation images: mean Image IoU and Boundary F1 of [P >= tau] (eq:inference-mask).

    With ``calibrated``, also the mean Image IoU at the epoch's best tau of
    :data:`pipeline.thresholds.EPOCH_TAU_GRID` (:func:`pipeline.thresholds.calibrate_threshold`, its tie-break
    included).  Each image counts once; empty masks score as :func:`pipeline.metrics.image_ious` and
    :func:`pipeline.metrics.boundary_f1` define.  The model is left in train mode.

    Parameters
    ----------
    model : torch.nn.Module
        The student; predicted in eval mode, then set back to train mode.
    val : ValData or None
        Images with reference masks; None or empty: nothing is predicted.
    device : str or torch.device
        Where to predict.
    precision : str
        ``fp32`` | ``bf16`` | ``auto`` (the autocast of :func:`pipeline.evaluation.inference.predict_probs`).
    channels_last : bool
        Predict in the channels-last memory format.
    tolerance : float
        The Boundary F1 tolerance in pixels (``train.val_bf1_tolerance``).
    tau : float
        The threshold of eq:inference-mask (``calibrate.fixed_tau`` by default).
    calibrated : bool
        Also compute ``val_iou_cal`` and ``val_tau_cal`` (NaN when False).

    Returns
    -------
    dict
        ``val_iou``, ``val_bf1``, ``val_iou_cal``, ``val_tau_cal``: floats, all NaN without validation data.
    """
    out = dict.fromkeys(("val_iou", "val_bf1", "val_iou_cal", "val_tau_cal"), float("nan"))
    if not _has_val(val):
        return out
    probs = predict_probs(model, val.images, device=device, batch_size=16, precision=precision,
                          channels_last=channels_last)
    model.train()
    pred = mask_from_probs(probs, tau)
    out["val_iou"] = float(np.mean(image_ious(pred, val.masks)))
    out["val_bf1"] = float(np.mean([boundary_f1(p, g, tolerance) for p, g in zip(pred, val.masks)]))
    if calibrated:
        tau_cal, curve = calibrate_threshold(probs, val.masks, EPOCH_TAU_GRID)
        out["val_iou_cal"], out["val_tau_cal"] = float(curve.max()), float(tau_cal)
    return out


def validate(model, val: ValData | None, device, *, precision: str, channels_last: bool, tolerance: float,
             tau: float = PAPER.calibrate.fixed_tau) -> tuple[float, float]:
    """Score the model at ``tau``: (``val_iou``, ``val_bf1``) of :func:`validation_scores`, uncalibrated.

    Parameters
    ----------
    model : torch.nn.Module
        The student; left in train mode.
    val : ValData or None
        Images with reference masks; None or empty: (NaN, NaN).
    device : str or torch.device
        Where to predict.
    precision : str
        ``fp32`` | ``bf16`` | ``auto``.
    channels_last : bool
        Predict in the channels-last memory format.
    tolerance : float
        The Boundary F1 tolerance in pixels.
    tau : float
        The threshold of eq:inference-mask.

    Returns
    -------
    tuple of float
        (mean Image IoU, mean Boundary F1) over the validation images.
    """
    s = validation_scores(model, val, device, precision=precision, channels_last=channels_last,
                          tolerance=tolerance, tau=tau, calibrated=False)
    return s["val_iou"], s["val_bf1"]


@dataclasses.dataclass
class TrainResult:
    """What :func:`train` returns: the selected model, the training log and what was selected and why.

    Attributes
    ----------
    model : pipeline.model.TinyUNet
        The selected (or weight-averaged) model, on the CPU in eval mode; with ``train.expand_branches``, folded
        into the plain TinyUNet (:func:`pipeline.model.fold_branches`).
    log : pandas.DataFrame
        One row per epoch (epoch 0: a warm-started method's starting point), columns :data:`LOG_COLUMNS`
        (schema ``training_log``); NaN where a method does not use a term or an epoch was not validated.
    selected_epoch : int
        The epoch whose weights ``model`` holds; with a weight average, the run's last epoch.
    info : dict
        ``selected_epoch``, ``selection`` (the rule, in words), ``epochs``, ``lr``, ``steps_run``,
        ``low_res_epochs``, ``mode``, ``loss_weights``, ``epoch0_eligible``, ``autocast``, ``channels_last``,
        the training data's stats, under ``until: plateau`` ``stable_epochs`` and ``stopped`` (why) and, with
        ``train.expand_branches``, ``folded`` (the parameters trained and deployed, the folding's largest |logit
        change| on the first training batch).
    timings : list of dict
        ``{"epoch", "seconds"}`` per log row (:data:`TIMING_COLUMNS`): wall-clock seconds, kept out of the log so
        that it is reproducible.
    """

    model: Any
    log: Any  # pandas.DataFrame (schema training_log)
    selected_epoch: int
    info: dict
    timings: list = dataclasses.field(default_factory=list)


@dataclasses.dataclass
class _Run:
    """Everything one (method, seed) run carries between epochs."""

    method: Method
    seed: int
    settings: Settings
    plan: Plan
    device: torch.device
    amp: Any  # autocast dtype or None
    model: Any
    opt: Any
    sched: Any
    tensors: dict
    n_train: int
    run_key: dict
    rows: list = dataclasses.field(default_factory=list)
    best: dict | None = None
    avg: dict | None = None  # the running mean of the weights: {"n", "state"}
    ema: list | None = None  # the parameters' moving average, on the device
    #: until plateau: {"stable_end": the last stable epoch or None, "epochs": the length so far, "reason", "scores"}
    until: dict | None = None
    stable_state: dict | None = None  # the state at the end of the stable phase: a larger budget continues from it
    #: until plateau without validation masks: pseudo-labelled images the rule scores (never a validation set)
    holdout: ValData | None = None
    scratch: tempfile.TemporaryDirectory | None = None  # streamed anchors
    soft_mask: bool = False  # train.soft_targets (pipeline.augment.soft_region), read once per run
    geometry: GeometryConstants = dataclasses.field(default_factory=GeometryConstants)

    @property
    def steps_per_epoch(self) -> int:
        """Optimizer steps per epoch (the last batch may be short)."""
        return steps_per_epoch(self.n_train, self.settings.batch_size)

    @property
    def epochs(self) -> int:
        """``train.epochs_*``, or (until plateau) the stable phase plus its decay."""
        return self.until["epochs"] if self.until is not None else self.settings.epochs


def _cpu_state(model) -> dict:
    """Copy ``model``'s state dict to the CPU, detached."""
    return {k: v.detach().to("cpu", copy=True) for k, v in model.state_dict().items()}


def setup_run(method: Method, cfg: Mapping[str, Any], s: Settings, plan: Plan, data: TrainData, seed: int,
           init_state: Mapping | None, device: torch.device) -> _Run:
    """Set up a run: the model, the frozen Stage-I anchor if the plan uses one, AdamW, schedule and tensors.

    They are built in the order that fixes the torch RNG stream.

    Parameters
    ----------
    method : pipeline.methods.Method
        The method.
    cfg : Mapping
        The validated ``train`` section.
    s : pipeline.training.settings.Settings
        The run's settings.
    plan : pipeline.methods.Plan
        The resolved loss weights and selection rule.
    data : TrainData
        The training rows.
    seed : int
        The run's seed.
    init_state : Mapping or None
        The Stage-I weights a warm-started method starts from.
    device : torch.device
        Where the run trains.

    Returns
    -------
    _Run
        The run's state, ready for :func:`train_epoch`.
    """
    amp = autocast_dtype(device, s.precision)
    model = build_model(method, cfg, seed, init_state, expand=s.expand_branches)
    anchor, scratch = None, None
    if "anchor" in plan.weights:  # from the folded (plain) Stage-I model: never expanded
        frozen = build_model(dataclasses.replace(method, terms=("region",)), cfg, seed, init_state)
        if isinstance(data.images, RowSource):
            scratch = tempfile.TemporaryDirectory(prefix="geodistill_anchor_")
        anchor = _anchor_probs(frozen, data.images, device, s, scratch)
    model = model.to(device)
    if s.channels_last:
        model = model.to(memory_format=torch.channels_last)
    model.train()
    # CUDA: the fused AdamW kernel; CPU: the default one, whose numerics the tests pin down bit for bit
    fused = {"fused": True} if device.type == "cuda" else {}
    opt = torch.optim.AdamW(model.parameters(), lr=s.lr, weight_decay=s.weight_decay, **fused)
    # a state saved under other numerics (threads, the autocast dtype ``auto`` resolved to) is not resumed
    run_key = {"method": method.name, "seed": int(seed), "epochs": s.epochs, "n_train": len(data),
               **({"until": s.until, "step_budget": s.step_budget,  # a finished stop is kept only under its rule
                   "plateau_rule": [s.plateau_gain, s.plateau_min_epochs, s.plateau_min_steps, PLATEAU_Z]} if s.until != "epochs" else {}),
               "train_ids": list(data.image_ids), "num_threads": int(torch.get_num_threads()),
               "autocast": str(amp).replace("torch.", "") if amp is not None else "fp32",
               # the states of a run with RepVGG branches hold the expanded weights; off, the key is as before
               **({"expand_branches": True} if s.expand_branches else {})}
    run = _Run(method=method, seed=int(seed), settings=s, plan=plan, device=device, amp=amp, model=model,
               opt=opt, sched=None, tensors=_tensors(data, device, anchor), n_train=len(data), run_key=run_key,
               scratch=scratch, geometry=data.geometry, soft_mask=soft_region(data.mask))
    if s.ema_decay > 0:
        run.ema = [p.detach().clone() for p in model.parameters()]
    total = s.epochs * run.steps_per_epoch
    if s.until == "plateau":
        run.until = {"stable_end": None, "epochs": stable_cap(s, run.steps_per_epoch), "reason": None, "scores": []}
        run.sched = torch.optim.lr_scheduler.LambdaLR(opt, until_lambda(run.until, run.steps_per_epoch, s.warmup_epochs * run.steps_per_epoch))
    else:
        run.sched = torch.optim.lr_scheduler.LambdaLR(opt, lr_lambda(
            s.schedule, total, s.warmup_epochs * run.steps_per_epoch, decay_steps(total, s.decay_fraction)))
    return run


def _stop_stable(run: _Run, epoch: int, row: Mapping) -> None:
    """Score stable epoch ``epoch`` and, at the plateau or the cap, end the stable phase.

    The score is the validation one, else the held-out images'; at the stop the stable state is kept and the
    decay scheduled.
    """
    u, s = run.until, run.settings
    if epoch <= s.low_res_epochs and epoch < u["epochs"]:  # the rule scores full-resolution epochs only
        return
    score = row["val_iou_cal"]
    if run.holdout is not None:
        score = validation_scores(run.model, run.holdout, run.device, precision=s.precision,
                                  channels_last=s.channels_last, tolerance=s.bf1_tolerance)["val_iou_cal"]
    u["scores"] = [*u.get("scores", []), float(score)]
    if plateau_reached(u["scores"], s.plateau_gain, plateau_window(s.plateau_min_epochs, s.plateau_min_steps,
                                                                   run.steps_per_epoch)):
        u["reason"] = f"plateau: the last doubling gained less than {s.plateau_gain:g} validation IoU"
    elif epoch >= u["epochs"]:
        budget = over_budget(s, epoch + 1, run.steps_per_epoch)
        u["reason"] = "the step budget (train.step_budget)" if budget else "the epochs cap (train.epochs_stage1)"
    else:
        return
    run.stable_state = _state(run, epoch)
    # the cap holds even where it leaves no room for a decay (train.epochs_stage1 = 1: no decay)
    u["stable_end"], u["epochs"] = epoch, min(s.epochs, epoch + decay_epochs(epoch, s.decay_fraction))


#: images per forward pass of the frozen Stage-I model: the paper's training batch, so that the pass is no larger
#: than a training step (docs/scaling.md); in eval mode each image's probabilities do not depend on the batch
ANCHOR_BATCH = PAPER.train.batch_size


def _anchor_probs(frozen, images: np.ndarray | RowSource, device: torch.device, s: Settings,
                  scratch: tempfile.TemporaryDirectory | None) -> np.ndarray | LazyRows:
    """Predict the frozen Stage-I probabilities of every training image (L_anchor's target).

    They are held in memory, or spilled to ``scratch`` and read back per batch.
    """
    probs = functools.partial(predict_probs, frozen, device=device, batch_size=ANCHOR_BATCH, precision=s.precision,
                              channels_last=s.channels_last)
    if scratch is None:
        return probs(images)
    blocks = (probs(images[i:i + ANCHOR_BATCH]) for i in range(0, len(images), ANCHOR_BATCH))
    return spill_rows(f"{scratch.name}/anchor.zarr", blocks, images.shape[:3], np.float32)


def _resume(run: _Run, checkpointer: Checkpointer) -> int:
    """Restore this run's saved state; return the first epoch still to train (1 without one)."""
    state = checkpointer.load(run.run_key)
    if state is None or state.get("version") != STATE_VERSION:
        return 1
    if state.get("run_key") != run.run_key:
        state = _continued(run, state)
        if state is None:
            log.warning("ignoring resume state from a different run (%s)", checkpointer)
            return 1
    run.model.load_state_dict(state["model"])
    run.opt.load_state_dict(state["optimizer"])
    run.sched.load_state_dict(state["scheduler"])
    torch.set_rng_state(state["torch_rng"])
    run.rows, run.best = list(state["log"]), state["best"]
    run.avg = state.get("avg")
    if run.until is not None and state.get("until") is not None:
        run.until.update(state["until"])
        run.stable_state = state.get("stable_state")
    if run.ema is not None and state.get("ema") is not None:
        run.ema = [t.to(run.device) for t in state["ema"]]
    log.info("resuming %s seed %s after epoch %d from %s", run.method.name, run.seed, state["epoch"], checkpointer)
    return int(state["epoch"]) + 1


def _continued(run: _Run, state: dict) -> dict | None:
    """Adapt a state of this until-plateau run saved under another step budget (None: another run).

    The budget's stop continues from its stable state, the plateau's is finished.
    """
    key = {k: v for k, v in state.get("run_key", {}).items() if k != "step_budget"}
    if run.until is None or key != {k: v for k, v in run.run_key.items() if k != "step_budget"}:
        return None
    u = state.get("until") or {}
    if str(u.get("reason", "")).startswith("plateau"):
        return {**state, "run_key": run.run_key}
    stable = state.get("stable_state")
    if stable is None or stable["epoch"] >= stable_cap(run.settings, run.steps_per_epoch):
        return None  # a smaller budget: train again
    return {**stable, "run_key": run.run_key,
            "until": {**stable["until"], "epochs": stable_cap(run.settings, run.steps_per_epoch)}}


def _state(run: _Run, epoch: int) -> dict:
    """Collect the complete resume state after ``epoch``: copies, the weights on the CPU, the optimizer's on device."""
    return {"version": STATE_VERSION, "run_key": run.run_key, "epoch": epoch, "model": _cpu_state(run.model),
            "optimizer": copy.deepcopy(run.opt.state_dict()), "scheduler": run.sched.state_dict(),
            "torch_rng": torch.get_rng_state(), "log": run.rows, "best": run.best,
            **({"avg": run.avg} if run.avg is not None else {}),
            **({"ema": [t.detach().to("cpu", copy=True) for t in run.ema]} if run.ema is not None else {}),
            **({"until": dict(run.until), "stable_state": run.stable_state} if run.until is not None else {})}


def select(best: dict | None, plan: Plan, val: ValData | None, epoch: int, row: Mapping, model,
           eligible: bool) -> dict | None:
    """Return the checkpoint candidate ``{"epoch", "score", "state"}`` after ``epoch``.

    Under ``select == "last"`` or without validation masks, the latest eligible epoch; else the highest
    (val IoU, val BF1), compared as a tuple (BF1 breaks an IoU tie), an earlier epoch winning an exact tie.  Once
    a scored candidate exists, a NaN score never replaces it, and one whose IoU is NaN is never replaced (tuple
    comparison).

    Parameters
    ----------
    best : dict or None
        The candidate so far (None: none yet).
    plan : pipeline.methods.Plan
        The method's resolved plan; its ``select`` rule (``last`` | ``best_val``).
    val : ValData or None
        The validation images (only whether there are any is read).
    epoch : int
        The epoch just trained (0: a warm-started method's starting point).
    row : Mapping
        The epoch's log row: ``val_iou`` and ``val_bf1`` are read.
    model : torch.nn.Module
        The model after ``epoch``; its state is copied to the CPU if it becomes the candidate.
    eligible : bool
        Whether ``epoch`` may be selected at all.

    Returns
    -------
    dict or None
        The new candidate, or ``best`` unchanged.
    """
    score = None if plan.select == "last" or not _has_val(val) else (row["val_iou"], row["val_bf1"])
    if eligible and (score is None or best is None or best["score"] is None or score > tuple(best["score"])):
        return {"epoch": epoch, "score": score, "state": _cpu_state(model)}
    return best


def _average(run: _Run, epoch: int) -> None:
    """Fold the weights after ``epoch`` into the mean when it is one of the last ``train.average_last``."""
    if in_average(epoch, run.epochs, run.settings.average_last,
                  run.until is None or run.until["stable_end"] is not None):
        run.avg = average_update(run.avg, run.model.state_dict())


def _empty_row(run: _Run, epoch: int) -> dict:
    """Start epoch ``epoch``'s log row: every loss term and the lr NaN."""
    return {"epoch": epoch, "stage": run.method.stage, "loss": float("nan"),
            **{k: float("nan") for k in LOG_TERMS}, "lr": float("nan")}


def _image_batches(run: _Run):
    """Yield the training images in manifest order, in training batches, on the run's device (no target is read)."""
    n, bs = run.n_train, run.settings.batch_size
    inputs = {k: run.tensors[k] for k in ("image", "area", "gate")}
    return (make_batch(inputs, torch.arange(i, min(i + bs, n), device=run.device), None,
                   run.settings.channels_last)["x"] for i in range(0, n, bs))


def _precise_bn(run: _Run) -> int:
    """Precise BN over the training images in manifest order and training batches (no weight, no random draw)."""
    with autocast(run.device, run.amp):
        return recompute_bn_stats(run.model, _image_batches(run))


@torch.no_grad()
def _fold(run: _Run) -> dict:
    """Fold the RepVGG branches of ``run.model`` into the plain TinyUNet; what the fold did, for the run's info.

    :func:`pipeline.model.fold_branches` measures the folded BN statistics over the training images in fp32.  The folded model's largest |logit change| on the first training batch (fp32, eval mode) is measured here, so
    each checkpoint records its own folding error.
    """
    x = next(iter(_image_batches(run)))
    was_training = run.model.training
    run.model.eval()
    before, trained = run.model(x).float(), count_parameters(run.model)
    fold_branches(run.model, _image_batches(run))
    err = float((run.model(x).float() - before).abs().max())
    run.model.train(was_training)
    return {"branches": "RepVGG (train.expand_branches), folded at the end of the stage, after any weight average "
                        "and its BN recompute",
            "parameters_trained": trained, "parameters_deployed": count_parameters(run.model),
            "fold_max_abs_logit_diff": err}


def validation_read(run: _Run, epoch: int) -> bool:
    """Tell whether a rule reads epoch ``epoch``'s validation scores.

    Only a half-side epoch of Stage I can go unread (``train.validate_low_res`` off): not the run's last, not the
    cap ``until: plateau`` scores, not the decay after a stable phase cut inside the schedule, and not under a
    best-validation pick without a weight average.

    Parameters
    ----------
    run : _Run
        The run: its settings, plan, length and ``until: plateau`` state.
    epoch : int
        The epoch just trained, 1-based.

    Returns
    -------
    bool
        False only for an epoch whose validation no rule or selection reads (it is skipped and logged as NaN).
    """
    s = run.settings
    if s.validate_low_res or epoch > s.low_res_epochs or epoch >= run.epochs:
        return True
    if run.until is not None and (run.until["stable_end"] is not None or epoch >= run.until["epochs"]):
        return True
    return run.plan.select == "best_val" and s.average_last == 0 and s.ema_decay == 0


def _validated(run: _Run, row: dict, val: ValData | None, t0: float) -> dict:
    """``row`` with the validation scores and the seconds since ``t0`` (after precise BN, when asked)."""
    s = run.settings
    if s.precise_bn:
        _precise_bn(run)
    row.update(validation_scores(run.model, val, run.device, precision=s.precision,
                                 channels_last=s.channels_last, tolerance=s.bf1_tolerance, tau=s.selection_tau))
    row["seconds"] = time.perf_counter() - t0
    return row


def _step(run: _Run, b: Mapping[str, torch.Tensor], epoch: int, step: int) -> dict[str, torch.Tensor]:
    """One optimizer step on batch ``b`` (eq:refine-loss with the plan's weights); its loss terms."""
    with autocast(run.device, run.amp):
        out = run.model.forward_train(b["x"])
    terms = losses.refine_loss(out, b, b["gate"], run.plan.weights, run.settings.constants)
    # CUDA: reading the loss would stall the GPU every step; the epoch's end checks it instead
    if run.device.type != "cuda" and not math.isfinite(float(terms["loss"].detach())):
        bad = [k for k, v in terms.items() if k != "loss" and not torch.isfinite(v).all()]
        raise TrainingDiverged(f"{run.method.name} seed {run.seed}: non-finite loss at epoch {epoch}, "
                               f"step {step + 1} (terms: {', '.join(bad) or 'loss'}); "
                               f"no checkpoint written -- lower the learning rate or check the inputs")
    run.opt.zero_grad(set_to_none=True)
    terms["loss"].backward()
    run.opt.step()
    run.sched.step()
    if run.ema is not None:  # e <- d e + (1 - d) w after every step
        ema_update(run.ema, run.model.parameters(), run.settings.ema_decay)
    return terms


def _epoch_batches(run: _Run, epoch: int):
    """Yield the epoch's (size, batch) pairs in a ``[seed, epoch]`` order; streamed data read two batches ahead."""
    batches = epoch_batches_in_order(run, epoch)
    return prefetch(batches, depth=2) if _streaming(run.tensors) else batches


def epoch_batches_in_order(run: _Run, epoch: int):
    """Yield an epoch's batches in the order ``[seed, epoch]`` draws, without a prefetching thread.

    The order and flips go to the device once.  The epoch loop reads its batches through this module's name,
    so a benchmark may bound an epoch by replacing it (benchmarks/bench_memory.py, ``--max-batches``).

    Parameters
    ----------
    run : _Run
        The run: its seed, settings (batch size, ``augment``, ``hflip``, ``channels_last``) and tensors.
    epoch : int
        The epoch, 1-based: with the seed, it seeds the batch order, the flips and the augmentation.

    Yields
    ------
    tuple of (int, dict)
        (images in the batch, the batch as :func:`make_batch` builds it) for each batch of the epoch.
    """
    n, bs = run.n_train, run.settings.batch_size
    order = np.random.default_rng([run.seed, epoch]).permutation(n)
    if run.settings.augment is not None:  # it replaces augment_hflip
        for s in range(0, n, bs):
            yield min(bs, n - s), augmented_batch(run, order[s:s + bs], epoch)
        return
    flips = np.random.default_rng([run.seed, epoch, 1]).random(n) < 0.5 if run.settings.hflip else None
    order_dev = torch.from_numpy(order).to(run.device)
    flips_dev = torch.from_numpy(flips[order]).to(run.device) if flips is not None else None
    for s in range(0, n, bs):
        flip = flips_dev[s:s + bs] if flips is not None and flips[order[s:s + bs]].any() else None
        yield min(bs, n - s), make_batch(run.tensors, order_dev[s:s + bs], flip, run.settings.channels_last)


def train_epoch(run: _Run, epoch: int, val: ValData | None, bar) -> dict:
    """Train one epoch of ``run`` and return its log row.

    Parameters
    ----------
    run : _Run
        The run (:func:`setup_run`).
    epoch : int
        The epoch, from 1.
    val : ValData or None
        The validation images; None: no validation.
    bar : object or None
        A progress bar to advance per batch (None: none).

    Returns
    -------
    dict
        The sample-weighted mean loss terms, the epoch's starting learning rate and the validation scores.

    Raises
    ------
    TrainingDiverged
        A non-finite loss or non-finite weights in the epoch.
    """
    t0 = time.perf_counter()
    lr_epoch = run.opt.param_groups[0]["lr"]
    # the last scored epoch's (half-side epochs may go unvalidated: train.validate_low_res)
    last_val = next((r["val_iou"] for r in reversed(run.rows) if math.isfinite(r["val_iou"])), float("nan"))
    sums: dict[str, torch.Tensor] = {}
    # until plateau: the decay trains at full resolution even when the stable phase ended early
    low_res = epoch <= run.settings.low_res_epochs and (run.until is None or run.until["stable_end"] is None)
    for step, (n, b) in enumerate(_epoch_batches(run, epoch)):
        terms = _step(run, low_resolution(b, run.soft_mask) if low_res else b, epoch, step)
        for k, v in terms.items():
            sums[k] = sums.get(k, 0.0) + v.detach().float() * n
        if bar is not None:
            bar.update(1)
            if run.device.type != "cuda":  # no per-step sync on CUDA
                bar.set_postfix(epoch=epoch, loss=f"{float(terms['loss'].detach()):.4f}", val_iou=f"{last_val:.3f}",
                                refresh=False)
    if run.device.type == "cuda" and "loss" in sums and not math.isfinite(float(sums["loss"])):
        raise TrainingDiverged(f"{run.method.name} seed {run.seed}: non-finite loss in epoch {epoch}; "
                               f"no checkpoint written -- lower the learning rate or check the inputs")
    if bar is not None and run.device.type == "cuda" and "loss" in sums:
        bar.set_postfix(epoch=epoch, loss=f"{float(sums['loss']) / run.n_train:.4f}", val_iou=f"{last_val:.3f}",
                        refresh=False)
    # a finite loss can still leave non-finite weights (an inf gradient in the last step)
    if not bool(torch.stack([torch.isfinite(p).all() for p in run.model.parameters()]).all()):
        raise TrainingDiverged(f"{run.method.name} seed {run.seed}: non-finite weights after epoch {epoch}; "
                               f"no checkpoint written -- lower the learning rate or check the inputs")
    row = {**_empty_row(run, epoch), **{k: float(v) / run.n_train for k, v in sums.items()}, "lr": float(lr_epoch)}
    return _validated(run, row, val if validation_read(run, epoch) else None, t0)


def _result(run: _Run, val: ValData | None, stats: Mapping[str, Any]) -> TrainResult:
    """Assemble the selected (or averaged) model on the CPU in eval mode, the log table and the run's info."""
    import pandas as pd

    if run.best is None:  # cannot happen with epochs >= 1: a guard against a silent wrong pick
        raise RuntimeError("no checkpoint candidate")
    plan, s = run.plan, run.settings
    selection = plan.select if _has_val(val) or plan.select == "last" else "last (no validation masks)"
    if run.ema is not None:
        with torch.no_grad():
            torch._foreach_copy_(list(run.model.parameters()), run.ema)
        selection = f"moving average of the weights, decay {s.ema_decay:g} per step (BN statistics recomputed)"
    elif run.avg is not None:
        run.model.load_state_dict(run.avg["state"])
        selection = f"mean weights of the last {run.avg['n']} epochs (BN statistics recomputed)"
    else:
        run.model.load_state_dict(run.best["state"])
    if run.ema is not None or run.avg is not None:  # averaged weights, BN statistics recomputed for them
        _precise_bn(run)
        run.best = {"epoch": run.epochs, "score": None, "state": None}
    folded = _fold(run) if s.expand_branches else None  # after the average and its BN recompute
    model = run.model.to("cpu").to(memory_format=torch.contiguous_format).eval()
    info = {"selected_epoch": int(run.best["epoch"]), "selection": selection, "epochs": run.epochs, "lr": s.lr,
            "steps_run": int(run.epochs * run.steps_per_epoch),
            # epochs at half the side: the schedule's, cut where until plateau ended the stable phase inside it
            "low_res_epochs": min(s.low_res_epochs, run.until["stable_end"] if run.until else s.low_res_epochs),
            "mode": plan.mode, "loss_weights": dict(plan.weights), "epoch0_eligible": plan.epoch0_eligible,
            "autocast": run.run_key["autocast"], "channels_last": s.channels_last, **stats}
    if run.until is not None:
        info.update(stable_epochs=run.until["stable_end"], stopped=run.until["reason"])
    if folded is not None:  # off: the info (and the checkpoint's metadata) as before
        info["folded"] = folded
    return TrainResult(model=model, log=pd.DataFrame(run.rows, columns=list(LOG_COLUMNS)),
                       selected_epoch=int(run.best["epoch"]), info=info,
                       timings=[{k: r[k] for k in TIMING_COLUMNS} for r in run.rows])


def train(method: Method, cfg: Mapping[str, Any], data: TrainData, val: ValData | None, seed: int, *,
          checkpointer: Checkpointer, init_state: Mapping | None = None, device="cpu",
          callback: Callable[[int, dict], None] | None = None, show_progress: bool = True,
          selection_tau: float = PAPER.calibrate.fixed_tau) -> TrainResult:
    """Train one (method, seed) run and return the selected model and its log.

    Stage I minimises eq:raw-loss on the voted masks; Stage II eq:refine-loss with the reliability gate
    (eq:reliability-gate) on the geometry terms; the other methods follow their row of the method table
    (:func:`pipeline.methods.resolve_plan`).  Reference masks, when given, only select the checkpoint (and the
    ``until: plateau`` stop): they never enter the loss of an annotation-free method.  Every epoch's state goes
    to ``checkpointer``; a run with the same key resumes after its last saved epoch and gives the same weights.

    Parameters
    ----------
    method : pipeline.methods.Method
        The method (its stage, loss terms, epochs, learning rate and selection rule).
    cfg : Mapping
        The ``train`` params section (validated through the schema here: :class:`Settings`).
    data : TrainData
        The training images and their targets.
    val : ValData or None
        Images with reference masks for checkpoint selection; None or empty: the method's rule without them
        (``until: plateau`` then scores held-out pseudo-labelled images, :func:`schedule.holdout`).
    seed : int
        Seeds the model's initialisation, the batch order and the augmentation.
    checkpointer : Checkpointer
        Where the per-epoch resume state is saved and loaded (:class:`pipeline.training.checkpointing.NoCheckpointer`: none).
    init_state : Mapping or None
        The Stage-I mask path that warm-started methods start from (``method.init == "stage1"``).
    device : str or torch.device
        Where to train (``"cpu"``, ``"cuda"``).
    callback : callable or None
        ``callback(epoch, row)`` after each saved epoch, with the epoch's log row.
    show_progress : bool
        Show a progress bar of the optimizer steps.
    selection_tau : float
        The threshold of eq:inference-mask at which validation scores select checkpoints (``calibrate.fixed_tau``).

    Returns
    -------
    TrainResult
        The selected (or weight-averaged) model on the CPU in eval mode, the log (one row per epoch,
        :data:`LOG_COLUMNS`), the selected epoch, what was selected and why, and the epochs' wall times.

    Raises
    ------
    TrainingDiverged
        A non-finite loss or non-finite weights; nothing of that epoch is saved.
    InputError
        A params value the schema refuses, or a warm-started method without ``init_state`` (or with one that
        does not match ``train.channels``).
    """
    s = Settings.from_params(method, cfg, selection_tau)
    device = torch.device(device)
    if s.num_threads > 0:
        torch.set_num_threads(s.num_threads)
    reuse_freed_memory(device)  # on a CPU each step reuses the memory the last one freed: the same bits, sooner
    plan = resolve_plan(method, cfg, data.stats.get("confidence_pass_ratio"))
    data, held = holdout(data, s.holdout_fraction) if s.until == "plateau" and not _has_val(val) else (data, None)
    run = setup_run(method, cfg, s, plan, data, seed, init_state, device)
    run.holdout = held
    try:
        return _train_run(run, val, checkpointer, callback, show_progress, data.stats)
    finally:
        if run.scratch is not None:
            run.scratch.cleanup()


def _train_run(run: _Run, val: ValData | None, checkpointer: Checkpointer,
               callback: Callable[[int, dict], None] | None, show_progress: bool, stats: Mapping[str, Any]
               ) -> TrainResult:
    """:func:`train` after the setup: resume, the warm-start row (epoch 0), the epochs, the selected result."""
    method, plan, seed = run.method, run.plan, run.seed
    start = _resume(run, checkpointer)
    if start == 1 and not run.rows and method.init == "stage1":
        row = _validated(run, _empty_row(run, 0), val, time.perf_counter())
        run.rows.append(row)
        run.best = select(run.best, plan, val, 0, row, run.model, plan.epoch0_eligible)
    total = (run.epochs - start + 1) * run.steps_per_epoch
    bar = progress(total=total, desc=f"train {method.name} s{seed}") if show_progress and total > 0 else None
    epoch = start
    while epoch <= run.epochs:
        row = train_epoch(run, epoch, val, bar)
        run.rows.append(row)
        if run.until is not None and run.until["stable_end"] is None:
            _stop_stable(run, epoch, row)
            if bar is not None:
                bar.total = bar.n + (run.epochs - epoch) * run.steps_per_epoch
        run.best = select(run.best, plan, val, epoch, row, run.model, plan.select == "best_val" or epoch == run.epochs)
        _average(run, epoch)
        checkpointer.save(_state(run, epoch))
        if callback is not None:
            callback(epoch, row)
        epoch += 1
    if bar is not None:
        bar.close()
    return _result(run, val, stats)
