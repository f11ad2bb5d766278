"""Units of the teacher package: cache entries, sharding, the SIMULATOR, the imported layout."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from pipeline.runtime.errors import InputError
from pipeline.teachers.base import TeacherInput, finalize_answers
from pipeline.teachers.cache import CorruptEntry, TeacherCache, decode_entry, encode_entry, entry_key
from pipeline.teachers.runner import parse_shard, shard_rows
from pipeline.teachers.simulated import PERSONAS, SimulatedFoundationTeacher
from tests.builders.teacher import teacher_items

PROMPTS = list(PERSONAS)


def test_entry_round_trip_and_corruption():
    rng = np.random.default_rng(0)
    mask = rng.random((7, 13)) > 0.5  # odd size: packed bits need padding
    key = entry_key("sha", "fp", "spacecraft")
    data = encode_entry(mask, 0.75, key)
    back, score = decode_entry(data, key)
    np.testing.assert_array_equal(back, mask)
    assert score == pytest.approx(0.75)
    with pytest.raises(CorruptEntry, match="key"):
        decode_entry(data, entry_key("sha", "fp", "satellite"))
    for bad in (data[:-1], data[:10], b"x" + data[1:], data[:-1] + bytes([data[-1] ^ 1])):
        with pytest.raises(CorruptEntry):
            decode_entry(bad)


def test_cache_keys_and_stats(tmp_path):
    k = entry_key("sha", "fp", "spacecraft")
    assert k == entry_key("sha", "fp", "spacecraft", "identity")
    assert len({k, entry_key("sha2", "fp", "spacecraft"), entry_key("sha", "fp2", "spacecraft"),
                entry_key("sha", "fp", "satellite"), entry_key("sha", "fp", "spacecraft", "vflip")}) == 5
    cache = TeacherCache(tmp_path, "fp")
    assert cache.get(k) is None
    cache.put(k, np.ones((4, 4), bool), 0.5)
    assert cache.get(k)[1] == pytest.approx(0.5)
    cache.path(k).write_bytes(b"garbage")
    assert cache.get(k) is None and not cache.path(k).exists()
    assert (cache.stats.hits, cache.stats.misses, cache.stats.corrupt, cache.stats.written) == (1, 2, 1, 1)
    assert not list(tmp_path.rglob("*.tmp"))  # atomic writes leave no temp files


def test_shards_partition_rows():
    rows = list(range(3, 20))
    parts = [shard_rows(rows, (i, 4)) for i in range(4)]
    assert sorted(sum(parts, [])) == rows
    assert max(map(len, parts)) - min(map(len, parts)) <= 1
    assert parse_shard("2/5") == (2, 5) and parse_shard(None) is None
    for bad in ("5/5", "-1/3", "a/b", "3", "1/0"):
        with pytest.raises(InputError):
            parse_shard(bad)


def test_finalize_answers_invalidates_nonpositive_scores():
    masks = np.ones((2, 3, 4, 4), bool)
    scores = np.array([[0.5, 0.0, -1.0], [np.nan, 0.2, 0.9]])
    m, s = finalize_answers(masks, scores)
    assert s.dtype == np.float32
    np.testing.assert_array_equal(s, np.float32([[0.5, 0, 0], [0, 0.2, 0.9]]))
    assert not m[s == 0].any() and m[s > 0].all()


def test_simulator_is_deterministic_and_seeded():
    items = teacher_items(12)
    t = SimulatedFoundationTeacher(seed=0, resolution=(32, 32))
    m1, s1 = t.predict(items, PROMPTS)
    m2, s2 = SimulatedFoundationTeacher(seed=0, resolution=(32, 32)).predict(items[::-1], PROMPTS[::-1])
    np.testing.assert_array_equal(m1, m2[::-1, ::-1])  # order of images and prompts does not matter
    np.testing.assert_array_equal(s1, s2[::-1, ::-1])
    m3, s3 = t.predict(items, PROMPTS[:3])            # nor does the rest of the prompt list
    np.testing.assert_array_equal(m3, m1[:, :3])
    _, s4 = SimulatedFoundationTeacher(seed=1, resolution=(32, 32)).predict(items, PROMPTS)
    assert not np.array_equal(s1, s4)
    assert t.fingerprint()["simulator"] is True and t.backend == "simulated"


def test_simulator_vote_beats_best_single_prompt():
    from pipeline.consensus import vote_batch
    from pipeline.metrics import per_image_metrics

    items = teacher_items(60, seed=3)
    gt = np.stack([it.reference["mask"] for it in items])
    masks, scores = SimulatedFoundationTeacher(seed=0, resolution=(32, 32)).predict(items, PROMPTS)
    single = np.array([per_image_metrics(masks[:, k], gt)["iou"].mean() for k in range(len(PROMPTS))])
    voted = per_image_metrics(vote_batch(masks, scores).voted, gt)["iou"].mean()
    assert voted > single.max() + 0.03
    assert single.std(ddof=1) > 0.1  # prompts differ a lot (paper: SD 0.24 across prompts)
    assert (scores == 0).any() and (scores > 0).any()
    # invalid answers carry an empty mask; scores loosely track quality
    assert not masks[scores == 0].any()
    iou = np.stack([per_image_metrics(masks[:, k], gt)["iou"] for k in range(len(PROMPTS))], axis=1)
    valid = scores > 0
    assert np.corrcoef(scores[valid], iou[valid])[0, 1] > 0.3


def test_simulator_needs_reference():
    item = teacher_items(1)[0]
    item.reference = None
    with pytest.raises(InputError, match="reference"):
        SimulatedFoundationTeacher().predict([item], PROMPTS)


def test_imported_layout(tmp_path):
    import cv2

    from pipeline.teachers.imported import ImportedTeacher

    rows = []
    rng = np.random.default_rng(0)
    truth = {}
    for img in ("a", "b"):
        (tmp_path / "masks" / img).mkdir(parents=True)
        for k, prompt in enumerate(PROMPTS[:3]):
            m = rng.random((16, 16)) > 0.5
            score = 0.0 if (img, k) == ("b", 1) else 0.4 + 0.1 * k
            if score > 0:
                cv2.imwrite(str(tmp_path / "masks" / img / f"{k}.png"), m.astype(np.uint8) * 255)
            truth[(img, prompt)] = (m if score > 0 else np.zeros_like(m), score)
            rows.append((img, k, prompt, score, "identity"))
        vm = rng.random((16, 16)) > 0.5
        cv2.imwrite(str(tmp_path / "masks" / img / "vflip_0.png"), vm.astype(np.uint8))
        truth[(img, "vflip")] = (vm, 0.3)
        rows.append((img, 0, PROMPTS[0], 0.3, "vflip"))
    pd.DataFrame(rows, columns=["image_id", "prompt_index", "prompt", "score", "view"]).to_csv(
        tmp_path / "scores.csv", index=False)
    t = ImportedTeacher(tmp_path, resolution=(16, 16))
    items = [TeacherInput(i, "sha", np.zeros((16, 16, 3), np.uint8)) for i in ("a", "b")]
    masks, scores = t.predict(items, PROMPTS[2::-1])  # prompts matched by text, in any order
    for b, img in enumerate(("a", "b")):
        for j, prompt in enumerate(PROMPTS[2::-1]):
            np.testing.assert_array_equal(masks[b, j], truth[(img, prompt)][0])
            assert scores[b, j] == pytest.approx(truth[(img, prompt)][1])
    # the vflip view: the stored mask is in the original frame; the runner's flip-back restores it
    from pipeline.teachers.jobs import flip_answer

    fl = [TeacherInput(i, "sha", np.zeros((16, 16, 3), np.uint8), view="vflip") for i in ("a", "b")]
    vm, vs = t.predict(fl, PROMPTS[:1])
    np.testing.assert_array_equal(flip_answer(vm)[0, 0], truth[("a", "vflip")][0])
    with pytest.raises(InputError, match="no row"):
        t.predict([TeacherInput("zzz", "sha", np.zeros((16, 16, 3), np.uint8))], PROMPTS[:1])
    (tmp_path / "masks" / "a" / "2.png").unlink()
    with pytest.raises(InputError, match="2.png"):
        t.predict(items[:1], PROMPTS[2:3])
    assert len(t.fingerprint()["content"]) == 64


#: sha256 of the masks and scores below, computed with the SIMULATOR before ``predict_with_draws`` was factored out
#: (commit 7de09f3): the refactor must leave every answer byte-identical (SIMULATOR_VERSION unchanged)
SIMULATOR_ANSWERS_SHA256 = "597ad9341d74e80b4dc9f97bea5d0228df5c22f402db5088c911d637a53e016d"


def _varied_items():
    """Inputs over every hard case and both backgrounds, some in the vflip view."""
    import dataclasses

    cases, backgrounds = ("none", "glare", "flare", "underexposed", "blur", "noise"), ("stars", "earth limb")
    return [dataclasses.replace(it, view="vflip" if i % 5 == 4 else "identity",
                                extras={**it.extras, "hard_case": cases[i % 6], "background": backgrounds[i % 2]})
            for i, it in enumerate(teacher_items(48, seed=5))]


def test_simulator_draws_leave_the_answers_byte_identical():
    import hashlib

    from pipeline.teachers.simulated import MISS, MODES, SIMULATOR_VERSION

    items = _varied_items()
    t = SimulatedFoundationTeacher(seed=7, resolution=(32, 32))
    masks, scores = t.predict(items, PROMPTS)
    assert SIMULATOR_VERSION == 1
    assert hashlib.sha256(masks.tobytes() + scores.tobytes()).hexdigest() == SIMULATOR_ANSWERS_SHA256
    m2, s2, draws = t.predict_with_draws(items, PROMPTS)
    np.testing.assert_array_equal(m2, masks)
    np.testing.assert_array_equal(s2, scores)
    assert len(draws) == len(items) and all(len(d) == len(PROMPTS) for _, d in draws)
    modes = np.array([[d.mode for d in per] for _, per in draws])
    assert set(modes.ravel()) <= {MISS, *MODES} and {MISS, "clean"} <= set(modes.ravel())
    assert not masks[modes == MISS].any() and (scores[modes == MISS] == 0).all()
    gt = np.stack([it.reference["mask"] for it in items])
    for i, (scene, per) in enumerate(draws):
        assert scene == t.scene(items[i])
        for k, d in enumerate(per):
            if d.mode == "clean" and not (d.shared_thin or d.shared_fp or d.jitter) and scores[i, k] > 0:
                np.testing.assert_array_equal(masks[i, k], gt[i])  # a clean draw answers the reference itself
            assert not (scene.breakdown and (d.shared_thin or d.shared_fp))  # shared events skip a breakdown
            assert not d.shared_thin or scene.shared_thin
            assert not d.shared_fp or scene.shared_fp
