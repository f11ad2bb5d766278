"""Stage I's label-noise levers (pipeline.losses.region_terms) and self-training's targets
(pipeline.training.self_training)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from pipeline import losses
from pipeline.training.self_training import fused_targets


def _batch(seed=0):
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(2, 1, 8, 8, generator=g, requires_grad=True)
    a = torch.randint(0, 7, (2, 1, 8, 8), generator=g).float() / 6  # an agreement map of six prompts
    return z, a


def test_with_every_lever_off_the_region_term_is_eq_raw_loss():
    z, a = _batch()
    c = losses.LossConstants()
    m = (a >= 0.5).float()
    got = losses.region_terms(z, {"mask": m}, torch.ones(2), c, torch.sigmoid(z))
    want = losses.raw_terms(z, m, c.dice_weight, c.max_weight)
    assert all(torch.equal(got[k], want[k]) for k in ("raw", "bbce", "dice"))


def test_the_ignore_band_drops_the_pixels_where_the_prompts_split():
    z, a = _batch()
    c = dataclasses.replace(losses.LossConstants(), ignore_band=0.2)
    losses.region_terms(z, {"mask": a}, torch.ones(2), c, torch.sigmoid(z))["raw"].backward()
    split = (a - 0.5).abs() < 0.2  # 2, 3 or 4 of 6 prompts
    assert split.any() and (~split).any()
    assert torch.all(z.grad[split] == 0) and torch.all(z.grad[~split] != 0)
    # the target outside the band is the vote [A >= 1/2]: a band that drops nothing is eq:raw-loss on the vote
    z2, untied = z.detach().clone().requires_grad_(True), torch.where(a == 0.5, 4 / 6, a)
    kept = losses.region_terms(z2, {"mask": untied}, torch.ones(2), dataclasses.replace(c, ignore_band=0.1),
                               torch.sigmoid(z2))
    ref = losses.raw_terms(z2, (untied >= 0.5).float())
    assert torch.allclose(kept["raw"], ref["raw"])


def test_the_agreement_weight_counts_each_pixel_by_how_unanimous_its_prompts_are():
    z, a = _batch()
    c = dataclasses.replace(losses.LossConstants(), agreement_weight=1.0)
    got = losses.region_terms(z, {"mask": a}, torch.ones(2), c, torch.sigmoid(z))
    w, m = (2 * a - 1).abs(), (a >= 0.5).float()  # |2A - 1|: 1 unanimous, 1/3 at 2 or 4 of 6, 0 at 3 of 6
    p = torch.sigmoid(z)
    assert torch.allclose(got["bbce"], losses.balanced_bce(z, m, w, c.max_weight))
    assert torch.allclose(got["dice"], losses.dice_loss(p * w, m * w))
    got["raw"].backward()
    split = a == 0.5
    assert split.any() and torch.all(z.grad[split] == 0) and torch.all(z.grad[~split] != 0)
    # on a unanimous map every weight is 1: eq:raw-loss on the vote
    z2, unanimous = z.detach().clone().requires_grad_(True), (a >= 0.5).float()
    same = losses.region_terms(z2, {"mask": unanimous}, torch.ones(2), c, torch.sigmoid(z2))
    assert torch.allclose(same["raw"], losses.raw_terms(z2, unanimous)["raw"])
    # a larger gamma weighs the 2-of-6 and 4-of-6 pixels less
    sharper = losses.region_terms(z, {"mask": a}, torch.ones(2), dataclasses.replace(c, agreement_weight=3.0),
                                  torch.sigmoid(z))
    assert torch.allclose(sharper["bbce"], losses.balanced_bce(z, m, w ** 3, c.max_weight))


def test_bootstrapped_targets_mix_in_the_detached_prediction():
    z, a = _batch()
    m = (a >= 0.5).float()
    c = dataclasses.replace(losses.LossConstants(), bootstrap_beta=0.8)
    p = torch.sigmoid(z)
    got = losses.region_terms(z, {"mask": m}, torch.ones(2), c, p)
    want = losses.balanced_bce(z, 0.8 * m + 0.2 * p.detach(), torch.ones_like(m))
    assert torch.allclose(got["bbce"], want)
    assert not torch.allclose(got["bbce"], losses.raw_terms(z, m)["bbce"])


def test_the_levers_apply_to_stage_one_only():
    from pipeline.training.settings import loss_constants
    from tests.builders.training import tiny_cfg

    cfg = tiny_cfg(bootstrap_beta=0.5, ignore_band=0.1)
    assert loss_constants(cfg, stage_one=True).robust_region
    assert not loss_constants(cfg, stage_one=False).robust_region
    weighted = tiny_cfg(agreement_weight=1.0)
    assert loss_constants(weighted, stage_one=True).robust_region
    assert not loss_constants(weighted, stage_one=False).robust_region


def test_fused_targets_follow_their_rule():
    p = np.array([[[0.9, 0.2, 0.6]]], dtype=np.float32)
    m = np.array([[[False, True, False]]])
    assert np.allclose(fused_targets(p, m, "mix", 0.5), [[[0.45, 0.6, 0.3]]])
    assert fused_targets(p, m, "mix", 0.5).dtype == np.float32
    assert fused_targets(p, m, "mix_hard", 0.5).tolist() == m.tolist()  # w <= 1/2: the vote
    assert fused_targets(p, m, "mix_hard", 0.8).tolist() == [[[True, False, False]]]  # 0.72, 0.36, 0.48
    assert np.array_equal(fused_targets(p, m, "prediction", 0.0), p)
    with pytest.raises(ValueError, match="fusion"):
        fused_targets(p, m, "vote", 0.5)
    with pytest.raises(ValueError, match="weight"):
        fused_targets(p, m, "mix", 1.5)


def test_a_departure_from_eq_raw_loss_is_named_in_every_table():
    from pipeline.methods import departures
    from pipeline.report import tables as T

    recorded = {"train.soft_targets": False, "train.bootstrap_beta": 0.8, "train.ignore_band": 0.0}
    assert departures(recorded) == ["bootstrapped targets, beta 0.8"]
    assert departures({"train.bootstrap_beta": 1.0, "train.ignore_band": 0.2}) == ["ignore band 0.2"]
    assert departures({"train.agreement_weight": 1.0}) == ["agreement-weighted loss, gamma 1"]
    assert departures({}) == []  # a run recorded before the levers departs from nothing
    plain = T.label("plain")
    with T.human_trained({}, {"plain": departures(recorded)}):
        assert T.label("plain") == f"{plain} + bootstrapped targets, beta 0.8" and T.label("geodistill") != plain
    assert T.label("plain") == plain
