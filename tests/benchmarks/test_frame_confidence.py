"""The per-frame confidence (:func:`pipeline.deploy.segmenter.frame_confidence`): its definition, the
Segmenter's ``score`` / ``predict(..., return_score=True)``, and that it ranks bad frames -- on a tiny
student trained here on synthetic boxes, frames degraded by noise, low contrast and blur score lower and
have lower IoU (positive Spearman between score and per-frame IoU)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from pipeline.deploy.confidence import confidence_rank_check, frame_confidence
from pipeline.deploy.segmenter import Segmenter
from pipeline.metrics import image_iou
from pipeline.model import TinyUNet

R = 32


def test_the_score_is_the_mean_normalised_margin_over_the_mask_and_its_band():
    p = np.zeros((16, 16), np.float32)
    assert frame_confidence(p, 0.5) == 1.0                       # nothing there, and sure of it
    assert frame_confidence(np.full((16, 16), 0.5, np.float32), 0.5) == 0.0
    p[4:8, 4:8] = 1.0
    assert frame_confidence(p, 0.5) == 1.0
    p[4:8, 4:8] = 0.75                                           # margin 0.5 inside; the band is still sure
    inside, band = 16, 8 * 8 - 16                                # band 2: the box grown to 8 x 8
    assert frame_confidence(p, 0.5) == pytest.approx((0.5 * inside + 1.0 * band) / (inside + band))
    assert frame_confidence(p, 0.5, band=0) == pytest.approx(0.5)
    p[0, 15] = 0.45                                              # far from the mask: not scored
    assert frame_confidence(p, 0.5) == pytest.approx((0.5 * inside + 1.0 * band) / (inside + band))
    assert frame_confidence(np.full((4, 4), 0.2, np.float32), 0.4) == pytest.approx(0.5)   # (0.4 - 0.2) / 0.4


def boxes(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Bright boxes of random size and place on dark, slightly noisy backgrounds (uint8 [n,R,R,3], bool masks)."""
    rng = np.random.default_rng(seed)
    images = np.empty((n, R, R, 3), np.uint8)
    masks = np.zeros((n, R, R), bool)
    for i in range(n):
        h, w = rng.integers(8, 16, size=2)
        y, x = rng.integers(2, R - 2 - h), rng.integers(2, R - 2 - w)
        masks[i, y:y + h, x:x + w] = True
        img = rng.normal(30, 6, (R, R, 3))
        img[masks[i]] = rng.normal(200, 6, (int(masks[i].sum()), 3))
        images[i] = np.clip(img, 0, 255).astype(np.uint8)
    return images, masks


def degrade(img: np.ndarray, kind: str, rng) -> np.ndarray:
    f = img.astype(np.float64)
    if kind == "noise":
        f = f + rng.normal(0, 70, f.shape)
    elif kind == "contrast":
        f = 80 + (f - 30) * 0.12
    elif kind == "blur":
        f = cv2.GaussianBlur(f, (0, 0), 3.0)
    return np.clip(f, 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def student():
    """A tiny TinyUNet trained for a few seconds on clean boxes (BCE), as a Segmenter at tau 0.5."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)           # a few seconds on one thread; more threads only contend here
    torch.manual_seed(0)
    model = TinyUNet(channels=(4, 8, 16))
    images, masks = boxes(32, seed=1)
    x = torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255
    y = torch.from_numpy(masks[:, None].astype(np.float32))
    opt = torch.optim.Adam(model.parameters(), lr=2e-2)
    model.train()
    for _ in range(80):
        opt.zero_grad()
        loss = torch.nn.functional.binary_cross_entropy_with_logits(model(x), y)
        loss.backward()
        opt.step()
    model.eval()

    def logits(t):
        with torch.inference_mode():
            return model(t).float().numpy()
    yield Segmenter("torch", R, {}, logits, {}, tau=0.5)
    torch.set_num_threads(threads)


def test_the_score_ranks_degraded_frames_below_clean_ones(student):
    images, masks = boxes(24, seed=7)
    rng = np.random.default_rng(3)
    kinds = ["clean"] * 12 + ["noise", "contrast", "blur"] * 4
    frames = [img if k == "clean" else degrade(img, k, rng) for img, k in zip(images, kinds)]
    results = student.predict(frames, return_score=True)
    scores = np.array([s for _, s in results])
    ious = np.array([image_iou(m, gt) for (m, _), gt in zip(results, masks)])
    assert np.mean(ious[:12]) > 0.8, ious                  # the student learned the task on clean frames
    assert np.mean(ious[12:]) < np.mean(ious[:12]) - 0.1   # the degraded frames are bad frames
    rank = confidence_rank_check(scores, ious)
    assert rank.n == 24 and rank.rho > 0.4, (rank, scores.round(3), ious.round(3))
    assert scores[:12].mean() > scores[12:].mean()
    # score() and predict(..., return_score=True) agree, and the mask is predict()'s
    mask, s = student.predict(frames[0], return_score=True)
    assert s == student.score(frames[0]) and 0.0 <= s <= 1.0
    np.testing.assert_array_equal(mask, student.predict(frames[0]))


def test_the_frame_confidence_benchmark_scores_a_runs_frames(tmp_path, capsys):
    """Smoke test of python -m benchmarks.frame_confidence on tiny artifacts and bundle: one
    row per group and one pooled, each frame's score the Segmenter's own, rho that of the stats module."""
    from benchmarks import frame_confidence as bench
    from pipeline.stats import spearman
    from tests.builders.deploy import make_artifacts, make_checkpoint, run_export

    art = make_artifacts(tmp_path / "artifacts")
    ckpt = make_checkpoint(tmp_path / "ckpt")
    assert run_export(ckpt, tmp_path / "deploy", "--tau", "0.5", "--no-onnx").exit_code == 0
    table = bench.main(["--artifacts", str(art), "--deploy", str(tmp_path / "deploy"), "--split", "val"])
    out = capsys.readouterr().out
    assert [r["group"] for r in table] == ["val", "all"] and table[0]["n"] == 4 and "IoU lowest 25%" in out
    scores, ious = bench.frame_scores(art, tmp_path / "deploy", split="val")["val"]
    seg = Segmenter.from_bundle(tmp_path / "deploy", engine="torch")
    from pipeline.artifacts.store import open_artifact

    images = open_artifact(art / "images.zarr", "images")
    assert scores[0] == pytest.approx(seg.score(np.asarray(images["image"][1])))   # val rows: 1, 3, 5, 7
    assert table[0]["rho"] == pytest.approx(spearman(scores, ious).rho, nan_ok=True)
