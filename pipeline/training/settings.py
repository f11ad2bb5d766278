"""The ``train.*`` values one training run uses, read once from the validated params.

The params schema (:class:`pipeline.params.TrainParams`) is the only place a default lives: :class:`Settings`
has no field defaults and :meth:`Settings.from_params` reads every key without a fallback, after the section
went through the schema (:func:`pipeline.params.validate_section` fills what a caller left out).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping

from pipeline import losses
from pipeline.augment import AugmentSpec
from pipeline.methods import Method, method_epochs, method_lr, parts_of, with_part_fields
from pipeline.params import validate_section
from pipeline.training.schedule import low_res_epochs

__all__ = ["Settings"]


def loss_constants(cfg: Mapping[str, Any], stage_one: bool = False) -> losses.LossConstants:
    """Read the losses' constants (eq:raw-loss, eq:positive-weight, eq:sdf-weight, eq:area-error) from ``cfg``.

    Parameters
    ----------
    cfg : Mapping
        A validated ``train`` section.
    stage_one : bool
        Whether the run is Stage I, where the label-noise levers (``bootstrap_beta``, ``ignore_band``,
        ``agreement_weight``) apply; elsewhere they are off.

    Returns
    -------
    pipeline.losses.LossConstants
        ``dice_weight``, the positive-weight clip, the SDF band (eq:pseudo-boundary-band) and base weight, the
        area epsilon, the losses' numerical epsilon, and the recipe parts read by the losses
        (:data:`pipeline.methods.PARTS` with home ``losses``; a Stage-I part is off outside Stage I).
    """
    return losses.LossConstants(dice_weight=float(cfg["dice_weight"]), max_weight=float(cfg["pos_weight_max"]),
                                sdf_band=float(cfg["sdf_band"]), sdf_base_weight=float(cfg["sdf_base_weight"]),
                                area_eps=float(cfg["area_eps"]), eps=float(cfg["loss_eps"]),
                                **{p.name: p.value_for(cfg, stage_one) for p in parts_of("train", "losses")})


@dataclasses.dataclass(frozen=True)
class _Settings:
    """The ``train.*`` values one (method, seed) run uses, built by :meth:`from_params`.

    Each field is the schema key of the same name unless noted, and none has a default (the schema's is the only
    one).  Epochs and steps count optimizer passes over the training set and optimizer steps; fractions are in
    [0, 1].

    Attributes
    ----------
    epochs : int
        The run's epochs, at least 1: the sum of the method's epoch keys (:func:`pipeline.methods.method_epochs`;
        Stage I ``train.epochs_stage1``, the cap under ``until: plateau``).
    lr : float
        The peak learning rate (:func:`pipeline.methods.method_lr`: ``train.lr_stage1`` times ``train.lr_scale``
        for Stage I, ``train.lr_stage2`` otherwise).
    weight_decay : float
        AdamW's decoupled weight decay.
    channels_last : bool
        Train in the channels-last memory format.
    hflip : bool
        ``train.augment_hflip``: flip each image left-right with probability 1/2 per epoch (unused when
        ``augment`` is set).
    num_threads : int
        torch CPU threads; 0 = torch's default.
    bf1_tolerance : float
        ``train.val_bf1_tolerance``: the Boundary F1 tolerance in pixels of the validation tie-break.
    constants : pipeline.losses.LossConstants
        The losses' constants (:func:`loss_constants`).
    selection_tau : float
        The threshold of eq:inference-mask at which validation scores select checkpoints
        (``calibrate.fixed_tau``; not a ``train`` key).
    precise_bn : bool
        Recompute the BN running statistics over the training images before each validation.
    decay_fraction : float
        The ``wsd`` schedule's (and ``until: plateau``'s) decay share of the run, in (0, 1].
    augment : pipeline.augment.AugmentSpec or None
        The target-consistent augmentation (``train.augmentation``); None when ``train.augment`` is off.
    step_budget : int
        Under ``until: plateau``, optimizer steps at most, warm-up and decay included; 0 = none.
    plateau_gain : float
        Under ``until: plateau``, the validation Image IoU gain below which the stable phase stops.
    plateau_min_epochs : int
        Under ``until: plateau``, the scored stable epochs before the rule may stop.
    plateau_min_steps : int
        Under ``until: plateau``, the optimizer steps of scored epochs before the rule may stop; 0 = epochs only.
    holdout_fraction : float
        Under ``until: plateau`` without validation masks, the share of the training images held out and scored
        against their vote (:func:`pipeline.training.schedule.holdout`).
    low_res_epochs : int
        The first epochs trained at half the side (:func:`pipeline.training.schedule.low_res_epochs` of
        ``train.low_res_fraction``); Stage I only, other stages get 0.
    validate_low_res : bool
        Validate after the half-side epochs too; off, those no rule reads are skipped and logged as NaN.
    """

    epochs: int
    lr: float
    weight_decay: float
    channels_last: bool
    hflip: bool
    num_threads: int
    bf1_tolerance: float
    constants: losses.LossConstants
    selection_tau: float
    precise_bn: bool
    decay_fraction: float
    augment: AugmentSpec | None
    step_budget: int
    plateau_gain: float
    plateau_min_epochs: int
    plateau_min_steps: int
    holdout_fraction: float
    low_res_epochs: int
    validate_low_res: bool

    @classmethod
    def from_params(cls, method: Method, cfg: Mapping[str, Any], selection_tau: float) -> "_Settings":
        """Read the train section for ``method``.

        Parameters
        ----------
        method : pipeline.methods.Method
            The method: its stage picks the epochs, learning rate and whether the Stage-I parts apply.
        cfg : Mapping
            The ``train`` section; validated here through the schema, which fills the keys a caller left out.
        selection_tau : float
            The threshold validation scores use for checkpoint selection (``calibrate.fixed_tau``).

        Returns
        -------
        Settings
            The run's values, read without a fallback from the validated section.

        Raises
        ------
        pipeline.runtime.errors.InputError
            A value the schema refuses, named by its key, or method epochs that sum to less than 1
            (:func:`pipeline.methods.method_epochs`).
        """
        cfg = validate_section("train", cfg)
        stage_one = method.stage == 1
        epochs = method_epochs(method, cfg)
        return cls(epochs=epochs, lr=method_lr(method, cfg),
                   weight_decay=float(cfg["weight_decay"]), channels_last=bool(cfg["channels_last"]),
                   hflip=bool(cfg["augment_hflip"]), num_threads=int(cfg["num_threads"]),
                   bf1_tolerance=float(cfg["val_bf1_tolerance"]), constants=loss_constants(cfg, stage_one),
                   selection_tau=float(selection_tau), precise_bn=bool(cfg["precise_bn"]),
                   decay_fraction=float(cfg["decay_fraction"]),
                   augment=AugmentSpec.from_params(cfg["augmentation"]) if cfg["augment"] else None,
                   step_budget=int(cfg["step_budget"]), plateau_gain=float(cfg["plateau_gain"]),
                   plateau_min_epochs=int(cfg["plateau_min_epochs"]),
                   plateau_min_steps=int(cfg["plateau_min_steps"]),
                   holdout_fraction=float(cfg["holdout_fraction"]),
                   low_res_epochs=low_res_epochs(epochs, float(cfg["low_res_fraction"])) if stage_one else 0,
                   validate_low_res=bool(cfg["validate_low_res"]),
                   **{p.name: p.value_for(cfg, stage_one) for p in parts_of("train", "settings")})


#: the run's values: :class:`_Settings` and the recipe parts read here (:data:`pipeline.methods.PARTS` with home
#: ``settings``)
Settings = with_part_fields(_Settings, "settings")
