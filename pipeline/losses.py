"""The student's training losses, one function per paper equation (eq:positive-count .. eq:refine-loss).

Tensors are ``[B, ...]`` with the sample on axis 0; per-sample gates g_i ``[B]`` (eq:reliability-gate)
broadcast to their pixels.  Everything is computed in float32, from logits wherever a log of a probability
appears.
"""

from __future__ import annotations

import dataclasses
from types import MappingProxyType
from typing import Mapping

import torch
import torch.nn.functional as F

from pipeline.methods import off_value, with_part_fields
from pipeline.params import PAPER

__all__ = ["positive_weight", "balanced_bce", "dice_loss", "raw_terms", "sdf_loss", "area_loss", "LossConstants",
           "refine_loss"]

_PAPER = PAPER.train  # the paper's constants: the defaults below


def _per_pixel_weights(weights: torch.Tensor | None, like: torch.Tensor) -> torch.Tensor | None:
    """Broadcast per-sample weights ``[B]`` to ``like``'s shape ``[B, ...]``; pass per-pixel weights through.

    Per-pixel weights hold as many values as ``like`` and more than one dimension.
    """
    if weights is None:
        return None
    w = torch.as_tensor(weights, dtype=torch.float32, device=like.device)
    if w.dim() > 1 and w.numel() == like.numel():
        return w.reshape(like.shape)
    w = w.reshape(-1)
    if w.numel() != like.shape[0]:
        raise ValueError(f"weights: {w.numel()} values for a batch of {like.shape[0]}")
    return w.reshape(-1, *([1] * (like.dim() - 1))).expand_as(like)


def positive_weight(targets: torch.Tensor, weights: torch.Tensor | None = None,
                    max_weight: float = _PAPER.pos_weight_max) -> torch.Tensor:
    """Positive-class weight of the balanced BCE, shared across the batch (no gradient).

    N+ = max(sum_i sum_x w_i M_i(x), 1) (eq:positive-count), N- = max(sum_i sum_x w_i (1 - M_i(x)), 1)
    (eq:negative-count), pi = clip(N- / N+, 1, max_weight) (eq:positive-weight); w_i = 1 without ``weights``.

    Parameters
    ----------
    targets : torch.Tensor
        Binary targets M [B, ...].
    weights : torch.Tensor, optional
        Per-sample weights w_i [B] (the gates of eq:skeleton-loss).
    max_weight : float, optional
        The clip's upper end (default ``train.pos_weight_max``, 500).

    Returns
    -------
    torch.Tensor
        pi, a float32 scalar.

    Raises
    ------
    ValueError
        ``weights`` does not hold one value per sample.
    """
    with torch.no_grad():
        t = targets.float()
        w = _per_pixel_weights(weights, t)
        pos, neg = (t, 1.0 - t) if w is None else (t * w, (1.0 - t) * w)
        return torch.clamp(torch.clamp(neg.sum(), min=1.0) / torch.clamp(pos.sum(), min=1.0), 1.0, float(max_weight))


def balanced_bce(logits: torch.Tensor, targets: torch.Tensor, weights: torch.Tensor | None = None,
                 max_weight: float = _PAPER.pos_weight_max) -> torch.Tensor:
    """Balanced binary cross-entropy (eq:bbce).

    L = -1/(BHW) sum_i sum_x w_i [pi M_i(x) log P_i(x) + (1 - M_i(x)) log(1 - P_i(x))], P = sigmoid(Z), pi of
    :func:`positive_weight`.  With ``weights`` it is eq:skeleton-loss's gated form: w_i scales the pixels and pi
    comes from the gated counts; the mean is not renormalised by the weights.

    Parameters
    ----------
    logits : torch.Tensor
        Logits Z [B, ...].
    targets : torch.Tensor
        Binary targets M, reshaped to the logits' shape.
    weights : torch.Tensor, optional
        Per-sample weights w_i [B]; None: 1.
    max_weight : float, optional
        pi's upper clip (default 500).

    Returns
    -------
    torch.Tensor
        The loss, a float32 scalar.

    Raises
    ------
    ValueError
        ``weights`` does not hold one value per sample.
    """
    z = logits.float()
    t = targets.float().reshape(z.shape)
    pi = positive_weight(t, weights, max_weight)
    w = _per_pixel_weights(weights, z)
    per_px = F.binary_cross_entropy_with_logits(z, t, weight=w, pos_weight=pi, reduction="sum")
    return per_px / z.numel()


def dice_loss(probs: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """Soft Dice loss, per image then averaged (eq:dice).

    L = 1 - 1/B sum_i (2 sum_x P_i M_i + 1) / (sum_x P_i + sum_x M_i + 1); two empty maps give a ratio of 1.

    Parameters
    ----------
    probs : torch.Tensor
        Probabilities P [B, ...].
    targets : torch.Tensor
        Binary targets M, reshaped to [B, -1].

    Returns
    -------
    torch.Tensor
        The loss, a float32 scalar.
    """
    p = probs.float().reshape(probs.shape[0], -1)
    t = targets.float().reshape(p.shape)
    ratio = (2.0 * (p * t).sum(1) + 1.0) / (p.sum(1) + t.sum(1) + 1.0)
    return 1.0 - ratio.mean()


def raw_terms(logits: torch.Tensor, targets: torch.Tensor, dice_weight: float = _PAPER.dice_weight,
              max_weight: float = _PAPER.pos_weight_max, probs: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Stage I's region loss with its parts: L_raw = L_BBCE + 0.2 L_Dice (eq:raw-loss).

    Parameters
    ----------
    logits : torch.Tensor
        Mask logits Z [B, ...].
    targets : torch.Tensor
        Voted pseudo-masks M^T.
    dice_weight : float, optional
        eq:raw-loss's 0.2 (``train.dice_weight``).
    max_weight : float, optional
        pi's upper clip (default 500).
    probs : torch.Tensor, optional
        sigmoid(logits) when already computed.

    Returns
    -------
    dict of str to torch.Tensor
        ``raw``, ``bbce`` and ``dice``, float32 scalars.
    """
    bbce = balanced_bce(logits, targets, None, max_weight)
    dice = dice_loss(torch.sigmoid(logits.float()) if probs is None else probs, targets)
    return {"raw": bbce + dice_weight * dice, "bbce": bbce, "dice": dice}


def boundary_band(target_sdf: torch.Tensor, band: float = _PAPER.sdf_band) -> torch.Tensor:
    """Pseudo-boundary band B_i(x) = [|D_i^T(x)| <= 0.55] (eq:pseudo-boundary-band).

    Parameters
    ----------
    target_sdf : torch.Tensor
        The SDF target D^T.
    band : float, optional
        The band's half-width (``train.sdf_band``, 0.55).

    Returns
    -------
    torch.Tensor
        float32 0/1, the shape of ``target_sdf``.
    """
    return (target_sdf.float().abs() <= band).float()


def sdf_weight(target_sdf: torch.Tensor, gates: torch.Tensor, band: float = _PAPER.sdf_band,
               base_weight: float = _PAPER.sdf_base_weight) -> torch.Tensor:
    """SDF pixel weight w_i(x) = g_i [0.15 + 0.85 B_i(x)] (eq:sdf-weight).

    Parameters
    ----------
    target_sdf : torch.Tensor
        The SDF target D^T [B, ...].
    gates : torch.Tensor
        Gates g_i [B].
    band : float, optional
        The band's half-width, 0.55.
    base_weight : float, optional
        The weight off the band, 0.15 (``train.sdf_base_weight``).

    Returns
    -------
    torch.Tensor
        float32, the shape of ``target_sdf``.

    Raises
    ------
    ValueError
        ``gates`` does not hold one value per sample.
    """
    b = boundary_band(target_sdf, band)
    return _per_pixel_weights(gates, b) * (base_weight + (1.0 - base_weight) * b)


def sdf_loss(pred: torch.Tensor, target: torch.Tensor, gates: torch.Tensor, band: float = _PAPER.sdf_band,
             base_weight: float = _PAPER.sdf_base_weight, eps: float = _PAPER.loss_eps) -> torch.Tensor:
    """Gated, boundary-weighted SDF loss (eq:sdf-loss).

    L_SDF = sum_i sum_x w_i(x) |D^S_i(x) - D^T_i(x)| / (sum_i sum_x w_i(x) + eps), w of :func:`sdf_weight`; a
    batch whose gates are all 0 gives 0.

    Parameters
    ----------
    pred : torch.Tensor
        The SDF head's output D^S in [-1, 1], reshaped to the target's shape.
    target : torch.Tensor
        The SDF target D^T [B, ...].
    gates : torch.Tensor
        Gates g_i [B].
    band : float, optional
        The band's half-width, 0.55.
    base_weight : float, optional
        The weight off the band, 0.15.
    eps : float, optional
        The denominator's epsilon (``train.loss_eps``).

    Returns
    -------
    torch.Tensor
        float32 scalar.

    Raises
    ------
    ValueError
        ``gates`` does not hold one value per sample.
    """
    d = pred.float().reshape(target.shape)
    w = sdf_weight(target, gates, band, base_weight)
    return (w * (d - target.float()).abs()).sum() / (w.sum() + eps)


def skeleton_loss(logits: torch.Tensor, targets: torch.Tensor, gates: torch.Tensor,
                  max_weight: float = _PAPER.pos_weight_max) -> torch.Tensor:
    """Gated skeleton loss L_skel = BBCE({Z^K_i}, {K^T_i}; {g_i}) (eq:skeleton-loss).

    g_i is broadcast as a per-pixel weight; pi comes from the gated counts (:func:`balanced_bce`).

    Parameters
    ----------
    logits : torch.Tensor
        Skeleton-head logits Z^K [B, ...].
    targets : torch.Tensor
        Skeleton targets K^T.
    gates : torch.Tensor
        Gates g_i [B].
    max_weight : float, optional
        pi's upper clip (default 500).

    Returns
    -------
    torch.Tensor
        float32 scalar.

    Raises
    ------
    ValueError
        ``gates`` does not hold one value per sample.
    """
    return balanced_bce(logits, targets, gates, max_weight)


def predicted_area(probs: torch.Tensor) -> torch.Tensor:
    """Predicted area a_hat_i = 1/(HW) sum_x P_i(x) (eq:predicted-area).

    Parameters
    ----------
    probs : torch.Tensor
        Probabilities P [B, ...].

    Returns
    -------
    torch.Tensor
        float32 [B].
    """
    return probs.float().reshape(probs.shape[0], -1).mean(1)


def area_error(pred_area: torch.Tensor, area_targets: torch.Tensor, area_eps: float = _PAPER.area_eps) -> torch.Tensor:
    """Log-ratio area error l_i = |log((a_hat_i + 1e-5) / (a_i + 1e-5))| (eq:area-error).

    Parameters
    ----------
    pred_area : torch.Tensor
        a_hat [B] (:func:`predicted_area`).
    area_targets : torch.Tensor
        a [B] (eq:pseudo-area).
    area_eps : float, optional
        eq:area-error's 1e-5 (``train.area_eps``).

    Returns
    -------
    torch.Tensor
        float32 [B].
    """
    a = torch.as_tensor(area_targets, dtype=torch.float32, device=pred_area.device).reshape(-1)
    return (torch.log(pred_area.float() + area_eps) - torch.log(a + area_eps)).abs()


def area_loss(probs: torch.Tensor, area_targets: torch.Tensor, gates: torch.Tensor,
              area_eps: float = _PAPER.area_eps, eps: float = _PAPER.loss_eps) -> torch.Tensor:
    """Gated area loss L_area = sum_i g_i l_i / (sum_i g_i + eps) (eq:area-loss).

    Parameters
    ----------
    probs : torch.Tensor
        Mask probabilities P [B, ...].
    area_targets : torch.Tensor
        a_i [B] (eq:pseudo-area).
    gates : torch.Tensor
        Gates g_i [B].
    area_eps : float, optional
        eq:area-error's 1e-5.
    eps : float, optional
        The denominator's epsilon.

    Returns
    -------
    torch.Tensor
        float32 scalar; 0 when every gate is 0.
    """
    g = torch.as_tensor(gates, dtype=torch.float32, device=probs.device).reshape(-1)
    err = area_error(predicted_area(probs), area_targets, area_eps)
    return (g * err).sum() / (g.sum() + eps)


def anchor_loss(logits: torch.Tensor, anchor_probs: torch.Tensor) -> torch.Tensor:
    """Weak region anchoring of the quality-adaptive mode.

    -1/(BHW) sum [Q log P + (1 - Q) log(1 - P)], Q the frozen Stage-I probabilities (docs/decisions.md, "Loss
    forms the paper does not give").

    Parameters
    ----------
    logits : torch.Tensor
        Mask logits Z [B, ...].
    anchor_probs : torch.Tensor
        Q, reshaped to the logits' shape.

    Returns
    -------
    torch.Tensor
        float32 scalar.
    """
    z = logits.float()
    return F.binary_cross_entropy_with_logits(z, anchor_probs.float().reshape(z.shape), reduction="mean")


def distance_regression_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Ungated distance regression mean |D^S - D^T| (the GABI-inspired baseline).

    Parameters
    ----------
    pred : torch.Tensor
        D^S, reshaped to the target's shape.
    target : torch.Tensor
        D^T.

    Returns
    -------
    torch.Tensor
        float32 scalar.
    """
    return (pred.float().reshape(target.shape) - target.float()).abs().mean()


def boundary_weighted_bce(logits: torch.Tensor, targets: torch.Tensor, target_sdf: torch.Tensor,
                          band: float = _PAPER.sdf_band, eps: float = _PAPER.loss_eps) -> torch.Tensor:
    """Ungated boundary-band BCE (the GABI-inspired baseline's boundary term).

    sum_x B(x) BCE(Z(x), M(x)) / (sum_x B(x) + eps), B of eq:pseudo-boundary-band.

    Parameters
    ----------
    logits : torch.Tensor
        Mask logits Z [B, ...].
    targets : torch.Tensor
        Binary targets M.
    target_sdf : torch.Tensor
        D^T, which defines the band.
    band : float, optional
        The band's half-width, 0.55.
    eps : float, optional
        The denominator's epsilon.

    Returns
    -------
    torch.Tensor
        float32 scalar.
    """
    z = logits.float()
    b = boundary_band(target_sdf, band).reshape(z.shape)
    bce = F.binary_cross_entropy_with_logits(z, targets.float().reshape(z.shape), reduction="none")
    return (b * bce).sum() / (b.sum() + eps)


@dataclasses.dataclass(frozen=True)
class _LossConstants:
    """The losses' constants, the paper's by default, and the recipe parts read here.

    :func:`pipeline.methods.with_part_fields` adds the parts of :data:`pipeline.methods.PARTS` with home
    ``losses``, each by default at its off value.

    Attributes
    ----------
    dice_weight : float
        eq:raw-loss's 0.2.
    max_weight : float
        eq:positive-weight's upper clip, 500.
    sdf_band : float
        eq:pseudo-boundary-band's 0.55.
    sdf_base_weight : float
        eq:sdf-weight's 0.15.
    area_eps : float
        eq:area-error's 1e-5.
    eps : float
        The denominators' epsilon (eq:sdf-loss, eq:area-loss).
    """

    dice_weight: float = _PAPER.dice_weight
    max_weight: float = _PAPER.pos_weight_max
    sdf_band: float = _PAPER.sdf_band
    sdf_base_weight: float = _PAPER.sdf_base_weight
    area_eps: float = _PAPER.area_eps
    eps: float = _PAPER.loss_eps

    @property
    def robust_region(self) -> bool:
        """Whether Stage I's region term departs from eq:raw-loss (:func:`region_terms`)."""
        return (self.bootstrap_beta != _BETA_OFF or self.ignore_band != _BAND_OFF
                or self.agreement_weight != _GAMMA_OFF)


LossConstants = with_part_fields(_LossConstants, "losses", defaults=True)
_BETA_OFF, _BAND_OFF = off_value("train.bootstrap_beta"), off_value("train.ignore_band")
_GAMMA_OFF = off_value("train.agreement_weight")


def region_terms(logits: torch.Tensor, targets: Mapping[str, torch.Tensor], gates: torch.Tensor,
                 c: LossConstants, probs: torch.Tensor) -> dict[str, torch.Tensor]:
    """Compute the region term: L_raw (eq:raw-loss) on ``targets["mask"]``, with Stage I's label-noise levers.

    With every lever off this is :func:`raw_terms`.  Otherwise, with A the agreement map (eq:agreement-map) that
    ``mask`` then holds under ``ignore_band`` or ``agreement_weight``, P = sigmoid(Z) and w the pixel weights:

    - ``ignore_band`` b > 0: w(x) = [|A(x) - 1/2| >= b], pixels where the prompts split leave the loss; the
      target is M = [A >= 1/2] (eq:majority-vote), or A itself under ``soft_targets``;
    - ``agreement_weight`` gamma > 0: w(x) = |2 A(x) - 1|^gamma (times the band's w), so a pixel counts by how
      unanimous its prompts are (1 where all agree, 0 where they split evenly); the target as under the band;
    - ``bootstrap_beta`` beta < 1: the target is beta M + (1 - beta) P, P detached (Reed et al. 2015, soft).

    L = L_BBCE(Z, T; w) + 0.2 L_Dice(P w, T w): the weighted BBCE of :func:`balanced_bce` (pi from the weighted
    counts, the mean over all pixels) and Dice over the kept pixels.

    Parameters
    ----------
    logits : torch.Tensor
        Mask logits Z [B, 1, H, W] (float32).
    targets : Mapping
        ``mask``: the voted mask or the agreement map [B, 1, H, W].
    gates : torch.Tensor
        Gates g_i [B] (unused: eq:raw-loss is ungated; the signature of every term).
    c : LossConstants
        The constants and the levers.
    probs : torch.Tensor
        sigmoid(logits).

    Returns
    -------
    dict of str to torch.Tensor
        ``raw``, ``bbce`` and ``dice``, float32 scalars.
    """
    t = targets["mask"].float().reshape(logits.shape)
    if not c.robust_region:
        return raw_terms(logits, t, c.dice_weight, c.max_weight, probs=probs)
    w = torch.ones_like(t)
    if c.ignore_band != _BAND_OFF:
        w = (torch.abs(t - 0.5) >= c.ignore_band).float()
    if c.agreement_weight != _GAMMA_OFF:
        w = w * torch.abs(2.0 * t - 1.0).pow(c.agreement_weight)
    if (c.ignore_band != _BAND_OFF or c.agreement_weight != _GAMMA_OFF) and not c.soft_targets:
        t = (t >= 0.5).float()
    if c.bootstrap_beta != _BETA_OFF:
        t = c.bootstrap_beta * t + (1.0 - c.bootstrap_beta) * probs.detach()
    bbce = balanced_bce(logits, t, w, c.max_weight)
    dice = dice_loss(probs * w, t * w)
    return {"raw": bbce + c.dice_weight * dice, "bbce": bbce, "dice": dice}


#: eq:refine-loss's weights with the paper's lambdas
PAPER_REFINE_WEIGHTS = MappingProxyType({"region": 1.0, "sdf": _PAPER.lambda_sdf, "skel": _PAPER.lambda_skel,
                                         "area": _PAPER.lambda_area})

#: objective term name -> the key of its value in :func:`refine_loss`'s result ("region" is L_raw)
TERM_KEYS = {"region": "raw", "anchor": "anchor", "sdf": "sdf", "dist": "dist", "skel": "skel",
             "area": "area", "boundary": "boundary"}


#: objective term name -> its loss(es) from (float32 mask logits z, p = sigmoid(z), the model's outputs, targets,
#: gates, :class:`LossConstants`); ``region``: L_raw with its eq:raw-loss parts
_TERMS = {
    "region": lambda z, p, o, t, g, c: region_terms(z, t, g, c, p),
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
    """Every method's objective as L = sum_t weights[t] L_t; with the paper's weights, L_refine (eq:refine-loss).

    L_refine = L_raw + lambda_SDF L_SDF + lambda_skel L_skel + lambda_area L_area, lambdas 0.002, 0.001, 0.05.
    The primary mask term (``region``) is ungated; the geometry terms are gated per sample.  Every term named in
    ``weights`` is computed, even at weight 0.

    Parameters
    ----------
    outputs : mapping of str to torch.Tensor
        The model's outputs: ``mask`` (Z), ``sdf`` (D^S), ``skeleton`` (Z^K) as the terms need them.
    targets : mapping of str to torch.Tensor
        ``mask`` (M^T), ``sdf`` (D^T), ``skeleton`` (K^T), ``area`` (a_i), ``anchor`` (Q) as the terms need them.
    gates : torch.Tensor
        Gates g_i [B].
    weights : mapping of str to float, optional
        Term name (a key of :data:`TERM_KEYS`) -> weight; default :data:`PAPER_REFINE_WEIGHTS`.
    constants : LossConstants, optional
        The losses' constants (the paper's by default).

    Returns
    -------
    dict of str to torch.Tensor
        ``loss`` (the weighted sum) and every computed term by its :data:`TERM_KEYS` key (``region`` adds
        ``raw``, ``bbce`` and ``dice``).

    Raises
    ------
    ValueError
        A term name is unknown.
    """
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
