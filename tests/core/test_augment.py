"""Target-consistent augmentation (pipeline/augment.py) and the ``strong`` recipe that turns it on.

Flips and 90-degree rotations move the stored SDF and skeleton exactly (bit for bit the targets of the
moved mask); a rescale recomputes them from the augmented pseudo-mask; the gate passes through; the
same seeds give the same batch; the paper and stable recipes never augment.
"""

from __future__ import annotations

import dataclasses
import hashlib

import numpy as np
import pytest

from pipeline.augment import (DEFAULT_SPEC, GeometryConstants, augment_batch, augment_sample, dihedral, hard_region,
                              lens_flare, photometric, soft_region)
from pipeline.geometry import area_ratio, sdf_target, skeleton_target
from pipeline.training.settings import Settings
from pipeline.training.checkpointing import NoCheckpointer


def _mask(h=40, w=40, seed=0) -> np.ndarray:
    """An irregular spacecraft-like mask: a bus, a panel touching the border, a thin boom, an ellipse."""
    rng = np.random.default_rng(seed)
    m = np.zeros((h, w), bool)
    m[10:22, 12:25] = True
    m[14:17, 25:w] = True  # panel to the right border
    m[22:34, 18] = True  # 1-px boom
    yy, xx = np.mgrid[0:h, 0:w]
    m |= ((yy - 30) / 5.0) ** 2 + ((xx - 8) / 3.0) ** 2 <= 1
    m[rng.integers(0, h, 6), rng.integers(0, w, 6)] ^= True
    return m


def _image(mask: np.ndarray, seed=1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 40, (*mask.shape, 3)).astype(np.uint8)
    img[mask] = rng.integers(150, 255, (int(mask.sum()), 3)).astype(np.uint8)
    return img


def _spec(**over):
    return dataclasses.replace(DEFAULT_SPEC, **over)


@pytest.mark.parametrize("shape", [(40, 40), (36, 44)])
def test_flips_and_rotations_move_the_stored_targets_exactly(shape):
    m = _mask(*shape)
    sdf, skel = sdf_target(m), skeleton_target(m)
    ks = range(4) if shape[0] == shape[1] else (0, 2)
    for k in ks:
        for hf in (False, True):
            for vf in (False, True):
                moved = dihedral(m, k, hf, vf)
                np.testing.assert_array_equal(dihedral(sdf, k, hf, vf), sdf_target(moved))
                np.testing.assert_array_equal(dihedral(skel, k, hf, vf), skeleton_target(moved))
    assert not np.array_equal(dihedral(sdf, 0, True, False), sdf)  # the test mask is not symmetric


def _targets(m):
    return {"mask": m, "sdf": sdf_target(m), "skeleton": skeleton_target(m), "area": area_ratio(m), "gate": 0.37,
            "anchor": np.where(m, 0.9, 0.1).astype(np.float32)}


def test_geometric_only_targets_equal_those_of_the_augmented_mask_and_the_gate_passes_through():
    m = _mask()
    spec = _spec(scale_probability=0.0, photometric_probability=0.0)
    for seed in range(6):
        img, t = augment_sample(_image(m), _targets(m), np.random.default_rng(seed), spec)
        np.testing.assert_array_equal(t["sdf"], sdf_target(t["mask"]))
        np.testing.assert_array_equal(t["skeleton"], skeleton_target(t["mask"]))
        assert t["area"] == area_ratio(m) == area_ratio(t["mask"]) and t["gate"] == 0.37
        np.testing.assert_array_equal(t["anchor"] > 0.5, t["mask"])  # the anchor moves with the mask
        assert img.dtype == np.uint8 and (img[t["mask"]].min() >= 150) and (img[~t["mask"]].max() < 40)


def test_scale_and_crop_recompute_sdf_skeleton_and_area_from_the_augmented_mask():
    m = _mask()
    geo = GeometryConstants(quantile=0.9, min_scale=1e-6, min_distance=1.0)  # not the defaults: passed on
    changed = 0
    for seed in range(8):
        spec = _spec(scale_probability=1.0, scale_range=(0.6, 1.6), photometric_probability=0.0)
        img, t = augment_sample(_image(m), _targets(m), np.random.default_rng(seed), spec, geo)
        assert t["mask"].shape == m.shape and t["mask"].dtype == bool
        np.testing.assert_array_equal(t["sdf"], sdf_target(t["mask"], quantile=0.9))
        np.testing.assert_array_equal(t["skeleton"], skeleton_target(t["mask"]))
        assert t["area"] == area_ratio(t["mask"]) and t["gate"] == 0.37
        changed += t["area"] != area_ratio(m)
        # the image moved with the mask: bright on it, dark off it
        assert img[t["mask"]].mean() > img[~t["mask"]].mean() + 60
    assert changed >= 6  # the rescale really changes the frame


def test_a_rescale_without_sdf_or_skeleton_targets_skips_the_distance_transforms(monkeypatch):
    """Stage I trains on the mask and the area only: a rescale then computes no SDF or skeleton (per-step host
    work), and its image, mask and area are those of the same draws with every target."""
    import pipeline.augment as augment

    m = _mask()
    spec = _spec(scale_probability=1.0, scale_range=(0.6, 1.6), photometric_probability=1.0)
    full = [augment_sample(_image(m), _targets(m), np.random.default_rng(seed), spec) for seed in range(4)]

    def no_transforms(*a, **k):
        raise AssertionError("distance transforms for targets nobody trains on")

    monkeypatch.setattr(augment, "recompute_geometry", no_transforms)
    for seed, (img_full, t_full) in enumerate(full):
        targets = {k: v for k, v in _targets(m).items() if k not in ("sdf", "skeleton")}
        img, t = augment_sample(_image(m), targets, np.random.default_rng(seed), spec)
        assert set(t) == set(targets) and t["area"] == t_full["area"] == area_ratio(t["mask"])
        np.testing.assert_array_equal(img, img_full)
        np.testing.assert_array_equal(t["mask"], t_full["mask"])


def test_a_region_target_is_soft_by_its_type_and_its_region_is_the_vote_of_it():
    agreement = np.array([[0.0, 0.49], [0.5, 1.0]], np.float32)  # A (eq:agreement-map)
    assert soft_region(agreement) and not soft_region(agreement >= 0.5) and not soft_region(np.ones(2, np.uint8))
    assert hard_region(agreement).tolist() == [[False, False], [True, True]]  # M = [A >= 1/2], a tie is foreground
    assert hard_region(np.array([0, 1, 2], np.uint8)).tolist() == [False, True, True]


def test_photometric_changes_the_image_only():
    m = _mask()
    img = _image(m)
    for seed in range(5):
        out = photometric(img, _spec(glare_probability=1.0, blur_probability=0.0), np.random.default_rng(seed))
        assert out.dtype == np.uint8 and out.shape == img.shape and not np.array_equal(out, img)
        assert (out == 255).any()  # the glare spot saturates
    blurred = photometric(img, _spec(glare_probability=0.0, blur_probability=1.0, noise_std=0.0, brightness=0.0,
                                     contrast=0.0, gamma=0.0), np.random.default_rng(0))
    assert np.abs(np.diff(blurred.astype(int), axis=1)).mean() < np.abs(np.diff(img.astype(int), axis=1)).mean()
    spec = _spec(hflip=0.0, vflip=0.0, rot90=False, scale_probability=0.0, photometric_probability=1.0)
    aug, t = augment_sample(img, _targets(m), np.random.default_rng(3), spec)
    assert not np.array_equal(aug, img)
    for k, v in _targets(m).items():
        np.testing.assert_array_equal(t[k], v)


def test_the_same_seeds_give_the_same_batch_and_the_inputs_are_untouched():
    masks = np.stack([_mask(seed=s) for s in range(4)])
    images = np.stack([_image(mm, s) for s, mm in enumerate(masks)])
    targets = {"mask": masks, "sdf": np.stack([sdf_target(x) for x in masks]),
               "skeleton": np.stack([skeleton_target(x) for x in masks]),
               "area": np.array([area_ratio(x) for x in masks], np.float32), "gate": np.float32([1, 0.5, 0, 0.2])}
    before = {k: v.copy() for k, v in targets.items()}, images.copy()
    seeds = [[42, 1, i] for i in range(4)]
    a = augment_batch(images, targets, seeds)
    b = augment_batch(images, targets, seeds)
    c = augment_batch(images, targets, [[42, 2, i] for i in range(4)])
    np.testing.assert_array_equal(a[0], b[0])
    for k in targets:
        np.testing.assert_array_equal(a[1][k], b[1][k])
        assert a[1][k].dtype == targets[k].dtype
        np.testing.assert_array_equal(targets[k], before[0][k])
    np.testing.assert_array_equal(images, before[1])
    np.testing.assert_array_equal(a[1]["gate"], targets["gate"])
    assert not np.array_equal(a[0], c[0])
    # one image's augmentation depends on its own seed only, not on the rest of the batch
    one = augment_batch(images[2:3], {k: v[2:3] for k, v in targets.items()}, seeds[2:3])
    np.testing.assert_array_equal(one[0][0], a[0][2])


# --------------------------------------------------------------------------------------------------
# the recipe and the training loop
# --------------------------------------------------------------------------------------------------
def test_only_the_strong_recipe_augments_and_the_others_keep_their_values():
    from pipeline.params import RECIPES, validate

    for recipe in ("paper", "stable"):
        t = validate({"train": {"recipe": recipe}})["train"]
        assert (t["augment"], t["schedule"], t["batch_size"], t["epochs_stage1"], t["epochs_stage2"]) == \
            (False, "cosine", 4, 20, 10), recipe
    strong = validate({"train": {"recipe": "strong"}})
    assert strong["train"]["augment"] is True and strong["train"]["schedule"] == "wsd"
    assert strong["train"]["average_last"] > 0 and strong["train"]["epochs_stage1"] > 20
    assert strong["calibrate"]["tau_rule"] == RECIPES["strong"]["calibrate"]["tau_rule"]
    assert validate({"train": {"recipe": "strong", "augment": False}})["train"]["augment"] is False


def test_wsd_schedule_is_flat_then_decays_linearly_to_zero():
    from pipeline.training.schedule import decay_steps, lr_lambda

    f = lr_lambda("wsd", 100, 10, decay_steps(100, 0.2))
    assert f(0) == pytest.approx(0.1) and f(9) == 1.0 and f(50) == 1.0 and f(80) == 1.0
    assert f(90) == pytest.approx(0.5) and f(99) == pytest.approx(0.05) and f(100) == 0.0
    # the stable phase does not depend on the total: a longer run is the shorter one up to its decay
    g = lr_lambda("wsd", 200, 10, 20)
    assert [f(s) for s in range(81)] == [g(s) for s in range(81)]


def test_augmented_training_is_seeded_and_differs_from_the_plain_batches(tiny):
    import torch

    from pipeline.training import loop as training
    from pipeline.methods import get_method
    from tests.builders.training import assert_same_state, clone_state, load_arrays, tiny_cfg

    m = get_method("geodistill")
    cfg = tiny_cfg(epochs_stage2=1, augment=True)
    data, val = load_arrays(tiny, "geodistill", cfg)
    init = training.build_model(get_method("plain"), cfg, 0).mask_path_state_dict()
    runs = [training.train(m, c, data, val, 7, init_state=init, checkpointer=NoCheckpointer(),
                           show_progress=False) for c in (cfg, cfg, {**cfg, "augment": False})]
    assert_same_state(clone_state(runs[0].model), clone_state(runs[1].model))
    a, off = clone_state(runs[0].model), clone_state(runs[2].model)
    assert any(not torch.equal(a[k], off[k]) for k in a)
    # the batch the loop builds: geometry targets of the augmented masks (moved or recomputed); the tiny
    # artifacts' SDF is an approximation, so the data here carries the geometry stage's exact targets
    masks = np.asarray(data.mask)
    data = dataclasses.replace(data, mask=masks, images=np.asarray(data.images),
                               sdf=np.stack([sdf_target(x) for x in masks]),
                               skeleton=np.stack([skeleton_target(x) for x in masks]))
    s = Settings.from_params(m, cfg, 0.5)
    run = training.setup_run(m, cfg, s, training.resolve_plan(m, cfg, None), data, 7, init, torch.device("cpu"))
    b = training.augmented_batch(run, np.arange(len(data)), 1)
    for i in range(len(data)):
        mask = b["mask"][i, 0].numpy() > 0.5
        np.testing.assert_array_equal(b["sdf"][i, 0].numpy(), sdf_target(mask))
        np.testing.assert_array_equal(b["skeleton"][i, 0].numpy() > 0.5, skeleton_target(mask))
    np.testing.assert_array_equal(b["gate"].numpy(), data.gate)
    assert not torch.equal(b["mask"][:, 0].bool(), torch.from_numpy(masks))  # augmented


def test_the_flare_and_exposure_parts_draw_nothing_when_off():
    # the generator's state after each of 20 images under the schema's defaults, recorded at a05ad27, before the
    # two parts existed: off, they leave every other draw where it was (so today's runs are today's runs)
    m, img = _mask(), _image(_mask())
    states = []
    for seed in range(20):
        rng = np.random.default_rng(seed)
        augment_sample(img, {"mask": m}, rng, DEFAULT_SPEC)
        states.append(rng.bit_generator.state["state"]["state"])
    assert DEFAULT_SPEC.flare_probability == 0 and DEFAULT_SPEC.exposure_range == (1.0, 1.0)
    assert hashlib.sha256(repr(states).encode()).hexdigest()[:16] == "b2c26b148f54c042"


def test_exposure_scales_the_image_by_a_gain_from_its_range():
    img = _image(_mask())
    quiet = dict(brightness=0.0, contrast=0.0, gamma=0.0, glare_probability=0.0, blur_probability=0.0, noise_std=0.0)
    out = photometric(img, _spec(exposure_range=(0.25, 0.25), **quiet), np.random.default_rng(0))
    np.testing.assert_allclose(out, img * 0.25, atol=1.0)  # the gain, within uint8 rounding
    gains = [photometric(img, _spec(exposure_range=(0.5, 2.0), **quiet), np.random.default_rng(s)).astype(float).sum()
             / img.astype(float).sum() for s in range(40)]
    assert min(gains) >= 0.49 and max(gains) <= 2.0 and min(gains) < 0.8 and max(gains) > 1.2


def test_a_lens_flare_adds_light_from_a_saturating_source_and_only_when_drawn():
    for seed in range(10):
        light = lens_flare(48, 64, np.random.default_rng(seed))
        assert light.shape == (48, 64, 3) and light.dtype == np.float32 and light.min() >= 0
        np.testing.assert_array_equal(light, lens_flare(48, 64, np.random.default_rng(seed)))
    # a source drawn inside the frame saturates its core (its position: the generator's first two draws)
    inside = 0
    for seed in range(10):
        rng = np.random.default_rng(seed)
        sy, sx = rng.uniform(-0.1, 1.1) * 200, rng.uniform(-0.1, 1.1) * 200
        if 0 <= sy < 200 and 0 <= sx < 200:
            inside += 1
            assert lens_flare(200, 200, np.random.default_rng(seed))[int(sy), int(sx)].min() >= 1.0
    assert inside >= 5
    dark = np.zeros((40, 40, 3), np.uint8)
    spec = _spec(flare_probability=1.0, glare_probability=0.0, blur_probability=0.0, noise_std=0.0)
    assert all(photometric(dark, spec, np.random.default_rng(s)).astype(float).mean() > 1 for s in range(5))
    off = _spec(flare_probability=0.0, glare_probability=0.0, blur_probability=0.0, noise_std=0.0, brightness=0.0)
    assert photometric(dark, off, np.random.default_rng(0)).max() == 0
