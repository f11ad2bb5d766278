"""Training losses of the student (paper eq:positive-count .. eq:refine-loss), one function per equation.

Conventions
  * ``logits`` / ``probs`` / ``targets`` are tensors ``[B,1,H,W]`` or ``[B,H,W]`` (any trailing shape;
    axis 0 is the sample index ``i``).  Targets are {0,1} floats (or bools).
  * ``gates`` / ``weights`` are per-sample reliability gates ``g_i`` ``[B]`` (eq:reliability-gate),
    broadcast to every pixel of their sample.
  * Every loss is computed in float32 (inputs are upcast), from logits where a log of a probability
    appears, using ``binary_cross_entropy_with_logits`` (a log-sum-exp form: no ``log(0)`` for
    saturated logits).
  * The constants default to the paper's values; the training loop passes them from
    ``params.yaml`` (section ``train``) as a :class:`LossConstants`.
  * :func:`refine_loss` is the one objective (eq:refine-loss, with eq:raw-loss inside it) that every
    training method uses, with the method's term weights.
  * Pure functions: no I/O, no state.
"""

from __future__ import annotations

import dataclasses
from types import MappingProxyType
from typing import Mapping

import torch
import torch.nn.functional as F

from pipeline.params import PAPER

# the paper's constants, from the params schema (their one place)
PAPER_POS_WEIGHT_MAX = PAPER.train.pos_weight_max
PAPER_DICE_WEIGHT = PAPER.train.dice_weight
PAPER_SDF_BAND = PAPER.train.sdf_band
PAPER_SDF_BASE_WEIGHT = PAPER.train.sdf_base_weight
PAPER_AREA_EPS = PAPER.train.area_eps
PAPER_EPS = PAPER.train.loss_eps


def _per_pixel_weights(weights: torch.Tensor | None, like: torch.Tensor) -> torch.Tensor | None:
    """Per-sample weights ``[B]`` broadcast to ``like``'s shape ``[B, ...]``."""
    if weights is None:
        return None
    w = torch.as_tensor(weights, dtype=torch.float32, device=like.device).reshape(-1)
    if w.numel() != like.shape[0]:
        raise ValueError(f"weights: {w.numel()} values for a batch of {like.shape[0]}")
    return w.reshape(-1, *([1] * (like.dim() - 1))).expand_as(like)


def positive_weight(targets: torch.Tensor, weights: torch.Tensor | None = None,
                    max_weight: float = PAPER_POS_WEIGHT_MAX) -> torch.Tensor:
    """Batch-shared positive-class weight pi (eq:positive-count, eq:negative-count, eq:positive-weight).

    ``N+ = max(sum_i sum_x w_i M_i(x), 1)``, ``N- = max(sum_i sum_x w_i (1 - M_i(x)), 1)`` and
    ``pi = clip(N- / N+, 1, max_weight)``.  Without ``weights`` every ``w_i = 1`` (the paper's
    eq:positive-count); with per-sample gates the counts are the *gated* counts (eq:skeleton-loss).
    All-background batch: N+ = 1, pi = min(N-, max_weight).  All-foreground: N- = 1, pi = 1.
    Zero gates: N+ = N- = 1, pi = 1.  Returns a float32 scalar tensor (no gradient).
    """
    with torch.no_grad():
        t = targets.float()
        w = _per_pixel_weights(weights, t)
        pos = t if w is None else t * w
        neg = (1.0 - t) if w is None else (1.0 - t) * w
        n_pos = torch.clamp(pos.sum(), min=1.0)
        n_neg = torch.clamp(neg.sum(), min=1.0)
        return torch.clamp(n_neg / n_pos, 1.0, float(max_weight))


def balanced_bce(logits: torch.Tensor, targets: torch.Tensor, weights: torch.Tensor | None = None,
                 max_weight: float = PAPER_POS_WEIGHT_MAX) -> torch.Tensor:
    """Balanced binary cross-entropy (eq:bbce; with ``weights``, the gated form of eq:skeleton-loss).

    ``L = -1/(B H W) sum_i sum_x w_i [pi M_i(x) log P_i(x) + (1 - M_i(x)) log(1 - P_i(x))]`` with
    ``P = sigmoid(logits)``, ``pi`` from :func:`positive_weight` (gated counts when ``weights`` is
    given) and ``w_i = 1`` without ``weights``.  The mean is over all B·H·W pixels -- gates are *not*
    renormalised, so an all-zero-gate batch gives exactly 0.  Computed from logits (stable).
    """
    z = logits.float()
    t = targets.float().reshape(z.shape)
    pi = positive_weight(t, weights, max_weight)
    w = _per_pixel_weights(weights, z)
    per_px = F.binary_cross_entropy_with_logits(z, t, weight=w, pos_weight=pi, reduction="sum")
    return per_px / z.numel()


def dice_loss(probs: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """Soft Dice loss with +1 smoothing, per image then averaged over the batch (eq:dice).

    ``L = 1 - 1/B sum_i (2 sum_x P_i M_i + 1) / (sum_x P_i + sum_x M_i + 1)``.
    All-background target with P = 0: the image's ratio is 1 (loss 0).
    """
    p = probs.float().reshape(probs.shape[0], -1)
    t = targets.float().reshape(p.shape)
    ratio = (2.0 * (p * t).sum(1) + 1.0) / (p.sum(1) + t.sum(1) + 1.0)
    return 1.0 - ratio.mean()


def raw_terms(logits: torch.Tensor, targets: torch.Tensor, dice_weight: float = PAPER_DICE_WEIGHT,
              max_weight: float = PAPER_POS_WEIGHT_MAX, probs: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Stage-I silhouette loss ``L_raw = L_BBCE + 0.2 L_Dice`` (eq:raw-loss), ungated, with its parts.

    The one implementation of eq:raw-loss: returns ``{"raw": L_raw, "bbce": L_BBCE (eq:bbce),
    "dice": L_Dice (eq:dice)}`` (float32 scalars); ``dice_weight`` is the 0.2.  ``probs``:
    ``sigmoid(logits)`` when the caller has it already (one graph node shared with other terms).
    """
    bbce = balanced_bce(logits, targets, None, max_weight)
    dice = dice_loss(torch.sigmoid(logits.float()) if probs is None else probs, targets)
    return {"raw": bbce + dice_weight * dice, "bbce": bbce, "dice": dice}


def raw_loss(logits: torch.Tensor, targets: torch.Tensor, dice_weight: float = PAPER_DICE_WEIGHT,
             max_weight: float = PAPER_POS_WEIGHT_MAX) -> torch.Tensor:
    """``L_raw`` (eq:raw-loss) as a scalar: :func:`raw_terms`'s ``raw``."""
    return raw_terms(logits, targets, dice_weight, max_weight)["raw"]


def boundary_band(target_sdf: torch.Tensor, band: float = PAPER_SDF_BAND) -> torch.Tensor:
    """Pseudo-boundary band ``B_i(x) = [|D_i^T(x)| <= 0.55]`` as float (eq:pseudo-boundary-band)."""
    return (target_sdf.float().abs() <= band).float()


def sdf_weight(target_sdf: torch.Tensor, gates: torch.Tensor, band: float = PAPER_SDF_BAND,
               base_weight: float = PAPER_SDF_BASE_WEIGHT) -> torch.Tensor:
    """Per-pixel SDF weight ``w_i(x) = g_i [0.15 + 0.85 B_i(x)]`` (eq:sdf-weight)."""
    b = boundary_band(target_sdf, band)
    return _per_pixel_weights(gates, b) * (base_weight + (1.0 - base_weight) * b)


def sdf_loss(pred: torch.Tensor, target: torch.Tensor, gates: torch.Tensor, band: float = PAPER_SDF_BAND,
             base_weight: float = PAPER_SDF_BASE_WEIGHT, eps: float = PAPER_EPS) -> torch.Tensor:
    """Gated, boundary-weighted L1 on the normalised SDF (eq:sdf-loss).

    ``L = sum_i sum_x w_i(x) |D^S_i(x) - D^T_i(x)| / (sum_i sum_x w_i(x) + eps)`` with ``w`` from
    :func:`sdf_weight`; ``pred`` is the tanh SDF head output in [-1, 1].  All gates zero -> 0.
    With ``gates`` all one this is the *ungated* form (ablation ``no_gate``).
    """
    d = pred.float().reshape(target.shape)
    w = sdf_weight(target, gates, band, base_weight)
    return (w * (d - target.float()).abs()).sum() / (w.sum() + eps)


def skeleton_loss(logits: torch.Tensor, targets: torch.Tensor, gates: torch.Tensor,
                  max_weight: float = PAPER_POS_WEIGHT_MAX) -> torch.Tensor:
    """``L_skel = BBCE({Z^K_i}, {K^T_i}; {g_i})`` (eq:skeleton-loss): :func:`balanced_bce` with the gates
    as per-pixel weights and pi from the gated skeleton-pixel counts."""
    return balanced_bce(logits, targets, gates, max_weight)


def predicted_area(probs: torch.Tensor) -> torch.Tensor:
    """Predicted foreground fraction ``a_hat_i = 1/(HW) sum_x P_i(x)`` per sample, ``[B]`` (eq:predicted-area)."""
    return probs.float().reshape(probs.shape[0], -1).mean(1)


def area_error(pred_area: torch.Tensor, area_targets: torch.Tensor, area_eps: float = PAPER_AREA_EPS) -> torch.Tensor:
    """``l_i = |log((a_hat_i + 1e-5) / (a_i + 1e-5))|`` per sample (eq:area-error)."""
    a = torch.as_tensor(area_targets, dtype=torch.float32, device=pred_area.device).reshape(-1)
    return (torch.log(pred_area.float() + area_eps) - torch.log(a + area_eps)).abs()


def area_loss(probs: torch.Tensor, area_targets: torch.Tensor, gates: torch.Tensor,
              area_eps: float = PAPER_AREA_EPS, eps: float = PAPER_EPS) -> torch.Tensor:
    """Gate-weighted mean log-area-ratio error ``sum_i g_i l_i / (sum_i g_i + eps)`` (eq:area-loss).

    ``area_targets`` are the pseudo-mask area ratios ``a_i`` (eq:pseudo-area).  All gates zero -> 0.
    """
    g = torch.as_tensor(gates, dtype=torch.float32, device=probs.device).reshape(-1)
    err = area_error(predicted_area(probs), area_targets, area_eps)
    return (g * err).sum() / (g.sum() + eps)


def anchor_loss(logits: torch.Tensor, anchor_probs: torch.Tensor) -> torch.Tensor:
    """Weak region anchoring to a frozen reference prediction (quality-adaptive mode; not a paper equation).

    Decision (the paper names the mechanism, not its form): binary cross-entropy between the student's
    mask logits and the frozen Stage-I probabilities used as *soft* targets, averaged over all pixels,
    ``-1/(BHW) sum [Q log P + (1 - Q) log(1 - P)]``.  Its minimum over P is at P = Q (the gradient is
    ``P - Q``, like the region BCE), so it pulls the mask toward the Stage-I silhouette without the
    positive re-weighting of eq:bbce.  Computed from logits (stable).
    """
    z = logits.float()
    return F.binary_cross_entropy_with_logits(z, anchor_probs.float().reshape(z.shape), reduction="mean")


def distance_regression_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Ungated, unweighted L1 distance-field regression ``mean |D^S - D^T|`` (GABI-inspired baseline)."""
    return (pred.float().reshape(target.shape) - target.float()).abs().mean()


def boundary_weighted_bce(logits: torch.Tensor, targets: torch.Tensor, target_sdf: torch.Tensor,
                          band: float = PAPER_SDF_BAND, eps: float = PAPER_EPS) -> torch.Tensor:
    """Mask BCE restricted to the pseudo-boundary band (GABI-inspired baseline's boundary term).

    ``sum B(x) BCE(Z(x), M(x)) / (sum B(x) + eps)`` with ``B`` from :func:`boundary_band`; ungated.
    Decision: the band is the same ``|D^T| <= 0.55`` band as eq:pseudo-boundary-band so the two
    geometry baselines differ in gating and staging, not in what "boundary" means.
    """
    z = logits.float()
    b = boundary_band(target_sdf, band).reshape(z.shape)
    bce = F.binary_cross_entropy_with_logits(z, targets.float().reshape(z.shape), reduction="none")
    return (b * bce).sum() / (b.sum() + eps)


@dataclasses.dataclass(frozen=True)
class LossConstants:
    """The numeric constants of the losses (defaults: the paper's values; training passes ``train.*``).

    ``dice_weight`` 0.2 (eq:raw-loss), ``max_weight`` the pi clip 500 (eq:positive-weight), ``sdf_band``
    0.55 (eq:pseudo-boundary-band), ``sdf_base_weight`` 0.15 (eq:sdf-weight), ``area_eps`` 1e-5
    (eq:area-error), ``eps`` the denominators' 1e-6 (eq:sdf-loss, eq:area-loss).
    """

    dice_weight: float = PAPER_DICE_WEIGHT
    max_weight: float = PAPER_POS_WEIGHT_MAX
    sdf_band: float = PAPER_SDF_BAND
    sdf_base_weight: float = PAPER_SDF_BASE_WEIGHT
    area_eps: float = PAPER_AREA_EPS
    eps: float = PAPER_EPS


#: eq:refine-loss's weights with the paper's lambdas: L_raw (region) weighs 1
PAPER_REFINE_WEIGHTS = MappingProxyType({"region": 1.0, "sdf": PAPER.train.lambda_sdf, "skel": PAPER.train.lambda_skel,
                                         "area": PAPER.train.lambda_area})  # eq:refine-loss, the schema's lambdas

#: objective term name -> the key of its value in :func:`refine_loss`'s result ("region" is L_raw)
TERM_KEYS = {"region": "raw", "anchor": "anchor", "sdf": "sdf", "dist": "dist", "skel": "skel",
             "area": "area", "boundary": "boundary"}


def _term(name: str, z: torch.Tensor, p: torch.Tensor, outputs: Mapping[str, torch.Tensor],
          targets: Mapping[str, torch.Tensor], gates: torch.Tensor, c: LossConstants) -> dict[str, torch.Tensor]:
    """One objective term (and, for ``region``, its eq:raw-loss parts) from its equation's function;
    ``z`` are the float32 mask logits and ``p = sigmoid(z)``."""
    if name == "region":
        return raw_terms(z, targets["mask"], c.dice_weight, c.max_weight, probs=p)
    if name == "sdf":
        return {"sdf": sdf_loss(outputs["sdf"], targets["sdf"], gates, c.sdf_band, c.sdf_base_weight, c.eps)}
    if name == "skel":
        return {"skel": skeleton_loss(outputs["skeleton"], targets["skeleton"], gates, c.max_weight)}
    if name == "area":
        return {"area": area_loss(p, targets["area"], gates, c.area_eps, c.eps)}
    if name == "dist":
        return {"dist": distance_regression_loss(outputs["sdf"], targets["sdf"])}
    if name == "boundary":
        return {"boundary": boundary_weighted_bce(z, targets["mask"], targets["sdf"], c.sdf_band, c.eps)}
    if name == "anchor":
        return {"anchor": anchor_loss(z, targets["anchor"])}
    raise ValueError(f"unknown loss term {name!r}: expected one of {', '.join(TERM_KEYS)}")


def refine_loss(outputs: Mapping[str, torch.Tensor], targets: Mapping[str, torch.Tensor],
                gates: torch.Tensor, weights: Mapping[str, float] = PAPER_REFINE_WEIGHTS,
                constants: LossConstants = LossConstants()) -> dict[str, torch.Tensor]:
    """Stage-II objective (eq:refine-loss), the one implementation every training method uses::

        L_refine = L_raw + lambda_SDF L_SDF + lambda_skel L_skel + lambda_area L_area

    ``weights`` maps each term in the objective to its weight, ``L = sum_t weights[t] L_t`` (summed in
    ``weights``' order); the default is the paper's eq:refine-loss.  Terms: ``region`` = L_raw
    (eq:raw-loss, ungated), ``sdf`` (eq:sdf-loss), ``skel`` (eq:skeleton-loss), ``area``
    (eq:area-loss), and the comparison methods' ``dist`` (:func:`distance_regression_loss`),
    ``boundary`` (:func:`boundary_weighted_bce`) and ``anchor`` (:func:`anchor_loss`).  So Stage I is
    ``weights={"region": 1}`` (L = L_raw), the quality-adaptive ``geometry_only`` mode omits
    ``region``, and the ``no_gate`` ablation passes gates of one.

    ``outputs``: ``mask`` (logits Z), ``sdf`` (D^S), ``skeleton`` (logits Z^K), as the terms need.
    ``targets``: ``mask`` (M^T), ``sdf`` (D^T), ``skeleton`` (K^T), ``area`` (a_i), ``anchor`` (frozen
    Stage-I probabilities), as the terms need.  The gate ``g_i`` [B] is applied exactly once, inside
    L_SDF, L_skel and L_area; L_raw (the primary mask loss) is ungated.
    Returns ``{"loss"}`` plus every computed term (``raw``, ``bbce``, ``dice`` for ``region``; the
    other terms under their own names), float32 scalars.
    """
    z = outputs["mask"].float()  # one cast (and one sigmoid) shared by the terms: one gradient path
    p = torch.sigmoid(z)
    t: dict[str, torch.Tensor] = {}
    for name in weights:
        t.update(_term(name, z, p, outputs, targets, gates, constants))
    total = z.new_zeros(())
    for name, w in weights.items():
        total = total + float(w) * t[TERM_KEYS[name]]
    t["loss"] = total
    return t
