"""Per-image metrics and threshold calibration on hand-made masks with known answers."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial.distance import cdist

from pipeline.runtime.errors import InputError
from pipeline.thresholds import calibrate_threshold
from pipeline.metrics import (area_fraction, boundary_f1, image_iou, image_ious, iou_curve,
                              mask_boundary, per_image_metrics, precision_recall, small_region_iou)


def _square(top, left, size=20, shape=(64, 64)):
    m = np.zeros(shape, bool)
    m[top:top + size, left:left + size] = True
    return m


def _brute_bf1(pred, gt, tol):
    """Reference: boundaries with scipy (outside the frame counts as foreground), all-pairs distances."""
    def bnd(m):
        return m & ~ndimage.binary_erosion(m, np.ones((3, 3)), border_value=1)
    bp, bg = np.argwhere(bnd(pred)), np.argwhere(bnd(gt))
    d = cdist(bp, bg)
    p = np.mean(d.min(axis=1) <= tol)
    r = np.mean(d.min(axis=0) <= tol)
    return 0.0 if p + r == 0 else 2 * p * r / (p + r)


# ------------------------------------------------------------------------------------------------
# IoU, precision, recall, area
# ------------------------------------------------------------------------------------------------
def test_iou_precision_recall_by_hand():
    gt = _square(10, 10, 10)            # 100 px
    pred = _square(10, 15, 10)          # shifted by 5: 50 px overlap
    assert image_iou(pred, gt) == pytest.approx(50 / 150)
    assert precision_recall(pred, gt) == pytest.approx((0.5, 0.5))
    big = _square(5, 5, 20)             # contains gt: precision 100/400, recall 1
    assert precision_recall(big, gt) == pytest.approx((0.25, 1.0))
    assert image_iou(big, gt) == pytest.approx(0.25)
    assert area_fraction(big) == pytest.approx(400 / 64 ** 2)


def test_empty_mask_conventions():
    z = np.zeros((8, 8), bool)
    m = z.copy()
    m[2:4, 2:4] = True
    assert image_iou(z, z) == 1.0 and image_iou(z, m) == 0.0 and image_iou(m, z) == 0.0
    assert precision_recall(z, z) == (1.0, 1.0)
    assert precision_recall(z, m) == (0.0, 0.0)
    assert precision_recall(m, z) == (0.0, 0.0)
    assert boundary_f1(z, z) == 1.0 and boundary_f1(z, m) == 0.0 and boundary_f1(m, z) == 0.0
    assert area_fraction(z) == 0.0


# ------------------------------------------------------------------------------------------------
# Boundary F1
# ------------------------------------------------------------------------------------------------
def test_boundary_is_one_pixel_inner_contour_and_frame_is_not_boundary():
    sq = _square(2, 2, 4, shape=(8, 8))
    b = mask_boundary(sq)
    assert b.sum() == 12 and not b[3:5, 3:5].any()   # 4x4 square: 16 - inner 2x2
    half = np.zeros((6, 8), bool)
    half[:, :4] = True                                # touches three frame edges
    expected = np.zeros_like(half)
    expected[:, 3] = True
    np.testing.assert_array_equal(mask_boundary(half), expected)


def test_bf1_shift_by_one_is_perfect_at_tolerance_two():
    gt = _square(10, 10)
    assert boundary_f1(gt, gt) == 1.0
    assert boundary_f1(_square(10, 11), gt) == 1.0
    assert boundary_f1(_square(11, 11), gt) == 1.0      # diagonal: sqrt(2) <= 2
    assert boundary_f1(_square(10, 11), gt, tolerance=0) < 1.0


def test_bf1_shift_by_four_by_hand():
    # 20x20 squares, the prediction shifted right by 4 px.  Each boundary has 76 pixels.  Pred top and
    # bottom rows: 18 of 20 within 2 px (the last two columns are 3 and 4 px from the gt corner);
    # pred left column (18 interior pixels): only the 2 pixels next to each corner reach the gt
    # top/bottom rows within 2 px; pred right column: 4 px from everything.  40 / 76 on both sides.
    gt, pred = _square(10, 10), _square(10, 14)
    assert boundary_f1(pred, gt, tolerance=2) == pytest.approx(40 / 76)
    assert boundary_f1(pred, gt, tolerance=2) == pytest.approx(_brute_bf1(pred, gt, 2))
    assert boundary_f1(pred, gt, tolerance=4) == 1.0


def test_bf1_thin_lines():
    gt = np.zeros((16, 32), bool)
    gt[8, 4:28] = True                  # a one-pixel boom: its boundary is the line itself
    near = np.roll(gt, 1, axis=0)
    far = np.roll(gt, 3, axis=0)
    assert image_iou(near, gt) == 0.0                  # IoU sees no overlap ...
    assert boundary_f1(near, gt) == 1.0                # ... BF1 sees a 1 px displacement
    assert boundary_f1(far, gt) == 0.0                 # 3 px > tolerance
    assert boundary_f1(far, gt, tolerance=3) == 1.0    # inclusive tolerance


def test_bf1_full_frame_masks():
    full = np.ones((8, 8), bool)
    part = _square(2, 2, 4, shape=(8, 8))
    assert boundary_f1(full, full) == 1.0
    assert boundary_f1(full, part) == 0.0


@pytest.mark.parametrize("seed", range(5))
def test_bf1_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    gt = ndimage.gaussian_filter(rng.random((40, 40)), 3) > 0.5   # smooth random blobs
    assert gt.any() and not gt.all()
    pred = ndimage.binary_dilation(gt, iterations=int(rng.integers(0, 4))) ^ (rng.random((40, 40)) < 0.02)
    for tol in (1, 2, 3):
        assert boundary_f1(pred, gt, tol) == pytest.approx(_brute_bf1(pred, gt, tol))


# ------------------------------------------------------------------------------------------------
# Small-region IoU
# ------------------------------------------------------------------------------------------------
def test_small_region_iou():
    gt = _square(10, 10, 30)            # 900 px = 22 % of 64x64: large
    assert np.isnan(small_region_iou(gt, gt))          # no small component
    gt_small = gt.copy()
    gt_small[50:53, 50:53] = True       # 9 px < 1 % of 4096: small
    assert small_region_iou(gt_small, gt_small) == 1.0
    assert small_region_iou(gt, gt_small) == 0.0       # missed the small part
    # a false positive ring within the margin: region = small 3x3 dilated by r=3; pred = 5x5 around it
    pred = gt.copy()
    pred[49:54, 49:54] = True
    assert small_region_iou(pred, gt_small, margin=3) == pytest.approx(9 / 25)
    # pixels of the large component never enter the region: predicting it perfectly changes nothing
    assert small_region_iou(gt_small & ~gt, gt_small) == 1.0
    # a larger max_fraction makes the large square "small" too
    assert small_region_iou(gt, gt_small, max_fraction=0.5) == pytest.approx(900 / 909)


# ------------------------------------------------------------------------------------------------
# Batched metrics
# ------------------------------------------------------------------------------------------------
def test_per_image_metrics_equals_single_functions():
    rng = np.random.default_rng(3)
    gts = np.stack([ndimage.gaussian_filter(rng.random((32, 32)), 2.5) > 0.5 for _ in range(5)])
    gts[1] = False                        # empty ground truth
    gts[2, 28:30, 28:30] = True
    preds = np.stack([ndimage.binary_dilation(g, iterations=1) for g in gts])
    preds[3] = False                      # empty prediction
    out = per_image_metrics(preds, gts, tolerance=2)
    assert set(out) == {"iou", "bf1", "precision", "recall", "area_ratio", "small_iou"}
    for i in range(5):
        assert out["iou"][i] == pytest.approx(image_iou(preds[i], gts[i]))
        assert out["bf1"][i] == pytest.approx(boundary_f1(preds[i], gts[i]))
        assert (out["precision"][i], out["recall"][i]) == pytest.approx(precision_recall(preds[i], gts[i]))
        assert out["area_ratio"][i] == pytest.approx(area_fraction(preds[i]))
        np.testing.assert_equal(out["small_iou"][i], small_region_iou(preds[i], gts[i]))


def test_bad_metric_inputs():
    with pytest.raises(InputError, match="shapes differ"):
        image_iou(np.zeros((4, 4), bool), np.zeros((4, 5), bool))
    with pytest.raises(InputError, match="binary"):
        boundary_f1(np.full((4, 4), 0.3), np.zeros((4, 4), bool))
    with pytest.raises(InputError, match="3-D"):
        per_image_metrics(np.zeros((4, 4), bool), np.zeros((4, 4), bool))


# ------------------------------------------------------------------------------------------------
# Calibration
# ------------------------------------------------------------------------------------------------
def _calibration_case(seed=0, n=6):
    rng = np.random.default_rng(seed)
    gts = np.zeros((n, 24, 24), bool)
    gts[:, 6:18, 6:18] = True
    # foreground probabilities around 0.7, background around 0.3, with noise: the best tau is interior
    probs = np.where(gts, 0.7, 0.3) + rng.normal(0, 0.15, gts.shape)
    return np.clip(probs, 0, 1).astype(np.float32), gts


def test_iou_curve_matches_brute_force():
    probs, gts = _calibration_case()
    grid = np.round(np.arange(0.05, 0.951, 0.01), 2)
    curve = iou_curve(probs, gts, grid)
    for j in (0, 17, 45, 90):
        brute = [image_iou(p >= grid[j], g) for p, g in zip(probs, gts)]
        np.testing.assert_allclose(curve[:, j], brute, rtol=1e-12)


def test_calibration_picks_the_best_grid_point():
    probs, gts = _calibration_case()
    grid = np.round(np.arange(0.05, 0.951, 0.01), 2)
    tau, curve = calibrate_threshold(probs, gts, grid)
    brute = np.array([np.mean([image_iou(p >= t, g) for p, g in zip(probs, gts)]) for t in grid])
    np.testing.assert_allclose(curve, brute, rtol=1e-12)
    assert tau == grid[np.argmax(brute)]
    assert 0.35 < tau < 0.65 and curve.max() > curve[0] and curve.max() > curve[-1]


def test_calibration_threshold_is_inclusive_and_ties_go_to_closest_to_half():
    gts = np.zeros((1, 4, 4), bool)
    gts[0, :2] = True
    probs = np.where(gts, 0.8, 0.1).astype(np.float64)
    # every tau in (0.1, 0.8] separates perfectly: a plateau of IoU 1 -> the tau closest to 0.5
    tau, curve = calibrate_threshold(probs, gts, [0.1, 0.2, 0.45, 0.6, 0.8, 0.9])
    np.testing.assert_allclose(curve, [0.5, 1, 1, 1, 1, 0])
    assert tau == 0.45
    # equal distance to 0.5 -> the smaller tau
    assert calibrate_threshold(probs, gts, [0.4, 0.6])[0] == 0.4
    # P >= tau (eq:inference-mask): tau = 0.8 keeps the 0.8 pixels
    assert iou_curve(probs, gts, [0.8])[0, 0] == 1.0


def test_calibration_bad_inputs():
    probs, gts = _calibration_case(n=2)
    with pytest.raises(InputError, match="increasing"):
        calibrate_threshold(probs, gts, [0.5, 0.4])
    bad = probs.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        calibrate_threshold(bad, gts, [0.5])
    with pytest.raises(InputError, match="N >= 1"):
        calibrate_threshold(probs[:0], gts[:0], [0.5])


def test_image_ious_is_image_iou_per_pair():
    rng = np.random.default_rng(3)
    preds = rng.random((5, 9, 7)) > 0.6
    gts = rng.random((5, 9, 7)) > 0.5
    preds[1] = gts[1] = False                     # both empty -> 1
    preds[2] = False                              # one empty -> 0
    expect = [image_iou(p, g) for p, g in zip(preds, gts)]
    np.testing.assert_array_equal(image_ious(preds, gts), expect)
    assert image_ious(np.zeros((0, 4, 4), bool), np.zeros((0, 4, 4), bool)).shape == (0,)


# ------------------------------------------------------------------------------------------------
# Batched fast path == the per-image distance-transform implementation it replaced
# ------------------------------------------------------------------------------------------------
def _mask_zoo(n=24, size=48, seed=0):
    """Smooth blobs, speckle, thin lines, empty and full-frame masks, frame-touching shapes."""
    rng = np.random.default_rng(seed)
    out = np.stack([ndimage.gaussian_filter(rng.random((size, size)), rng.uniform(1, 4)) > rng.uniform(0.45, 0.55)
                    for _ in range(n)])
    out[0] = False
    out[1] = True
    out[2] = rng.random((size, size)) < 0.03        # hundreds of 1-px components
    out[3, :, 10] = True                            # a one-pixel line through the frame
    out[4, :size // 2] = True                       # touches three frame edges
    return out


@pytest.mark.parametrize("tolerance,margin", [(2, 3), (0, 3), (1.5, 0), (3, 1)])
def test_batched_metrics_equal_the_per_image_baseline(tolerance, margin):
    from benchmarks.bench_evaluate import baseline_per_image_metrics

    gts = _mask_zoo(seed=1)
    preds = np.concatenate([_mask_zoo(seed=2)[:12], np.roll(gts[12:], 1, axis=2)])
    preds[5] = gts[5]                               # identical pair
    preds[1] = True                                 # both full frame
    new = per_image_metrics(preds, gts, tolerance, margin=margin)
    old = baseline_per_image_metrics(preds, gts, tolerance, 0.01, margin)
    for k in old:
        np.testing.assert_array_equal(new[k], old[k], err_msg=k)
    assert np.isfinite(new["small_iou"]).sum() >= 3 and np.isnan(new["small_iou"]).sum() >= 1


def test_many_small_components_take_the_lookup_table_path():
    from benchmarks.bench_evaluate import baseline_small_region_iou
    from pipeline.metrics import _SMALL_LUT_ABOVE

    rng = np.random.default_rng(4)
    gts = rng.random((3, 64, 64)) < 0.04            # > _SMALL_LUT_ABOVE isolated pixels in the batch
    assert ndimage.label(gts[0], np.ones((3, 3)))[1] * 3 > _SMALL_LUT_ABOVE
    preds = rng.random((3, 64, 64)) < 0.05
    out = per_image_metrics(preds, gts)["small_iou"]
    np.testing.assert_array_equal(out, [baseline_small_region_iou(p, g, 0.01, 3) for p, g in zip(preds, gts)])


def test_prepared_reference_and_torch_morphology_give_the_same_scores():
    from pipeline.metrics import score_masks, scoring_reference

    gts = _mask_zoo(seed=5)
    ref = scoring_reference(gts, 2)
    for seed in (6, 7):                             # one reference, several prediction sets
        preds = _mask_zoo(seed=seed)
        fresh = per_image_metrics(preds, gts, 2)
        for out in (score_masks(preds, ref), score_masks(preds, ref, device="cpu")):   # torch on the CPU
            for k in fresh:
                np.testing.assert_array_equal(out[k], fresh[k], err_msg=k)
    with pytest.raises(InputError, match="shapes differ"):
        score_masks(gts[:3], ref)


def test_tolerance_disk_is_the_euclidean_ball():
    from pipeline.metrics import tolerance_disk

    assert tolerance_disk(0).tolist() == [[1]]
    assert tolerance_disk(1).sum() == 5 and tolerance_disk(1.5).sum() == 9 and tolerance_disk(2).sum() == 13
    assert tolerance_disk(2)[0].tolist() == [0, 0, 1, 0, 0]   # (2, 1) is sqrt(5) > 2 away
