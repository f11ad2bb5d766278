"""16-bit frames under a stated bit depth (params ``data.bit_depth``): a 12-bit sensor's frames stored in
16-bit PNG/TIFF files are nearly black read as full range (``auto``, today's rule, now with a warning),
and full-range 8-bit with ``bit_depth=12`` -- in the loader, the decode cache, prepare's reader, segment's
reader and :class:`pipeline.Segmenter`."""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pandas as pd
import pytest

from pipeline.datasets import loading
from pipeline.datasets.loading import iter_arrays
from pipeline.datasets.manifest import DatasetSpec
from pipeline.datasets.params import FrameSettings, fingerprint_params
from pipeline.runtime.errors import InputError
from pipeline.params import PAPER, validate_section


def twelve_bit_frame(h: int = 24, w: int = 40) -> np.ndarray:
    """A 12-bit grey ramp 0..4095 in a uint16 array, as a 12-bit sensor's driver stores it."""
    ramp = np.linspace(0, 4095, h * w).round().astype(np.uint16).reshape(h, w)
    ramp[0, 0], ramp[-1, -1] = 0, 4095
    return ramp


@pytest.fixture(autouse=True)
def _fresh_warnings():
    loading._warned_frames.clear()
    yield
    loading._warned_frames.clear()


@pytest.mark.parametrize("suffix", [".png", ".tif"])
def test_a_12_bit_frame_is_dark_and_warned_under_auto_and_full_range_at_12(tmp_path, caplog, suffix):
    raw = twelve_bit_frame()
    f = tmp_path / f"frame{suffix}"
    assert cv2.imwrite(str(f), raw)
    with caplog.at_level(logging.WARNING, logger=loading.__name__):
        auto = loading.read_rgb(f)
    assert auto.dtype == np.uint8 and auto.max() == 16       # 4095 / 257: nearly black, today's map
    np.testing.assert_array_equal(auto[..., 0], ((raw.astype(np.uint32) + 128) // 257).astype(np.uint8))
    assert [r for r in caplog.records if str(f) in r.getMessage() and "bit_depth" in r.getMessage()
            and "4,095 of 65,535" in r.getMessage()], caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger=loading.__name__):
        full = loading.read_rgb(f, bit_depth=12)
    assert not caplog.records
    assert full.min() == 0 and full.max() == 255
    np.testing.assert_array_equal(full[..., 1], np.round(raw.astype(np.float64) * 255 / 4095).astype(np.uint8))


def test_the_16_bit_map_is_unchanged_under_auto_and_16_and_a_full_frame_is_not_warned(caplog):
    v = np.arange(65536, dtype=np.uint16)
    with caplog.at_level(logging.WARNING, logger=loading.__name__):
        a, note = loading.scale_16bit(v, "auto")
    assert note is None and not caplog.records        # max 65535: the whole range is used
    np.testing.assert_array_equal(a, ((v.astype(np.uint32) + 128) // 257).astype(np.uint8))
    np.testing.assert_array_equal(loading.scale_16bit(v, 16)[0], a)
    for bits in (10, 12, 14):
        top = 2 ** bits - 1
        got, _ = loading.scale_16bit(np.arange(top + 1, dtype=np.uint16), bits)
        np.testing.assert_array_equal(got, np.floor(np.arange(top + 1) * 255 / top + 0.5).astype(np.uint8))


def test_values_above_the_stated_depth_clip_with_a_warning(tmp_path, caplog):
    raw = twelve_bit_frame()
    raw[3, 3] = 5000
    f = tmp_path / "hot.png"
    cv2.imwrite(str(f), raw)
    with caplog.at_level(logging.WARNING, logger=loading.__name__):
        got = loading.read_rgb(f, bit_depth=12)
    assert got[3, 3, 0] == 255 and "above the stated 12-bit maximum" in caplog.text


def test_bad_bit_depths_are_refused_by_the_api_and_the_params():
    with pytest.raises(InputError, match="bit_depth=11"):
        loading.scale_16bit(np.zeros(3, np.uint16), 11)
    with pytest.raises(InputError, match="data: bit_depth=11"):
        validate_section("data", {**PAPER.data.model_dump(), "bit_depth": 11})
    assert validate_section("data", {**PAPER.data.model_dump(), "bit_depth": 12})["bit_depth"] == 12
    assert PAPER.data.bit_depth == "auto"


def test_the_decode_cache_keys_the_bit_depth_and_keeps_the_warning(tmp_path, caplog):
    f = tmp_path / "frame.png"
    cv2.imwrite(str(f), twelve_bit_frame())
    cache = loading.DecodeCache(tmp_path / "cache")
    first = loading.load_rgb(f, 16, cache).array
    loading._warned_frames.clear()                   # a new process: the entry is read from the cache
    with caplog.at_level(logging.WARNING, logger=loading.__name__):
        again = loading.load_rgb(f, 16, cache)
    assert cache.hits == 1 and "under 1/8 of the range" in caplog.text
    np.testing.assert_array_equal(again.array, first)
    deep = loading.load_rgb(f, 16, cache, bit_depth=12).array
    assert cache.hits == 1 and deep.max() > 200 > first.max()   # its own entry, not the auto one


def test_prepares_reader_and_its_fingerprint_follow_data_bit_depth(tmp_path):
    f = tmp_path / "frame.tif"
    cv2.imwrite(str(f), twelve_bit_frame(32, 32))
    rows = pd.DataFrame({"image_path": [str(f)], "mask_path": [None], "part_path": [None]})
    dark = next(iter_arrays(rows, DatasetSpec(rows), FrameSettings.from_params(PAPER.data.model_dump()), 32, None))[1]
    bright = next(iter_arrays(rows, DatasetSpec(rows), FrameSettings.from_params(PAPER.data.model_dump() | {"bit_depth": 12}), 32, None))[1]
    assert dark.max() <= 16 and bright.max() >= 250
    data = PAPER.data.model_dump()
    assert "bit_depth" not in fingerprint_params(data)      # the default leaves earlier fingerprints alone
    assert fingerprint_params({**data, "bit_depth": 12})["bit_depth"] == 12


def test_segment_and_the_segmenter_read_frames_at_their_bit_depth(tmp_path):
    from pipeline.deploy.image_files import _load
    from pipeline.deploy.segmenter import Segmenter

    raw = twelve_bit_frame(32, 32)
    f = tmp_path / "frame.png"
    cv2.imwrite(str(f), raw)
    assert _load(f, 32, None, False)[0].max() <= 16
    assert _load(f, 32, None, False, 12)[0].max() >= 250
    seen = []

    def logits(x):
        seen.append(x.numpy().copy())
        return np.zeros((x.shape[0], 1, *x.shape[2:]), np.float32)

    seg = Segmenter("torch", 32, {}, logits, {}, tau=0.5, bit_depth=12)
    seg.predict(raw)                                   # an array straight from the sensor
    seg.predict(f)                                     # the same frame from its file
    assert len(seen) == 2 and seen[0].max() == seen[1].max() == 1.0


def _low_range_warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if loading.LOW_RANGE_NOTE in r.getMessage()]


def _twelve_bit_folder(root):
    from tests.builders.teacher import make_image_folder

    images, _ = make_image_folder(root, n=3, masks=False)
    cv2.imwrite(str(images / "deep.png"), twelve_bit_frame(32, 32))
    return images


def test_label_warns_once_naming_the_flag_on_the_cli_and_the_keyword_in_python(tmp_path, caplog, tiny_sam3):
    import pipeline
    from click.testing import CliRunner
    from pipeline.cli.main import main

    images = _twelve_bit_folder(tmp_path / "data")
    fast = ["--set", "data.resolution=32", "--set", "data.contact_sheet_images=2", "--device", "cpu"]
    run = lambda out, *extra: CliRunner().invoke(main, ["label", str(images), "--out", str(tmp_path / out),  # noqa: E731
                                                        "--checkpoint", str(tiny_sam3), "--format", "png",
                                                        *fast, *extra])
    with caplog.at_level(logging.WARNING, logger=loading.__name__):
        res = run("a")
    assert res.exit_code == 0, res.output
    said = _low_range_warnings(caplog)
    assert len(said) == 1 and "--bit-depth 12" in said[0] and "bit_depth=" not in said[0], said  # once, not twice
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger=loading.__name__):  # the flag states the depth: nothing to say
        assert run("b", "--bit-depth", "12").exit_code == 0
        assert run("c", "--set", "data.bit_depth=12").exit_code == 0
    assert _low_range_warnings(caplog) == []
    with caplog.at_level(logging.WARNING, logger=loading.__name__):
        pipeline.label(images, out=tmp_path / "d", checkpoint=tiny_sam3, formats="png", device="cpu",
                       overrides=["data.resolution=32", "data.contact_sheet_images=2"])
    said = _low_range_warnings(caplog)
    assert len(said) == 1 and "bit_depth=12" in said[0] and "--bit-depth" not in said[0], said


def test_segment_reads_frames_as_the_bundle_records_and_warns_only_when_no_depth_is_known(tmp_path, caplog, ckpts):
    from click.testing import CliRunner
    from pipeline.cli.main import main
    from tests.builders.deploy import run_export

    bundle = tmp_path / "deploy"
    res = run_export(ckpts["with"], bundle, "--no-int8", "--no-onnx", "--set", "data.bit_depth=12")
    assert res.exit_code == 0, res.output
    frames = tmp_path / "frames"
    frames.mkdir()
    cv2.imwrite(str(frames / "deep.png"), twelve_bit_frame(32, 32))
    seg = lambda model, out, *extra: CliRunner().invoke(main, ["segment", "--checkpoint", str(model), "--input",  # noqa: E731
                                                               str(frames), "--output", str(tmp_path / out),
                                                               "--device", "cpu", "--engine", "torch", *extra])
    with caplog.at_level(logging.WARNING, logger=loading.__name__):
        assert seg(bundle, "a").exit_code == 0                                  # the bundle records 12
        assert seg(ckpts["with"], "b", "--bit-depth", "12").exit_code == 0      # the flag says 12
    assert _low_range_warnings(caplog) == []
    with caplog.at_level(logging.WARNING, logger=loading.__name__):
        assert seg(ckpts["with"], "c").exit_code == 0                           # nothing known: said once
    said = _low_range_warnings(caplog)
    assert len(said) == 1 and "--bit-depth 12" in said[0], said
