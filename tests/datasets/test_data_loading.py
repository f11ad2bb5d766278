"""The one image/mask loader: colour conversions, resizing, decode cache, bad files."""


import cv2
import numpy as np
import pytest

from pipeline.datasets import loading as L
from pipeline.runtime.errors import InputError


def _write(path, arr):
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), arr)
    return path


def test_read_rgb_converts_bgr_grey_rgba_and_16bit(tmp_path):
    bgr = np.zeros((8, 10, 3), np.uint8)
    bgr[..., 0] = 200  # blue in OpenCV order
    rgb = L.read_rgb(_write(tmp_path / "c.png", bgr))
    assert rgb.shape == (8, 10, 3) and rgb[0, 0].tolist() == [0, 0, 200]

    grey = np.arange(80, dtype=np.uint8).reshape(8, 10)
    g = L.read_rgb(_write(tmp_path / "g.png", grey))
    assert g.shape == (8, 10, 3) and (g[..., 0] == grey).all() and (g[..., 2] == grey).all()

    bgra = np.dstack([bgr, np.full((8, 10), 7, np.uint8)])
    a = L.read_rgb(_write(tmp_path / "a.png", bgra))
    assert a.shape == (8, 10, 3) and a[0, 0].tolist() == [0, 0, 200]

    w16 = np.full((4, 4), 65535, np.uint16)
    w16[0, 0] = 257 * 100
    s = L.read_rgb(_write(tmp_path / "d.png", w16))
    assert s.dtype == np.uint8 and s[1, 1, 0] == 255 and s[0, 0, 0] == 100

    for ext in (".jpg", ".tif", ".bmp"):
        assert L.read_rgb(_write(tmp_path / f"x{ext}", bgr)).shape == (8, 10, 3)


@pytest.mark.parametrize("case", ["missing", "zero", "corrupt", "unsupported"])
def test_bad_files_raise_input_error_naming_the_file(tmp_path, case):
    p = {"missing": tmp_path / "nope.png", "zero": tmp_path / "zero.png",
         "corrupt": tmp_path / "bad.jpg", "unsupported": tmp_path / "anim.gif"}[case]
    if case == "zero":
        p.write_bytes(b"")
    elif case == "corrupt":
        p.write_bytes(b"\xff\xd8\xff this is not a jpeg")
    elif case == "unsupported":
        p.write_bytes(b"GIF89a")
    with pytest.raises(InputError) as e:
        L.read_rgb(p)
    msg = str(e.value)
    assert str(p) in msg and "\n" not in msg
    assert {"missing": "not found", "zero": "zero-byte", "corrupt": "corrupt", "unsupported": "unsupported"}[case] in msg


def test_read_mask_thresholds(tmp_path, caplog):
    m = np.array([[0, 1], [128, 255]], np.uint8)
    p = _write(tmp_path / "m.png", m)
    with caplog.at_level("WARNING"):
        assert L.read_mask(p).tolist() == [[False, True], [True, True]]         # default: value > 0
        L.read_mask(p)
    assert len([r for r in caplog.records if str(p) in r.getMessage()]) == 1    # multi-valued: warned once
    assert L.read_mask(p, threshold=128).tolist() == [[False, False], [False, True]]
    assert L.read_mask(p, threshold=0).tolist() == [[False, True], [True, True]]
    p01 = _write(tmp_path / "m01.png", np.array([[0, 1]], np.uint8))
    assert L.read_mask(p01).tolist() == [[False, True]]                         # 0/1 labels
    p255 = _write(tmp_path / "m255.png", np.array([[0, 255]], np.uint8))
    assert L.read_mask(p255).tolist() == [[False, True]]                        # 0/255
    p16 = _write(tmp_path / "m16.png", np.array([[0, 65535]], np.uint16))
    assert L.read_mask(p16).tolist() == [[False, True]]                         # 0/65535
    assert not [r for r in caplog.records if "m01" in r.getMessage() or "m255" in r.getMessage()]
    seg = np.zeros((2, 2, 3), np.uint8)
    seg[0, 1] = (40, 0, 0)                                                      # dark part colour
    assert L.read_mask(_write(tmp_path / "seg.png", seg), threshold=0).tolist() == [[False, True], [False, False]]


def test_resize_area_for_images_nearest_for_masks(tmp_path):
    img = np.zeros((4, 4, 3), np.uint8)
    img[::2, ::2] = 255
    out = L.load_rgb(_write(tmp_path / "i.png", img), 2).array
    assert out.shape == (2, 2, 3) and np.all(np.abs(out.astype(int) - 64) <= 1)   # area average
    mask = np.zeros((4, 4), np.uint8)
    mask[:, :2] = 255
    mo = L.load_mask(_write(tmp_path / "k.png", mask), 2).array
    assert mo.dtype == bool and mo.tolist() == [[True, False], [True, False]]


def test_decode_cache_hits_and_recovers_from_torn_entries(tmp_path):
    p = _write(tmp_path / "i.png", np.full((6, 6, 3), 9, np.uint8))
    cache = L.DecodeCache(tmp_path / "cache")
    a = L.load_rgb(p, 4, cache)
    assert cache.misses == 1 and cache.hits == 0
    entry = cache.path(a.sha256, "rgb", 4)
    assert entry.exists() and not [f for f in entry.parent.iterdir() if f.name.startswith(".")]
    b = L.load_rgb(p, 4, cache)
    assert cache.hits == 1 and np.array_equal(a.array, b.array) and b.native_hw == (6, 6)
    entry.write_bytes(b"torn")           # e.g. a foreign or damaged entry: treated as a miss, rewritten
    c = L.load_rgb(p, 4, cache)
    assert np.array_equal(a.array, c.array) and cache.misses == 2
    assert L.load_rgb(p, 4, cache).array is not None and cache.hits == 2
    # different resolution = different key
    L.load_rgb(p, 3, cache)
    assert cache.path(a.sha256, "rgb", 3).exists()


def test_parts_from_colors():
    rgb = np.zeros((1, 3, 3), np.uint8)
    rgb[0, 1] = (10, 20, 30)
    assert L.parts_from_colors(rgb, {(10, 20, 30): 2}).tolist() == [[0, 2, 0]]
    rgb[0, 2] = (1, 2, 3)                        # outside the table: refused, never silently background
    with pytest.raises(L.BadFileError, match=r"p.png: seg colour \(1, 2, 3\) is outside the class table"):
        L.parts_from_colors(rgb, {(10, 20, 30): 2}, "p.png")
