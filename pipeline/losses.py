"""The student's training losses, one function per paper equation (eq:positive-count .. eq:refine-loss).

Tensors are ``[B, ...]`` with the sample on axis 0; per-sample gates g_i ``[B]`` (eq:reliability-gate) broadcast to
their pixels.  Everything is computed in float32, from logits wherever a log of a probability appears.
"""

from __future__ import annotations

import dataclasses
from types import MappingProxyType
from typing import Mapping

import torch
import torch.nn.functional as F

from pipeline.params import PAPER

_PAPER = PAPER.train  # the paper's constants: the defaults below


def _per_pixel_weights(weights: torch.Tensor | None, like: torch.Tensor) -> torch.Tensor | None:
    """Per-sample weights ``[B]`` broadcast to ``like``'s shape ``[B, ...]``."""
    if weights is None:
        return None
    w = torch.as_tensor(weights, dtype=torch.float32, device=like.device).reshape(-1)
    if w.numel() != like.shape[0]:
        raise ValueError(f"weights: {w.numel()} values for a batch of {like.shape[0]}")
    return w.reshape(-1, *([1] * (like.dim() - 1))).expand_as(like)


def positive_weight(targets: torch.Tensor, weights: torch.Tensor | None = None,
                    max_weight: float = _PAPER.pos_weight_max) -> torch.Tensor:
    """pi = clip(N- / N+, 1, max_weight), N+ = max(sum_i sum_x w_i M_i(x), 1), N- = max(sum_i sum_x w_i (1 - M_i(x)), 1)
    (eq:positive-count, eq:negative-count, eq:positive-weight); w_i = 1 without ``weights``; no gradient."""
    with torch.no_grad():
        t = targets.float()
        w = _per_pixel_weights(weights, t)
        pos, neg = (t, 1.0 - t) if w is None else (t * w, (1.0 - t) * w)
        return torch.clamp(torch.clamp(neg.sum(), min=1.0) / torch.clamp(pos.sum(), min=1.0), 1.0, float(max_weight))


def balanced_bce(logits: torch.Tensor, targets: torch.Tensor, weights: torch.Tensor | None = None,
                 max_weight: float = _PAPER.pos_weight_max) -> torch.Tensor:
    """L = -1/(BHW) sum_i sum_x w_i [pi M_i(x) log P_i(x) + (1 - M_i(x)) log(1 - P_i(x))] (eq:bbce; with ``weights``,
    eq:skeleton-loss's gated form, not renormalised)."""
    z = logits.float()
    t = targets.float().reshape(z.shape)
    pi = positive_weight(t, weights, max_weight)
    w = _per_pixel_weights(weights, z)
    per_px = F.binary_cross_entropy_with_logits(z, t, weight=w, pos_weight=pi, reduction="sum")
    return per_px / z.numel()


def dice_loss(probs: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """Soft Dice (eq:dice): L = 1 - 1/B sum_i (2 sum_x P_i M_i + 1) / (sum_x P_i + sum_x M_i + 1)."""
    p = probs.float().reshape(probs.shape[0], -1)
    t = targets.float().reshape(p.shape)
    ratio = (2.0 * (p * t).sum(1) + 1.0) / (p.sum(1) + t.sum(1) + 1.0)
    return 1.0 - ratio.mean()


def raw_terms(logits: torch.Tensor, targets: torch.Tensor, dice_weight: float = _PAPER.dice_weight,
              max_weight: float = _PAPER.pos_weight_max, probs: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """L_raw = L_BBCE + 0.2 L_Dice (eq:raw-loss) with its parts; ``probs``: sigmoid(logits) when known."""
    bbce = balanced_bce(logits, targets, None, max_weight)
    dice = dice_loss(torch.sigmoid(logits.float()) if probs is None else probs, targets)
    return {"raw": bbce + dice_weight * dice, "bbce": bbce, "dice": dice}


def raw_loss(logits: torch.Tensor, targets: torch.Tensor, dice_weight: float = _PAPER.dice_weight,
             max_weight: float = _PAPER.pos_weight_max) -> torch.Tensor:
    """L_raw (eq:raw-loss) as a scalar."""
    return raw_terms(logits, targets, dice_weight, max_weight)["raw"]


def boundary_band(target_sdf: torch.Tensor, band: float = _PAPER.sdf_band) -> torch.Tensor:
    """B_i(x) = [|D_i^T(x)| <= 0.55] as float (eq:pseudo-boundary-band)."""
    return (target_sdf.float().abs() <= band).float()


def sdf_weight(target_sdf: torch.Tensor, gates: torch.Tensor, band: float = _PAPER.sdf_band,
               base_weight: float = _PAPER.sdf_base_weight) -> torch.Tensor:
    """w_i(x) = g_i [0.15 + 0.85 B_i(x)] (eq:sdf-weight)."""
    b = boundary_band(target_sdf, band)
    return _per_pixel_weights(gates, b) * (base_weight + (1.0 - base_weight) * b)


def sdf_loss(pred: torch.Tensor, target: torch.Tensor, gates: torch.Tensor, band: float = _PAPER.sdf_band,
             base_weight: float = _PAPER.sdf_base_weight, eps: float = _PAPER.loss_eps) -> torch.Tensor:
    """L_SDF = sum_i sum_x w_i(x) |D^S_i(x) - D^T_i(x)| / (sum_i sum_x w_i(x) + eps) (eq:sdf-loss)."""
    d = pred.float().reshape(target.shape)
    w = sdf_weight(target, gates, band, base_weight)
    return (w * (d - target.float()).abs()).sum() / (w.sum() + eps)


def skeleton_loss(logits: torch.Tensor, targets: torch.Tensor, gates: torch.Tensor,
                  max_weight: float = _PAPER.pos_weight_max) -> torch.Tensor:
    """L_skel = BBCE({Z^K_i}, {K^T_i}; {g_i}) (eq:skeleton-loss), pi from the gated counts."""
    return balanced_bce(logits, targets, gates, max_weight)


def predicted_area(probs: torch.Tensor) -> torch.Tensor:
    """a_hat_i = 1/(HW) sum_x P_i(x), ``[B]`` (eq:predicted-area)."""
    return probs.float().reshape(probs.shape[0], -1).mean(1)


def area_error(pred_area: torch.Tensor, area_targets: torch.Tensor, area_eps: float = _PAPER.area_eps) -> torch.Tensor:
    """l_i = |log((a_hat_i + 1e-5) / (a_i + 1e-5))| (eq:area-error)."""
    a = torch.as_tensor(area_targets, dtype=torch.float32, device=pred_area.device).reshape(-1)
    return (torch.log(pred_area.float() + area_eps) - torch.log(a + area_eps)).abs()


def area_loss(probs: torch.Tensor, area_targets: torch.Tensor, gates: torch.Tensor,
              area_eps: float = _PAPER.area_eps, eps: float = _PAPER.loss_eps) -> torch.Tensor:
    """L_area = sum_i g_i l_i / (sum_i g_i + eps) (eq:area-loss); ``area_targets``: a_i (eq:pseudo-area)."""
    g = torch.as_tensor(gates, dtype=torch.float32, device=probs.device).reshape(-1)
    err = area_error(predicted_area(probs), area_targets, area_eps)
    return (g * err).sum() / (g.sum() + eps)


def anchor_loss(logits: torch.Tensor, anchor_probs: torch.Tensor) -> torch.Tensor:
    """Weak region anchoring of the quality-adaptive mode: -1/(BHW) sum [Q log P + (1 - Q) log(1 - P)], Q the frozen
    Stage-I probabilities (docs/decisions.md, "Loss forms the paper does not give")."""
    z = logits.float()
    return F.binary_cross_entropy_with_logits(z, anchor_probs.float().reshape(z.shape), reduction="mean")


def distance_regression_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """mean |D^S - D^T|, ungated (the GABI-inspired baseline)."""
    return (pred.float().reshape(target.shape) - target.float()).abs().mean()


def boundary_weighted_bce(logits: torch.Tensor, targets: torch.Tensor, target_sdf: torch.Tensor,
                          band: float = _PAPER.sdf_band, eps: float = _PAPER.loss_eps) -> torch.Tensor:
    """sum B(x) BCE(Z(x), M(x)) / (sum B(x) + eps), B of eq:pseudo-boundary-band, ungated (the GABI-inspired
    baseline's boundary term)."""
    z = logits.float()
    b = boundary_band(target_sdf, band).reshape(z.shape)
    bce = F.binary_cross_entropy_with_logits(z, targets.float().reshape(z.shape), reduction="none")
    return (b * bce).sum() / (b.sum() + eps)


@dataclasses.dataclass(frozen=True)
class LossConstants:
    """The losses' constants (the paper's by default): eq:raw-loss's 0.2, eq:positive-weight's clip,
    eq:pseudo-boundary-band's 0.55, eq:sdf-weight's 0.15, eq:area-error's 1e-5, the denominators' eps."""

    dice_weight: float = _PAPER.dice_weight
    max_weight: float = _PAPER.pos_weight_max
    sdf_band: float = _PAPER.sdf_band
    sdf_base_weight: float = _PAPER.sdf_base_weight
    area_eps: float = _PAPER.area_eps
    eps: float = _PAPER.loss_eps


#: eq:refine-loss's weights with the paper's lambdas
PAPER_REFINE_WEIGHTS = MappingProxyType({"region": 1.0, "sdf": _PAPER.lambda_sdf, "skel": _PAPER.lambda_skel,
                                         "area": _PAPER.lambda_area})

#: objective term name -> the key of its value in :func:`refine_loss`'s result ("region" is L_raw)
TERM_KEYS = {"region": "raw", "anchor": "anchor", "sdf": "sdf", "dist": "dist", "skel": "skel",
             "area": "area", "boundary": "boundary"}


#: objective term name -> its loss(es) from (float32 mask logits z, p = sigmoid(z), the model's outputs, targets,
#: gates, :class:`LossConstants`); ``region``: L_raw with its eq:raw-loss parts
_TERMS = {
    "region": lambda z, p, o, t, g, c: raw_terms(z, t["mask"], c.dice_weight, c.max_weight, probs=p),
    "anchor": lambda z, p, o, t, g, c: {"anchor": anchor_loss(z, t["anchor"])},
    "sdf": lambda z, p, o, t, g, c: {"sdf": sdf_loss(o["sdf"], t["sdf"], g, c.sdf_band, c.sdf_base_weight, c.eps)},
    "dist": lambda z, p, o, t, g, c: {"dist": distance_regression_loss(o["sdf"], t["sdf"])},
    "skel": lambda z, p, o, t, g, c: {"skel": skeleton_loss(o["skeleton"], t["skeleton"], g, c.max_weight)},
    "area": lambda z, p, o, t, g, c: {"area": area_loss(p, t["area"], g, c.area_eps, c.eps)},
    "boundary": lambda z, p, o, t, g, c: {"boundary": boundary_weighted_bce(z, t["mask"], t["sdf"], c.sdf_band,
                                                                              c.eps)},
}


def refine_loss(outputs: Mapping[str, torch.Tensor], targets: Mapping[str, torch.Tensor],
                gates: torch.Tensor, weights: Mapping[str, float] = PAPER_REFINE_WEIGHTS,
                constants: LossConstants = LossConstants()) -> dict[str, torch.Tensor]:
    """L_refine = L_raw + lambda_SDF L_SDF + lambda_skel L_skel + lambda_area L_area (eq:refine-loss), every method's
    objective as L = sum_t weights[t] L_t; ``loss`` and every term computed, from the model's ``outputs`` (Z, D^S,
    Z^K) and the ``targets`` (M^T, D^T, K^T, a_i, the anchor)."""
    z = outputs["mask"].float()  # one cast (and one sigmoid) shared by the terms: one gradient path
    p = torch.sigmoid(z)
    t: dict[str, torch.Tensor] = {}
    for name in weights:
        if name not in _TERMS:
            raise ValueError(f"unknown loss term {name!r}: expected one of {', '.join(TERM_KEYS)}")
        t.update(_TERMS[name](z, p, outputs, targets, gates, constants))
    total = z.new_zeros(())
    for name, w in weights.items():
        total = total + float(w) * t[TERM_KEYS[name]]
    t["loss"] = total
    return t
