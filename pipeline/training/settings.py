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
from pipeline.methods import Method, method_epochs, method_lr
from pipeline.params import validate_section
from pipeline.training.schedule import low_res_epochs


def loss_constants(cfg: Mapping[str, Any], stage_one: bool = False) -> losses.LossConstants:
    """The losses' constants (eq:raw-loss, eq:positive-weight, eq:sdf-weight, eq:area-error) from the train params.

    Parameters
    ----------
    cfg : Mapping
        A validated ``train`` section.
    stage_one : bool
        Whether the run is Stage I, where the label-noise levers (``bootstrap_beta``, ``ignore_band``) apply;
        elsewhere they are off.

    Returns
    -------
    pipeline.losses.LossConstants
        ``dice_weight``, the positive-weight clip, the SDF band and base weight, the area epsilon and the
        losses' numerical epsilon.
    """
    return losses.LossConstants(dice_weight=float(cfg["dice_weight"]), max_weight=float(cfg["pos_weight_max"]),
                                sdf_band=float(cfg["sdf_band"]), sdf_base_weight=float(cfg["sdf_base_weight"]),
                                area_eps=float(cfg["area_eps"]), eps=float(cfg["loss_eps"]),
                                soft_targets=bool(cfg["soft_targets"]),
                                bootstrap_beta=float(cfg["bootstrap_beta"]) if stage_one else 1.0,
                                ignore_band=float(cfg["ignore_band"]) if stage_one else 0.0)


@dataclasses.dataclass(frozen=True)
class Settings:
    """The ``train.*`` values one (method, seed) run uses; each field is the schema key of the same name unless
    noted, and none has a default (the schema's is the only one).

    ``epochs`` and ``lr`` follow the method table (:func:`pipeline.methods.method_epochs`, ``method_lr``);
    ``hflip`` is ``train.augment_hflip``, ``bf1_tolerance`` ``train.val_bf1_tolerance``, ``selection_tau`` the
    calibrate stage's fixed tau; ``augment`` is None when ``train.augment`` is off; ``until`` and
    ``low_res_epochs`` (:func:`pipeline.training.schedule.low_res_epochs`) apply to Stage I only, other stages
    get ``"epochs"`` and 0.
    """

    epochs: int
    lr: float
    batch_size: int
    weight_decay: float
    schedule: str
    precision: str
    channels_last: bool
    hflip: bool
    num_threads: int
    bf1_tolerance: float
    constants: losses.LossConstants
    selection_tau: float
    precise_bn: bool
    warmup_epochs: int
    average_last: int
    decay_fraction: float
    augment: AugmentSpec | None
    ema_decay: float
    until: str
    step_budget: int
    plateau_gain: float
    plateau_min_epochs: int
    plateau_min_steps: int
    holdout_fraction: float
    low_res_epochs: int
    validate_low_res: bool

    @classmethod
    def from_params(cls, method: Method, cfg: Mapping[str, Any], selection_tau: float) -> "Settings":
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

        Raises
        ------
        pipeline.runtime.errors.InputError
            A value the schema refuses, named by its key.
        """
        cfg = validate_section("train", cfg)
        stage_one = method.stage == 1
        epochs = method_epochs(method, cfg)
        return cls(epochs=epochs, lr=method_lr(method, cfg), batch_size=int(cfg["batch_size"]),
                   weight_decay=float(cfg["weight_decay"]), schedule=str(cfg["schedule"]),
                   precision=str(cfg["precision"]), channels_last=bool(cfg["channels_last"]),
                   hflip=bool(cfg["augment_hflip"]), num_threads=int(cfg["num_threads"]),
                   bf1_tolerance=float(cfg["val_bf1_tolerance"]), constants=loss_constants(cfg, stage_one),
                   selection_tau=float(selection_tau), precise_bn=bool(cfg["precise_bn"]),
                   warmup_epochs=int(cfg["warmup_epochs"]), average_last=int(cfg["average_last"]),
                   decay_fraction=float(cfg["decay_fraction"]),
                   augment=AugmentSpec.from_params(cfg["augmentation"]) if cfg["augment"] else None,
                   ema_decay=float(cfg["ema_decay"]), until=str(cfg["until"]) if stage_one else "epochs",
                   step_budget=int(cfg["step_budget"]), plateau_gain=float(cfg["plateau_gain"]),
                   plateau_min_epochs=int(cfg["plateau_min_epochs"]),
                   plateau_min_steps=int(cfg["plateau_min_steps"]),
                   holdout_fraction=float(cfg["holdout_fraction"]),
                   low_res_epochs=low_res_epochs(epochs, float(cfg["low_res_fraction"])) if stage_one else 0,
                   validate_low_res=bool(cfg["validate_low_res"]))
