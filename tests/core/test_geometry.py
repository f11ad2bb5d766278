"""Pseudo-geometry targets and the reliability gate (eq:sdf-target .. eq:reliability-gate), and the
geometry stage end to end."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner
from scipy import ndimage

from pipeline.artifacts.lineage import make_meta
from pipeline.artifacts.store import open_artifact, write_parquet, write_zarr
from pipeline.consensus import vote_batch
from pipeline.runtime.errors import InputError
from pipeline.geometry import (GateFactors, area_ratio, area_ratios, distance_maps, foreground_agreement, gate_factors,
                               median_area, pseudo_targets, sdf_target, skeleton_target, valid_ratio)

PARAMS = Path(__file__).resolve().parents[2] / "params.yaml"


def _random_blobs(seed: int, h: int = 40, w: int = 48) -> np.ndarray:
    """A few random ellipses and bars, some touching the frame."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:h, :w]
    m = np.zeros((h, w), bool)
    for _ in range(rng.integers(1, 4)):
        cy, cx = rng.uniform(-5, h + 5), rng.uniform(-5, w + 5)
        ry, rx = rng.uniform(2, 12), rng.uniform(2, 12)
        m |= ((yy - cy) / ry) ** 2 + ((xx - cx) / rx) ** 2 < 1
    r = rng.integers(0, h)
    m[r, rng.integers(0, w // 2):] = True  # a one-pixel-wide boom
    return m


def _scipy_sdf(mask: np.ndarray, q: float = 0.95) -> np.ndarray:
    """Independent reference of eq:sdf-target with scipy's exact EDT and np.quantile."""
    if not mask.any():
        return np.zeros(mask.shape)
    if mask.all():
        return np.ones(mask.shape)
    raw = ndimage.distance_transform_edt(mask) - ndimage.distance_transform_edt(~mask)
    s = np.quantile(np.abs(raw), q)
    s = s if s >= 1e-6 else 1.0
    return np.clip(raw / s, -1, 1)


# ------------------------------------------------------------------------------------------------
# SDF
# ------------------------------------------------------------------------------------------------
def test_sdf_empty_and_full():
    z = np.zeros((5, 6), bool)
    assert sdf_target(z).dtype == np.float32
    np.testing.assert_array_equal(sdf_target(z), 0.0)
    np.testing.assert_array_equal(sdf_target(~z), 1.0)


def test_sdf_single_pixel_by_hand():
    m = np.zeros((5, 5), bool)
    m[2, 2] = True
    raw = np.empty((5, 5))
    yy, xx = np.mgrid[:5, :5]
    raw[:] = -np.hypot(yy - 2, xx - 2)   # d_out: distance to the single foreground pixel
    raw[2, 2] = 1.0                      # d_in: distance to the nearest background pixel
    s = np.quantile(np.abs(raw), 0.95)
    d = sdf_target(m)
    np.testing.assert_allclose(d, np.clip(raw / s, -1, 1), atol=1e-6)
    assert d[2, 2] > 0 and (d[~m] < 0).all()


def test_distance_convention_and_border_is_not_background():
    m = np.zeros((5, 7), bool)
    m[:, :3] = True                       # touches the top, bottom and left frame edges
    d_in, d_out = distance_maps(m)
    np.testing.assert_allclose(d_in[0], [3, 2, 1, 0, 0, 0, 0])   # not 1 at the frame edge
    np.testing.assert_allclose(d_out[0], [0, 0, 0, 1, 2, 3, 4])


@pytest.mark.parametrize("seed", range(6))
def test_sdf_matches_scipy_reference_and_properties(seed):
    m = _random_blobs(seed)
    d = sdf_target(m)
    np.testing.assert_allclose(d, _scipy_sdf(m), atol=1e-5)
    # properties: sign agrees with M, |D| <= 1, float32
    assert d.dtype == np.float32
    assert (d[m] > 0).all() and (d[~m] < 0).all()
    assert np.abs(d).max() <= 1.0
    # the quantile normalisation saturates about 5 % of the pixels at +-1
    saturated = np.mean(np.abs(d) >= 1.0 - 1e-6)
    assert 0.05 <= saturated <= 0.5


def test_sdf_min_scale_branch():
    # |D~| >= 1 on every pixel of a non-degenerate mask (pixel-centre distances), so q >= 1 and the
    # s = 1 branch is reachable only through the parameter; with s = 1, D = clip(D~, -1, 1) = +-1.
    m = _random_blobs(3)
    d = sdf_target(m, min_scale=1e9)
    np.testing.assert_array_equal(d, np.where(m, 1.0, -1.0))


# ------------------------------------------------------------------------------------------------
# Skeleton
# ------------------------------------------------------------------------------------------------
def test_skeleton_empty_full_single_pixel_and_thin_line_fall_back():
    z = np.zeros((6, 6), bool)
    assert not skeleton_target(z).any() and skeleton_target(z).dtype == bool
    np.testing.assert_array_equal(skeleton_target(~z), ~z)
    one = z.copy()
    one[3, 2] = True
    np.testing.assert_array_equal(skeleton_target(one), one)        # d_in = 1 only -> fallback to M
    line = np.zeros((9, 12), bool)
    line[4, 1:11] = True
    np.testing.assert_array_equal(skeleton_target(line), line)      # one-pixel-wide line -> M
    bar2 = np.zeros((9, 12), bool)
    bar2[3:5, 1:11] = True
    np.testing.assert_array_equal(skeleton_target(bar2), bar2)      # 2 px thick: d_in = 1 everywhere


def test_skeleton_of_bars_by_hand():
    bar3 = np.zeros((9, 14), bool)
    bar3[3:6, 1:13] = True                 # 3 px thick: d_in = 2 on the centre row except its ends
    expected = np.zeros_like(bar3)
    expected[4, 2:12] = True
    np.testing.assert_array_equal(skeleton_target(bar3), expected)
    bar4 = np.zeros((10, 14), bool)
    bar4[3:7, 1:13] = True                 # 4 px thick: a two-pixel plateau of d_in = 2 (non-strict maxima)
    expected = np.zeros_like(bar4)
    expected[4:6, 2:12] = True
    np.testing.assert_array_equal(skeleton_target(bar4), expected)


def test_skeleton_of_disk_is_its_centre():
    yy, xx = np.mgrid[:21, :21]
    disk = (yy - 10) ** 2 + (xx - 10) ** 2 <= 36
    sk = skeleton_target(disk)
    assert np.argwhere(sk).tolist() == [[10, 10]]


@pytest.mark.parametrize("seed", range(6))
def test_skeleton_properties_and_scipy_reference(seed):
    m = _random_blobs(seed)
    sk = skeleton_target(m)
    assert sk.dtype == bool and sk.any()
    assert not (sk & ~m).any()                                  # inside M
    d_in = ndimage.distance_transform_edt(m)
    local_max = d_in >= ndimage.maximum_filter(d_in, size=3, mode="constant", cval=-np.inf)
    ref = (d_in > 1) & local_max
    np.testing.assert_array_equal(sk, ref if ref.any() else m)


def test_batched_targets_equal_single_functions():
    masks = np.stack([_random_blobs(s) for s in range(4)] + [np.zeros((40, 48), bool), np.ones((40, 48), bool)])
    sdf, sk, area = pseudo_targets(masks)
    assert sdf.dtype == np.float32 and sk.dtype == bool and area.shape == (6,)
    for i, m in enumerate(masks):
        np.testing.assert_array_equal(sdf[i], sdf_target(m))
        np.testing.assert_array_equal(sk[i], skeleton_target(m))
        assert area[i] == area_ratio(m)
    # an empty batch (a shard or worker chunk with no images) is an empty result, not an error
    sdf, sk, area = pseudo_targets(np.zeros((0, 40, 48), bool))
    assert sdf.shape == sk.shape == (0, 40, 48) and area.shape == (0,)
    assert area_ratios(np.zeros((0, 4, 5), bool)).shape == (0,)


def test_area_ratio():
    m = np.zeros((4, 5), bool)
    assert area_ratio(m) == 0.0
    m[1, 1:4] = True
    assert area_ratio(m) == pytest.approx(3 / 20)
    assert area_ratio(np.ones((3, 3), np.uint8)) == 1.0


def test_bad_masks():
    with pytest.raises(InputError, match="binary"):
        sdf_target(np.full((3, 3), 0.5))
    with pytest.raises(InputError, match="2-D"):
        skeleton_target(np.zeros((2, 3, 3), bool))


# ------------------------------------------------------------------------------------------------
# Agreement, validity, gate
# ------------------------------------------------------------------------------------------------
def test_foreground_agreement_by_hand_and_batched():
    a = np.array([[1.0, 0.5, 0.0], [2 / 3, 1 / 3, 0.0]], np.float32)
    m = a >= 0.5
    assert foreground_agreement(a, m) == pytest.approx((1 + 0.5 + 2 / 3) / 3)
    assert foreground_agreement(a, np.zeros_like(m)) == 0.0       # empty M -> 0
    c = foreground_agreement(np.stack([a, a]), np.stack([m, np.zeros_like(m)]))
    np.testing.assert_allclose(c, [(1 + 0.5 + 2 / 3) / 3, 0.0], rtol=1e-6)


def test_valid_ratio():
    assert valid_ratio(6) == 1.0 and valid_ratio(0) == 0.0 and valid_ratio(3) == 0.5
    np.testing.assert_allclose(valid_ratio(np.array([1, 2]), n_prompts=4), [0.25, 0.5])


def test_worked_landsat8_example():
    gf = gate_factors(0.936, 1.0, 0.00230, 0.00197)
    assert isinstance(gf, GateFactors)
    assert round(gf.conf, 3) == 0.902
    assert round(gf.valid, 3) == 1.000
    assert round(gf.area, 3) == 0.842
    assert gf.g == pytest.approx(gf.conf * gf.valid * gf.area)
    # The paper prints g = 0.760.  From its rounded inputs the formula gives 0.7591 (and the rounded
    # factors give 0.902 * 0.842 = 0.7595), so the paper used unrounded c, a, a0.  Check that 0.760 is
    # what the formula gives somewhere inside the rounding box of the printed inputs.
    lo = gate_factors(0.9355, 1.0, 0.002305, 0.001965).g
    hi = gate_factors(0.9365, 1.0, 0.002295, 0.001975).g
    assert lo < 0.7595 <= 0.7605 < hi
    assert abs(gf.g - 0.760) < 1.5e-3


def test_gate_branches():
    assert gate_factors(0.9, 0.0, 0.01, 0.01).g == 0.0          # no valid prompt: g_valid = 0
    assert gate_factors(0.9, 0.2, 0.01, 0.01).valid == 0.0
    assert gate_factors(0.35, 1.0, 0.01, 0.01).g == 0.0         # c at the confidence offset
    empty = gate_factors(0.0, 1.0, 0.0, 0.01)                   # empty pseudo-mask
    assert empty.conf == 0.0 and empty.area == 0.05 and empty.g == 0.0
    same = gate_factors(1.0, 1.0, 0.02, 0.02)
    assert same.area == 1.0 and same.g == 1.0
    # symmetric in log area: twice and half the median are gated alike
    assert gate_factors(1, 1, 0.04, 0.02).area == pytest.approx(gate_factors(1, 1, 0.01, 0.02).area, rel=1e-3)
    # the floor holds for a wildly wrong area
    assert gate_factors(1, 1, 0.9, 1e-4).area == 0.05
    # constants are keywords
    assert gate_factors(0.5, 1, 0.02, 0.02, conf_offset=0.5).g == 0.0


def test_gate_vectorised_equals_scalar():
    rng = np.random.default_rng(0)
    c, v, a = rng.random(20), rng.integers(0, 7, 20) / 6, rng.random(20) * 0.05
    gf = gate_factors(c, v, a, 0.01)
    assert gf.g.shape == (20,)
    for i in range(20):
        s = gate_factors(c[i], v[i], a[i], 0.01)
        assert (gf.conf[i], gf.valid[i], gf.area[i], gf.g[i]) == pytest.approx(tuple(s))
    assert ((gf.g >= 0) & (gf.g <= 1)).all()
    with pytest.raises(InputError, match="NaN"):
        gate_factors(np.nan, 1, 0.1, 0.1)


def test_median_area_uses_non_empty_training_masks_only():
    a = np.array([0.0, 0.1, 0.3, 0.2, 0.9, 0.0, 0.4])
    is_train = np.array([True, True, True, True, False, True, True])
    assert median_area(a, is_train) == pytest.approx(0.25)       # median of 0.1, 0.3, 0.2, 0.4
    with pytest.raises(InputError, match="no spacecraft in any training image"):
        median_area(np.array([0.0, 0.2]), np.array([True, False]))


# ------------------------------------------------------------------------------------------------
# Stage
# ------------------------------------------------------------------------------------------------
def _write_inputs(tmp_path, n=6, h=24, w=28, prompts=6, splits=None, seed=0):
    rng = np.random.default_rng(seed)
    masks = np.zeros((n, prompts, h, w), bool)
    for i in range(n):
        cy, cx = rng.integers(6, h - 6), rng.integers(6, w - 6)
        ry, rx = rng.integers(2, 6), rng.integers(2, 6)
        masks[i, :, cy - ry:cy + ry, cx - rx:cx + rx] = True
    masks ^= rng.random(masks.shape) < 0.05
    scores = rng.uniform(0.2, 0.9, (n, prompts)).astype(np.float32)
    scores[2, :] = 0.0                                  # no valid prompt
    scores[3, :2] = 0.0                                 # four valid prompts
    c = vote_batch(masks, scores)
    ids = [f"im{i}" for i in range(n)]
    write_zarr(tmp_path / "consensus.zarr",
               {"agreement": c.agreement, "voted": c.voted, "n_valid": c.n_valid},
               make_meta("consensus", "consensus", "test", {"vote_threshold": 0.5}),
               attrs={"image_ids": ids, "prompts": [f"p{k}" for k in range(prompts)]})
    splits = splits or ["train", "train", "train", "train", "val", "test"][:n]
    manifest = pd.DataFrame({
        "image_id": ids, "dataset": "synthetic", "domain": "synthetic", "split": splits, "group": splits,
        "spacecraft": "sc", "image_path": "x.png", "mask_path": None, "part_path": None,
        "width": w, "height": h, "sha256": "0"})
    write_parquet(tmp_path / "manifest.parquet", manifest, make_meta("manifest", "prepare", "test", {}))
    return c, manifest


def _run_geometry(tmp_path, *extra, consensus="consensus.zarr", manifest="manifest.parquet"):
    from stages.geometry import main

    return CliRunner().invoke(main, [
        "--consensus", str(tmp_path / consensus), "--manifest", str(tmp_path / manifest),
        "--out", str(tmp_path / "geometry.zarr"), "--gates", str(tmp_path / "gates.parquet"),
        "--params", str(PARAMS), *extra], catch_exceptions=False)


def test_geometry_stage_end_to_end(tmp_path):
    c, manifest = _write_inputs(tmp_path)
    res = _run_geometry(tmp_path, "--chunk-images", "4")
    assert res.exit_code == 0, res.output
    geo = open_artifact(tmp_path / "geometry.zarr", "geometry")
    sdf, sk, area = pseudo_targets(c.voted)
    np.testing.assert_array_equal(geo.numpy("sdf"), sdf)
    np.testing.assert_array_equal(geo.numpy("skeleton"), sk)
    assert geo.attrs["image_ids"] == list(manifest.image_id)
    gates = open_artifact(tmp_path / "gates.parquet", "gates").df
    assert list(gates.columns) == ["image_id", "split", "c", "v", "a", "a0", "g_conf", "g_valid",
                                   "g_area", "g", "n_valid"]
    assert list(gates.image_id) == list(manifest.image_id)
    a0 = median_area(area, manifest.split.to_numpy() == "train")
    assert (gates.a0 == a0).all()
    np.testing.assert_allclose(gates.a, area)
    np.testing.assert_allclose(gates.c, foreground_agreement(c.agreement, c.voted))
    np.testing.assert_allclose(gates.v, c.n_valid / 6)
    gf = gate_factors(gates.c, gates.v, gates.a, a0)
    np.testing.assert_allclose(gates.g, gf.g)
    # the image without a valid prompt: empty targets and g = 0
    row = gates.iloc[2]
    assert row.n_valid == 0 and row.g == 0.0 and row.g_valid == 0.0 and row.a == 0.0
    assert not geo.numpy("skeleton")[2].any() and not geo.numpy("sdf")[2].any()
    assert gates.n_valid.tolist() == c.n_valid.tolist()
    # determinism
    fp = geo.fingerprint
    assert _run_geometry(tmp_path).exit_code == 0
    assert open_artifact(tmp_path / "geometry.zarr").fingerprint == fp


def test_geometry_stage_bad_inputs(tmp_path):
    _write_inputs(tmp_path)
    # n_prompts in params differs from teacher.prompts: the schema refuses it before any artifact is read
    res = _run_geometry(tmp_path, "--set", "geometry.n_prompts=5")
    assert res.exit_code == 2 and "geometry.n_prompts=5" in res.output and "teacher.prompts" in res.output
    # consistent params, but the consensus artifact was voted over another number of prompts
    res = _run_geometry(tmp_path, "--set", "geometry.n_prompts=5", "--set", "teacher.prompts=[a, b, c, d, e]")
    assert res.exit_code == 2 and "consensus.zarr" in res.output and "n_prompts" in res.output
    # manifest of another length / order
    sub = tmp_path / "sub"
    sub.mkdir()
    _write_inputs(sub, n=5)
    res = _run_geometry(tmp_path, manifest="sub/manifest.parquet")
    assert res.exit_code == 2 and "manifest.parquet" in res.output
    # no non-empty training pseudo-mask: a0 undefined
    none = tmp_path / "none"
    none.mkdir()
    _write_inputs(none, splits=["val", "val", "test", "test", "val", "test"])
    res = _run_geometry(none)
    assert res.exit_code == 2 and "training" in res.output
    # non-binary voted mask: the consensus schema refuses a float 'voted'
    c, _ = _write_inputs(tmp_path)
    write_zarr(tmp_path / "bad.zarr", {"agreement": c.agreement, "voted": c.voted.astype(np.float32),
                                       "n_valid": c.n_valid},
               make_meta("consensus", "consensus", "test", {}), attrs={"image_ids": [f"im{i}" for i in range(6)],
                                                                     "prompts": list("abcdef")})
    res = _run_geometry(tmp_path, consensus="bad.zarr")
    assert res.exit_code == 2 and "bad.zarr" in res.output
    # shapes of agreement and voted differ
    write_zarr(tmp_path / "shape.zarr", {"agreement": c.agreement[:, :-1], "voted": c.voted, "n_valid": c.n_valid},
               make_meta("consensus", "consensus", "test", {}), attrs={"image_ids": [f"im{i}" for i in range(6)],
                                                                     "prompts": list("abcdef")})
    res = _run_geometry(tmp_path, consensus="shape.zarr")
    assert res.exit_code == 2 and "shape.zarr" in res.output
    assert not (tmp_path / "gates.parquet").exists()
