"""Every loss against values computed by hand on tiny tensors (eq:positive-count .. eq:refine-loss)."""

from __future__ import annotations

import math

import pytest
import torch

from pipeline import losses

L = math.log


def sig(z):
    return 1.0 / (1.0 + math.exp(-z))


def t(x):
    return torch.tensor(x, dtype=torch.float32)


# ---- eq:positive-count .. eq:positive-weight ------------------------------------------------------
def test_positive_weight_counts_and_clip():
    m = t([[[1, 0], [0, 0]], [[0, 0], [0, 0]]])  # N+ = 1, N- = 7
    assert losses.positive_weight(m).item() == pytest.approx(7.0)
    # all background: N+ = max(0, 1) = 1, N- = 8 -> pi = 8; with a clip at 5 -> 5
    z = torch.zeros(2, 2, 2)
    assert losses.positive_weight(z).item() == pytest.approx(8.0)
    assert losses.positive_weight(z, max_weight=5).item() == pytest.approx(5.0)
    # all foreground: N- = max(0, 1) = 1, N+ = 8 -> 1/8 clipped up to 1
    assert losses.positive_weight(torch.ones(2, 2, 2)).item() == pytest.approx(1.0)
    # gated counts: sample 0 gated by 0.5, sample 1 by 0 -> N+ = 0.5 -> 1, N- = 1.5 -> 1.5
    assert losses.positive_weight(m, t([0.5, 0.0])).item() == pytest.approx(1.5)
    # all gates zero: N+ = N- = 1 -> pi = 1
    assert losses.positive_weight(m, t([0.0, 0.0])).item() == pytest.approx(1.0)
    # clip at 500 on a large background
    big = torch.zeros(1, 40, 40)
    big[0, 0, 0] = 1
    assert losses.positive_weight(big).item() == pytest.approx(500.0)


# ---- eq:bbce ----------------------------------------------------------------------------------------
def test_balanced_bce_hand_value():
    z = t([[[2.0, -1.0]], [[0.5, 0.0]]])  # B=2, H=1, W=2
    m = t([[[1.0, 0.0]], [[0.0, 0.0]]])   # N+ = 1, N- = 3 -> pi = 3
    expected = -(3 * L(sig(2.0)) + L(1 - sig(-1.0)) + L(1 - sig(0.5)) + L(1 - sig(0.0))) / 4
    assert losses.balanced_bce(z, m).item() == pytest.approx(expected, rel=1e-6)


def test_balanced_bce_all_background_and_all_foreground():
    z = t([[[1.0, -2.0]]])
    bg = torch.zeros(1, 1, 2)
    assert losses.balanced_bce(z, bg).item() == pytest.approx(-(L(1 - sig(1.0)) + L(1 - sig(-2.0))) / 2, rel=1e-6)
    fg = torch.ones(1, 1, 2)  # pi = 1
    assert losses.balanced_bce(z, fg).item() == pytest.approx(-(L(sig(1.0)) + L(sig(-2.0))) / 2, rel=1e-6)


def test_balanced_bce_is_stable_for_saturated_logits():
    z = t([[[80.0, -80.0]]])
    m = t([[[0.0, 1.0]]])  # confidently wrong: finite, ~ (80 + pi*80)/2 with pi = 1
    v = losses.balanced_bce(z, m)
    assert math.isfinite(v.item()) and v.item() == pytest.approx(80.0, rel=1e-4)


def test_gated_balanced_bce_hand_value_and_zero_gates():
    z = t([[[1.0, -1.0]], [[0.0, 2.0]]])
    k = t([[[1.0, 0.0]], [[0.0, 1.0]]])
    g = t([0.5, 0.25])
    # gated counts: N+ = 0.5 + 0.25 -> max(0.75, 1) = 1; N- = 0.5 + 0.25 -> 1  => pi = 1
    expected = -(0.5 * (L(sig(1.0)) + L(1 - sig(-1.0))) + 0.25 * (L(1 - sig(0.0)) + L(sig(2.0)))) / 4
    assert losses.balanced_bce(z, k, g).item() == pytest.approx(expected, rel=1e-6)
    assert losses.skeleton_loss(z, k, g).item() == pytest.approx(expected, rel=1e-6)
    assert losses.balanced_bce(z, k, t([0.0, 0.0])).item() == 0.0
    # gated pi: gates 1 and 1 with 3 negatives and 1 positive -> pi = 3 vs. the ungated pi
    k2 = t([[[1.0, 0.0]], [[0.0, 0.0]]])
    ones = losses.balanced_bce(z, k2, t([1.0, 1.0]))
    assert ones.item() == pytest.approx(losses.balanced_bce(z, k2).item(), rel=1e-6)


# ---- eq:dice / eq:raw-loss ------------------------------------------------------------------------
def test_dice_hand_value_and_edge_cases():
    p = t([[[0.8, 0.2]], [[0.5, 0.5]]])
    m = t([[[1.0, 0.0]], [[0.0, 0.0]]])
    r0 = (2 * 0.8 + 1) / (1.0 + 1 + 1)
    r1 = (0 + 1) / (1.0 + 0 + 1)
    assert losses.dice_loss(p, m).item() == pytest.approx(1 - (r0 + r1) / 2, rel=1e-6)
    # all background predicted as background: ratio 1 -> loss 0
    assert losses.dice_loss(torch.zeros(2, 1, 3), torch.zeros(2, 1, 3)).item() == pytest.approx(0.0)
    # all foreground predicted perfectly: (2*3+1)/(3+3+1) = 1
    assert losses.dice_loss(torch.ones(1, 1, 3), torch.ones(1, 1, 3)).item() == pytest.approx(0.0)


def test_raw_loss_is_bbce_plus_point_two_dice():
    z = t([[[2.0, -1.0]], [[0.5, 0.0]]])
    m = t([[[1.0, 0.0]], [[0.0, 0.0]]])
    expected = losses.balanced_bce(z, m) + 0.2 * losses.dice_loss(torch.sigmoid(z), m)
    assert losses.raw_terms(z, m)["raw"].item() == pytest.approx(expected.item(), rel=1e-6)
    parts = losses.raw_terms(z, m, dice_weight=0.5)
    assert parts["bbce"].item() == pytest.approx(losses.balanced_bce(z, m).item(), rel=1e-6)
    assert parts["dice"].item() == pytest.approx(losses.dice_loss(torch.sigmoid(z), m).item(), rel=1e-6)
    assert parts["raw"].item() == pytest.approx((parts["bbce"] + 0.5 * parts["dice"]).item(), rel=1e-6)


# ---- eq:pseudo-boundary-band .. eq:sdf-loss ---------------------------------------------------------
def test_sdf_loss_hand_value():
    d_t = t([[[0.0, 0.9]], [[-0.5, 1.0]]])
    d_s = t([[[0.2, 0.5]], [[-0.5, 0.0]]])
    g = t([1.0, 0.5])
    # band: |0|<=.55 yes, .9 no, .5 yes, 1 no -> weights g*(.15 + .85 B): 1, .15, .5, .075
    w = [1.0, 0.15, 0.5, 0.075]
    err = [0.2, 0.4, 0.0, 1.0]
    expected = sum(a * b for a, b in zip(w, err)) / (sum(w) + 1e-6)
    assert losses.sdf_loss(d_s, d_t, g).item() == pytest.approx(expected, rel=1e-6)
    assert losses.sdf_weight(d_t, g).flatten().tolist() == pytest.approx(w)
    assert losses.sdf_loss(d_s, d_t, t([0.0, 0.0])).item() == 0.0


def test_sdf_band_boundary_is_inclusive():
    assert losses.boundary_band(t([0.55, -0.55, 0.5501])).tolist() == [1.0, 1.0, 0.0]


# ---- eq:predicted-area .. eq:area-loss --------------------------------------------------------------
def test_area_loss_hand_value_and_zero_gates():
    p = t([[[0.5, 0.5]], [[0.0, 0.2]]])   # a_hat = .5, .1
    a = t([0.25, 0.0])
    g = t([1.0, 0.5])
    l0 = abs(L((0.5 + 1e-5) / (0.25 + 1e-5)))
    l1 = abs(L((0.1 + 1e-5) / (0.0 + 1e-5)))
    expected = (1.0 * l0 + 0.5 * l1) / (1.5 + 1e-6)
    assert losses.area_loss(p, a, g).item() == pytest.approx(expected, rel=1e-5)
    assert losses.predicted_area(p).tolist() == pytest.approx([0.5, 0.1])
    assert losses.area_loss(p, a, t([0.0, 0.0])).item() == 0.0


# ---- eq:refine-loss ---------------------------------------------------------------------------------
def test_refine_loss_combination_and_single_gating():
    torch.manual_seed(0)
    z = torch.randn(2, 1, 4, 4)
    m = (torch.rand(2, 1, 4, 4) > 0.5).float()
    d_s, d_t = torch.tanh(torch.randn(2, 1, 4, 4)), torch.rand(2, 1, 4, 4) * 2 - 1
    zk = torch.randn(2, 1, 4, 4)
    k = (torch.rand(2, 1, 4, 4) > 0.8).float()
    a = t([0.3, 0.6])
    g = t([0.7, 0.2])
    out = losses.refine_loss({"mask": z, "sdf": d_s, "skeleton": zk},
                             {"mask": m, "sdf": d_t, "skeleton": k, "area": a}, g)
    raw = losses.raw_terms(z, m)["raw"]
    sdf = losses.sdf_loss(d_s, d_t, g)
    skel = losses.balanced_bce(zk, k, g)
    area = losses.area_loss(torch.sigmoid(z), a, g)
    assert out["loss"].item() == pytest.approx((raw + 0.002 * sdf + 0.001 * skel + 0.05 * area).item(), rel=1e-6)
    # the raw (region) term is ungated: scaling the gates changes only the geometric terms
    out0 = losses.refine_loss({"mask": z, "sdf": d_s, "skeleton": zk},
                              {"mask": m, "sdf": d_t, "skeleton": k, "area": a}, t([0.0, 0.0]))
    assert out0["loss"].item() == pytest.approx(raw.item(), rel=1e-6)


def _batch():
    torch.manual_seed(3)
    out = {"mask": torch.randn(2, 1, 4, 4), "sdf": torch.tanh(torch.randn(2, 1, 4, 4)),
           "skeleton": torch.randn(2, 1, 4, 4)}
    tgt = {"mask": (torch.rand(2, 1, 4, 4) > 0.5).float(), "sdf": torch.rand(2, 1, 4, 4) * 2 - 1,
           "skeleton": (torch.rand(2, 1, 4, 4) > 0.8).float(), "area": t([0.3, 0.6]),
           "anchor": torch.rand(2, 1, 4, 4)}
    return out, tgt, t([0.7, 0.2])


def test_refine_loss_with_method_weights_sums_exactly_the_named_terms():
    """The comparison methods' objectives: Stage I = L_raw only, GABI's ungated dist/boundary terms, the
    adaptive anchor, the geometry_only mode without L_raw, and non-paper constants."""
    out, tgt, g = _batch()
    stage1 = losses.refine_loss(out, tgt, g, {"region": 1.0})
    assert set(stage1) == {"loss", "raw", "bbce", "dice"}
    assert stage1["loss"].item() == pytest.approx(losses.raw_terms(out["mask"], tgt["mask"])["raw"].item(), rel=1e-6)
    gabi = losses.refine_loss(out, tgt, g, {"region": 1.0, "dist": 0.5, "boundary": 0.25})
    dist = losses.distance_regression_loss(out["sdf"], tgt["sdf"])
    bnd = losses.boundary_weighted_bce(out["mask"], tgt["mask"], tgt["sdf"])
    assert gabi["loss"].item() == pytest.approx((stage1["raw"] + 0.5 * dist + 0.25 * bnd).item(), rel=1e-6)
    assert gabi["dist"].item() == dist.item() and gabi["boundary"].item() == bnd.item()
    geo_only = losses.refine_loss(out, tgt, g, {"anchor": 0.1, "sdf": 0.002, "skel": 0.001, "area": 0.05})
    assert "raw" not in geo_only
    anchor = losses.anchor_loss(out["mask"], tgt["anchor"])
    full = losses.refine_loss(out, tgt, g)
    expected = 0.1 * anchor + 0.002 * full["sdf"] + 0.001 * full["skel"] + 0.05 * full["area"]
    assert geo_only["loss"].item() == pytest.approx(expected.item(), rel=1e-6)
    c = losses.LossConstants(dice_weight=0.5, sdf_band=0.2)
    other = losses.refine_loss(out, tgt, g, constants=c)
    assert other["raw"].item() == pytest.approx(losses.raw_terms(out["mask"], tgt["mask"], 0.5)["raw"].item(), rel=1e-6)
    assert other["sdf"].item() == pytest.approx(losses.sdf_loss(out["sdf"], tgt["sdf"], g, 0.2).item(), rel=1e-6)
    with pytest.raises(ValueError, match="unknown loss term"):
        losses.refine_loss(out, tgt, g, {"vibes": 1.0})


def test_gradients_flow_and_are_finite():
    z = torch.zeros(1, 1, 3, 3, requires_grad=True)
    m = torch.zeros(1, 1, 3, 3)
    m[0, 0, 1, 1] = 1
    losses.raw_terms(z, m)["raw"].backward()
    assert torch.isfinite(z.grad).all() and z.grad[0, 0, 1, 1] < 0 < z.grad[0, 0, 0, 0]


# ---- baselines' terms -------------------------------------------------------------------------------
def test_anchor_and_gabi_terms_hand_values():
    z = t([[[0.0, 2.0]]])
    q = t([[[0.25, 1.0]]])
    expected = -((0.25 * L(0.5) + 0.75 * L(0.5)) + L(sig(2.0))) / 2
    assert losses.anchor_loss(z, q).item() == pytest.approx(expected, rel=1e-6)
    assert losses.distance_regression_loss(t([[0.5, -0.5]]), t([[0.0, 0.0]])).item() == pytest.approx(0.5)
    d_t = t([[[0.1, 0.9]]])  # only the first pixel is in the band
    m = t([[[1.0, 0.0]]])
    assert losses.boundary_weighted_bce(z, m, d_t).item() == pytest.approx(-L(0.5) / (1 + 1e-6), rel=1e-6)
