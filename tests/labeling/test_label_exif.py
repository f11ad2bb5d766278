"""Images as a viewer shows them: a JPEG's EXIF orientation is applied in the one decode path
(pipeline.datasets.loading._decode), so ``label`` votes and writes its masks at the displayed size and in the
displayed orientation."""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.datasets.loading import jpeg_orientation
from pipeline.datasets.loading import DecodeCache, load_rgb, read_rgb
from pipeline.teachers.base import finalize_answers
from pipeline.teachers.simulated import SimulatedFoundationTeacher
from tests.builders.teacher import FAST, cli


def exif_app1(orientation: int, order: str = "II") -> bytes:
    """An APP1 segment holding an EXIF block whose IFD0 has one entry: Orientation (SHORT) = ``orientation``."""
    e = "<" if order == "II" else ">"
    tiff = order.encode() + struct.pack(e + "HI", 42, 8) + struct.pack(e + "H", 1)
    tiff += struct.pack(e + "HHI", 0x0112, 3, 1) + struct.pack(e + "HH", orientation, 0) + struct.pack(e + "I", 0)
    body = b"Exif\x00\x00" + tiff
    return b"\xff\xe1" + struct.pack(">H", len(body) + 2) + body


def jpeg_with_orientation(bgr: np.ndarray, orientation: int, order: str = "II") -> bytes:
    """``bgr`` encoded as a JPEG (stored as given) that carries EXIF ``orientation`` right after SOI."""
    ok, enc = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert ok
    data = enc.tobytes()
    return data[:2] + exif_app1(orientation, order) + data[2:]


@pytest.mark.parametrize("orientation", range(1, 9))
def test_decode_applies_every_orientation_as_opencv_imread_does(tmp_path, orientation):
    """All eight orientations (both byte orders) match OpenCV's own EXIF handling (imdecode IMREAD_COLOR),
    which is what a viewer shows; the file's header still gives the stored size."""
    rng = np.random.default_rng(orientation)
    stored = np.kron(rng.integers(0, 255, (6, 10, 3)), np.ones((8, 8, 1))).astype(np.uint8)  # 48 x 80, blocky
    for order in ("II", "MM"):
        data = jpeg_with_orientation(stored, orientation, order)
        assert jpeg_orientation(data) == orientation
        p = tmp_path / f"o{orientation}{order}.jpg"
        p.write_bytes(data)
        shown = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]  # RGB as displayed
        got = read_rgb(p)
        assert got.shape == shown.shape and (orientation < 5) == (got.shape[:2] == (48, 80))
        assert np.array_equal(got, shown)


def test_orientation_is_one_for_other_files():
    ok, png = cv2.imencode(".png", np.zeros((4, 4), np.uint8))
    ok2, jpg = cv2.imencode(".jpg", np.zeros((4, 4), np.uint8))
    assert jpeg_orientation(png.tobytes()) == jpeg_orientation(jpg.tobytes()) == 1
    assert jpeg_orientation(jpeg_with_orientation(np.zeros((4, 4, 3), np.uint8), 9)) == 1  # out of range
    assert jpeg_orientation(jpeg_with_orientation(np.zeros((4, 4, 3), np.uint8), 6)[:30]) == 1  # cut short


def test_turned_files_get_their_own_decode_cache_entry_and_teacher_key(tmp_path):
    """An entry decoded before the orientation was applied (same file sha, plain kind) is not reused, and the
    key the teacher cache uses differs from the file's sha256 exactly when the file is shown turned."""
    stored = np.zeros((40, 64, 3), np.uint8)
    stored[5:15, 40:60] = 255
    for o in (1, 6):
        p = tmp_path / f"o{o}.jpg"
        p.write_bytes(jpeg_with_orientation(stored, o))
        cache = DecodeCache(tmp_path / f"cache{o}")
        first = load_rgb(p, 16, cache)
        again = load_rgb(p, 16, cache)
        assert cache.hits == 1 and np.array_equal(first.array, again.array)
        assert (first.content_sha256 == first.sha256) == (o == 1) and first.orientation == o
        assert first.native_hw == ((40, 64) if o == 1 else (64, 40))
        assert len(list(Path(cache.root).rglob(f"*-rgb{'-exif6' if o == 6 else ''}-16.npz"))) == 1


def bright_teacher_predict(self, batch, prompts):
    """A test teacher that answers every prompt with the image's bright pixels: its mask follows the pixels
    the teacher was given, so it lies over the object only where the decode showed the image as displayed."""
    masks = np.stack([np.stack([it.image.max(axis=2) > 100] * len(prompts)) for it in batch])
    return finalize_answers(masks, np.full((len(batch), len(prompts)), 0.9, np.float32))


def test_label_masks_overlay_the_object_as_displayed(tmp_path, monkeypatch):
    """A 96 x 64 (w x h) JPEG stored sideways with EXIF orientation 6 and an off-centre bright object: the mask
    label writes is 64 x 96 as displayed, and lies over the object of the displayed image (IoU > 0.8), not
    over where it is stored."""
    stored = np.full((64, 96, 3), 15, np.uint8)
    stored[6:26, 60:88] = 220                        # top right as stored
    folder, refs = tmp_path / "images", tmp_path / "refs"
    folder.mkdir()
    refs.mkdir()
    data = jpeg_with_orientation(stored, 6)
    (folder / "turned.jpg").write_bytes(data)
    displayed = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)       # 96 x 64 (h x w)
    obj = displayed.max(axis=2) > 100
    assert displayed.shape[:2] == (96, 64) and obj[60:88].any() and not obj[:40].any()   # turned: now lower part
    cv2.imwrite(str(refs / "turned.png"), obj.astype(np.uint8) * 255)  # the SIMULATOR's input, as displayed
    monkeypatch.setattr(SimulatedFoundationTeacher, "predict", bright_teacher_predict)
    out = tmp_path / "out"
    res = cli("label", folder, "--out", out, "--backend", "simulated", "--reference-masks", refs, "--format", "png",
              "-q", *FAST, "--set", "consensus.vote_threshold=0.5")
    assert res.exit_code == 0, res.output
    mask = cv2.imread(str(out / "masks" / "turned.png"), cv2.IMREAD_UNCHANGED) > 0
    assert mask.shape == obj.shape
    inter, union = (mask & obj).sum(), (mask | obj).sum()
    assert inter / union > 0.8, inter / union
    assert not mask[:40].any()  # nothing where the object lies as stored, turned
