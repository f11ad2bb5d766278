"""Consensus vote (eq:agreement-map, eq:majority-vote) and the consensus stage end to end."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from pipeline.artifacts.lineage import make_meta
from pipeline.artifacts.store import open_artifact, write_zarr
from pipeline.consensus import Consensus, vote, vote_batch
from pipeline.runtime.errors import InputError

PARAMS = Path(__file__).resolve().parents[2] / "params.yaml"
PROMPTS = ["spacecraft", "satellite", "space probe", "space vehicle",
           "spacecraft with rigid body and appendages", "artificial object in space with panels and antennas"]


def _votes(counts_fg: int, k: int = 6, h: int = 2, w: int = 3) -> np.ndarray:
    """k masks of which the first ``counts_fg`` are all-foreground, the rest all-background."""
    m = np.zeros((k, h, w), bool)
    m[:counts_fg] = True
    return m


# ------------------------------------------------------------------------------------------------
# vote
# ------------------------------------------------------------------------------------------------
def test_tie_at_exactly_half_is_foreground():
    c = vote(_votes(3), np.ones(6))
    assert isinstance(c, Consensus)
    assert np.all(c.agreement == 0.5) and c.agreement.dtype == np.float32
    assert c.voted.all()                       # 3 of 6: tie -> foreground
    assert not vote(_votes(2), np.ones(6)).voted.any()   # 2 of 6: background
    # four valid prompts: 2 of 4 is a tie -> foreground
    scores = np.array([1, 1, 1, 1, 0, 0.0])
    masks = np.zeros((6, 1, 1), bool)
    masks[[0, 1]] = True
    c4 = vote(masks, scores)
    assert c4.agreement[0, 0] == 0.5 and c4.voted[0, 0] and c4.n_valid == 4


def test_odd_valid_count_and_pixelwise_agreement():
    masks = np.zeros((6, 1, 4), bool)
    # pixel j gets j+1 foreground votes among the first five prompts; prompt 6 is invalid and votes everywhere
    for j in range(4):
        masks[: j + 1, 0, j] = True
    masks[5] = True
    scores = np.array([0.9, 0.8, 0.7, 0.6, 0.5, 0.0])
    c = vote(masks, scores)
    np.testing.assert_allclose(c.agreement[0], [0.2, 0.4, 0.6, 0.8], rtol=1e-6)
    np.testing.assert_array_equal(c.voted[0], [False, False, True, True])
    np.testing.assert_array_equal(c.valid, [True] * 5 + [False])


def test_scores_never_weight_pixels_and_negative_scores_are_invalid():
    rng = np.random.default_rng(0)
    masks = rng.random((6, 8, 8)) > 0.5
    a = vote(masks, np.array([0.9, 0.1, 0.5, 0.3, -0.2, 0.0]))
    b = vote(masks, np.array([0.01, 5.0, 1.0, 2.0, -9.0, 0.0]))  # same validity, other magnitudes
    np.testing.assert_array_equal(a.agreement, b.agreement)
    np.testing.assert_array_equal(a.voted, b.voted)
    expected = masks[:4].mean(axis=0)
    np.testing.assert_allclose(a.agreement, expected, rtol=1e-6)
    np.testing.assert_array_equal(a.voted, expected >= 0.5)


def test_no_valid_prompt_gives_zero_agreement_and_empty_mask():
    masks = np.ones((6, 4, 4), bool)
    c = vote(masks, np.zeros(6))
    assert c.n_valid == 0 and not c.valid.any()
    assert not c.agreement.any() and not c.voted.any()
    # even with a threshold of 0 the mask stays empty (the paper's rule, not the inequality)
    assert not vote(masks, -np.ones(6), threshold=0.0).voted.any()


def test_threshold_is_a_keyword_and_integer_masks_are_accepted():
    masks = _votes(4).astype(np.uint8)
    assert vote(masks, np.ones(6), threshold=0.5).voted.all()
    assert not vote(masks, np.ones(6), threshold=0.7).voted.any()   # 4/6 = 0.667 < 0.7


def test_batch_equals_single_image_calls():
    rng = np.random.default_rng(1)
    masks = rng.random((5, 6, 7, 9)) > 0.4
    scores = rng.normal(0.3, 0.5, (5, 6)).astype(np.float32)
    scores[2] = -1  # one image without a valid prompt
    b = vote_batch(masks, scores)
    assert b.agreement.shape == (5, 7, 9) and b.valid.shape == (5, 6)
    np.testing.assert_array_equal(b.n_valid, (scores > 0).sum(1))
    assert b.n_valid.dtype == np.int16
    for i in range(5):
        s = vote(masks[i], scores[i])
        np.testing.assert_array_equal(s.agreement, b.agreement[i])
        np.testing.assert_array_equal(s.voted, b.voted[i])
    assert not b.voted[2].any()


@pytest.mark.parametrize("masks, scores, match", [
    (np.full((6, 3, 3), 2, np.uint8), np.ones(6), "binary"),
    (np.full((6, 3, 3), 0.5), np.ones(6), "binary"),
    (np.zeros((6, 3, 3), bool), np.ones(5), "scores"),
    (np.zeros((3, 3), bool), np.ones(6), "K,H,W"),
    (np.zeros((6, 3, 3), bool), np.array([1, np.nan, 1, 1, 1, 1]), "NaN"),
])
def test_bad_input_raises_input_error(masks, scores, match):
    with pytest.raises(InputError, match=match):
        vote(masks, scores)


def test_bad_threshold():
    with pytest.raises(InputError, match="vote_threshold"):
        vote(_votes(3), np.ones(6), threshold=1.5)


# ------------------------------------------------------------------------------------------------
# stage
# ------------------------------------------------------------------------------------------------
def write_teacher(path, masks, scores, prompts=PROMPTS, image_ids=None):
    n = masks.shape[0]
    meta = make_meta("teacher", "teacher", "test", {"backend": "test"})
    write_zarr(path, {"masks": masks, "scores": scores}, meta,
               attrs={"prompts": list(prompts), "image_ids": image_ids or [f"img{i}" for i in range(n)],
                      "backend": "test"})
    return path


def _teacher_arrays(n=7, h=16, w=20, seed=0):
    rng = np.random.default_rng(seed)
    base = np.zeros((n, h, w), bool)
    base[:, 4:12, 5:15] = True
    noise = rng.random((n, 6, h, w)) < 0.15
    masks = base[:, None] ^ noise
    scores = rng.uniform(0.1, 0.9, (n, 6)).astype(np.float32)
    scores[1, [0, 2, 4]] = 0.0          # three valid prompts
    scores[3] = 0.0                     # no valid prompt at all
    return masks, scores


def _run(args, tmp_path):
    from stages.consensus import main

    runner = CliRunner()
    return runner.invoke(main, [*args, "--params", str(PARAMS)], catch_exceptions=False)


def test_consensus_stage_end_to_end(tmp_path):
    masks, scores = _teacher_arrays()
    teacher = write_teacher(tmp_path / "teacher.zarr", masks, scores)
    out = tmp_path / "consensus.zarr"
    res = _run(["--teacher", str(teacher), "--out", str(out), "--chunk-images", "3"], tmp_path)
    assert res.exit_code == 0, res.output
    art = open_artifact(out, "consensus")
    ref = vote_batch(masks, scores)
    np.testing.assert_array_equal(art.numpy("agreement"), ref.agreement)
    np.testing.assert_array_equal(art.numpy("voted"), ref.voted)
    np.testing.assert_array_equal(art.numpy("n_valid"), [6, 3, 6, 0, 6, 6, 6])
    assert art["n_valid"].dtype == np.int16 and art["agreement"].dtype == np.float32
    assert not art.numpy("voted")[3].any()
    assert art.attrs["image_ids"] == [f"img{i}" for i in range(7)]
    assert art.attrs["prompts"] == PROMPTS
    assert art.meta.inputs[0]["fingerprint"] == open_artifact(teacher).fingerprint
    assert art.meta.params == {"consensus.vote_threshold": 0.5}
    # determinism: a rerun gives the same fingerprint and arrays
    out2 = tmp_path / "consensus2.zarr"
    assert _run(["--teacher", str(teacher), "--out", str(out2)], tmp_path).exit_code == 0
    art2 = open_artifact(out2)
    assert art2.fingerprint == art.fingerprint
    np.testing.assert_array_equal(art2.numpy("agreement"), art.numpy("agreement"))


def test_consensus_stage_rejects_bad_teacher(tmp_path):
    masks, scores = _teacher_arrays(n=4)
    # non-binary masks: the teacher schema wants bool masks, so a uint8 array is refused on open
    t = write_teacher(tmp_path / "u8.zarr", masks.astype(np.uint8) * 2, scores)
    res = _run(["--teacher", str(t), "--out", str(tmp_path / "o.zarr")], tmp_path)
    assert res.exit_code == 2 and "u8.zarr" in res.output and "masks" in res.output
    # attrs["prompts"] disagree with the mask count K
    t = write_teacher(tmp_path / "attr.zarr", masks, scores, prompts=PROMPTS[:4])
    res = _run(["--teacher", str(t), "--out", str(tmp_path / "o.zarr")], tmp_path)
    assert res.exit_code == 2 and "attr.zarr" in res.output
    # NaN scores
    bad = scores.copy()
    bad[1, 2] = np.nan
    t = write_teacher(tmp_path / "nan.zarr", masks, bad)
    res = _run(["--teacher", str(t), "--out", str(tmp_path / "o.zarr")], tmp_path)
    assert res.exit_code == 2 and "nan.zarr" in res.output and "NaN" in res.output
    # scores shape mismatch
    t = write_teacher(tmp_path / "shape.zarr", masks, scores[:2])
    res = _run(["--teacher", str(t), "--out", str(tmp_path / "o.zarr")], tmp_path)
    assert res.exit_code == 2 and "shape.zarr" in res.output
    # image_ids do not match N
    t = write_teacher(tmp_path / "ids.zarr", masks, scores, image_ids=["a", "b"])
    res = _run(["--teacher", str(t), "--out", str(tmp_path / "o.zarr")], tmp_path)
    assert res.exit_code == 2 and "ids.zarr" in res.output
    # not an artifact at all
    res = _run(["--teacher", str(tmp_path / "missing.zarr"), "--out", str(tmp_path / "o.zarr")], tmp_path)
    assert res.exit_code == 2 and "missing.zarr" in res.output
    assert not (tmp_path / "o.zarr").exists()
