"""Letterbox (params ``data.letterbox``): a non-square frame is padded to a square with black, resized,
and its prediction comes back at the frame's own size with the pad cropped -- the pad never reaches the
output; the paper's squash stays the default."""

from __future__ import annotations

import cv2
import numpy as np
import pandas as pd

from pipeline.datasets import loading
from pipeline.datasets.loading import iter_arrays
from pipeline.datasets.manifest import DatasetSpec
from pipeline.datasets.params import FrameSettings
from pipeline.deploy.segmenter import Segmenter
from pipeline.params import PAPER

R = 32


def logits_of(rule):
    """A stand-in model: logits [N,1,R,R] = +10 where ``rule(x)`` holds, else -10 (x: [N,3,R,R] in [0,1])."""
    def run(x):
        x = x.numpy()
        return np.where(rule(x), 10.0, -10.0).astype(np.float32)[:, :1]
    return run


def wide_frame(h: int = 30, w: int = 90) -> tuple[np.ndarray, np.ndarray]:
    """A grey (never black) non-square frame with a bright box touching its right edge, and the box."""
    img = np.full((h, w, 3), 60, np.uint8)
    box = np.zeros((h, w), bool)
    box[8:22, 60:90] = True
    img[box] = 220
    return img, box


def test_the_box_and_the_pad_geometry():
    assert loading.letterbox_box(30, 90) == (90, 30, 0)
    assert loading.letterbox_box(91, 30) == (91, 0, 30)
    img, _ = wide_frame()
    sq = loading.pad_to_square(img)
    assert sq.shape == (90, 90, 3) and (sq[:30] == 0).all() and (sq[60:] == 0).all()
    np.testing.assert_array_equal(sq[30:60], img)
    assert PAPER.data.letterbox is False                       # the paper's squash is the default
    np.testing.assert_array_equal(loading.resize_image(img, R), cv2.resize(img, (R, R), interpolation=cv2.INTER_AREA))


def test_a_letterboxed_prediction_comes_back_at_the_frame_size_without_the_pad():
    img, box = wide_frame()
    # the model calls exact black (the pad) spacecraft: if any pad reached the output, it would show
    seg = Segmenter("torch", R, {}, logits_of(lambda x: (x == 0).all(axis=1, keepdims=True)), {}, tau=0.5,
                    letterbox=True)
    work, hw = seg.working_probabilities(img)
    assert hw == img.shape[:2] and (work >= 0.5).sum() > R * R // 3   # the pad is "foreground" at R x R
    mask = seg.predict(img)
    assert mask.shape == img.shape[:2] and not mask.any()
    probs = seg.probabilities(img)
    assert probs.shape == img.shape[:2] and probs.max() < 1e-3


def test_a_letterboxed_object_maps_back_to_its_place():
    img, box = wide_frame()
    bright = logits_of(lambda x: x[:, :1] > 0.5)
    boxed = Segmenter("torch", R, {}, bright, {}, tau=0.5, letterbox=True).predict(img)
    squashed = Segmenter("torch", R, {}, bright, {}, tau=0.5).predict(img)
    for mask in (boxed, squashed):
        assert mask.shape == box.shape
        iou = (mask & box).sum() / (mask | box).sum()
        assert iou > 0.85, iou
    ys, xs = np.nonzero(boxed)
    assert xs.max() == 89 and abs(ys.mean() - 14.5) < 1 and abs(xs.mean() - 74.5) < 1.5


def test_segment_writes_letterboxed_masks_at_the_input_size(tmp_path):
    from pipeline.deploy.image_files import MASK_SUFFIX, output_path, segment_files

    img, box = wide_frame()
    f = tmp_path / "wide.png"
    cv2.imwrite(str(f), img[..., ::-1])
    seg = Segmenter("torch", R, {}, logits_of(lambda x: x[:, :1] > 0.5), {}, tau=0.5, letterbox=True)
    stem = tmp_path / "out" / "wide.png"
    for workers in (0, 1):
        segment_files(seg, [f], [stem], tau=0.5, resolution=R, workers=workers)
        mask = cv2.imread(str(output_path(stem, MASK_SUFFIX)), cv2.IMREAD_UNCHANGED) > 0
        np.testing.assert_array_equal(mask, seg.predict(img))
        assert (mask & box).sum() / (mask | box).sum() > 0.85


def test_prepare_letterboxes_images_and_masks_together(tmp_path):
    img, box = wide_frame()
    fi, fm = tmp_path / "wide.png", tmp_path / "wide_mask.png"
    cv2.imwrite(str(fi), img[..., ::-1])
    cv2.imwrite(str(fm), box.astype(np.uint8) * 255)
    rows = pd.DataFrame({"image_path": [str(fi)], "mask_path": [str(fm)], "part_path": [None]})
    _, image, mask, _ = next(iter_arrays(rows, DatasetSpec(rows), FrameSettings.from_params(PAPER.data.model_dump() | {"letterbox": True}), R, None))
    assert image.shape == (R, R, 3) and mask.shape == (R, R)
    side_pad = R * 30 // 90                                 # 30 pad rows of 90 -> about R/3 at R
    assert (image[:side_pad - 1] == 0).all() and not mask[:side_pad].any() and not mask[-side_pad:].any()
    bright = image[..., 0] > 150                             # mask and image stay aligned (to a pixel)
    for axis in (0, 1):
        assert abs(np.nonzero(mask)[axis].mean() - np.nonzero(bright)[axis].mean()) < 1
    cache = loading.DecodeCache(tmp_path / "cache")
    squashed = loading.load_rgb(fi, R, cache).array
    boxed = loading.load_rgb(fi, R, cache, letterbox=True).array
    assert cache.hits == 0 and not np.array_equal(squashed, boxed)    # separate cache entries
