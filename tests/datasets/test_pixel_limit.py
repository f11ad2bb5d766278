"""The pixel limit before decoding (``data.max_pixels``, ``--max-pixels`` / ``max_pixels=``) and the
convention that an error names a parameter in the caller's terms (pipeline/runtime/errors.py).

The bombs are header-only files built here: a PNG whose IHDR declares 30,000 x 30,000 pixels with a
tiny IDAT, a JPEG start-of-frame, a BMP header and a TIFF directory declaring huge sizes."""

from __future__ import annotations

import pickle
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml
from click.testing import CliRunner

from pipeline.datasets.loading import header_size
from pipeline.datasets.loading import (DEFAULT_MAX_PIXELS, BadFileError, DecodeCache, load_rgb, pixel_limit,
                                       read_mask, read_rgb)
from pipeline.datasets.manifest import BadInputPolicy
from pipeline.runtime.errors import API, CLI, MAX_PIXELS, SKIP_BAD, InputError
from pipeline.params import PAPER

REPO = Path(__file__).resolve().parents[2]
SIDE = 30_000


# --------------------------------------------------------------------------------------------------
# header-only bombs
# --------------------------------------------------------------------------------------------------
def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def png_bomb(w: int = SIDE, h: int = SIDE) -> bytes:
    """A valid-looking PNG: IHDR declares w x h (8-bit grey), the IDAT holds one compressed row."""
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
            + _chunk(b"IDAT", zlib.compress(b"\0" * (w + 1))) + _chunk(b"IEND", b""))


def jpeg_bomb(w: int = 60_000, h: int = 60_000) -> bytes:
    """SOI, an APP0 segment, a baseline SOF0 declaring w x h with 3 components, EOI."""
    app0 = b"\xff\xe0" + struct.pack(">H", 16) + b"JFIF\0\x01\x01\0\0\x01\0\x01\0\0"
    sof = b"\xff\xc0" + struct.pack(">HBHHB", 17, 8, h, w, 3) + b"\x01\x11\x00\x02\x11\x01\x03\x11\x01"
    return b"\xff\xd8" + app0 + sof + b"\xff\xd9"


def bmp_bomb(w: int = SIDE, h: int = -SIDE, core: bool = False) -> bytes:
    """A BMP file header and DIB header (BITMAPINFOHEADER, or the 12-byte BITMAPCOREHEADER), no pixels."""
    dib = (struct.pack("<IHHHH", 12, w, abs(h), 1, 24) if core
           else struct.pack("<IiiHHIIiiII", 40, w, h, 1, 24, 0, 0, 2835, 2835, 0, 0))
    return b"BM" + struct.pack("<IHHI", 14 + len(dib), 0, 0, 14 + len(dib)) + dib


def tiff_bomb(w: int = SIDE, h: int = SIDE, order: str = "<", big: bool = False) -> bytes:
    """A TIFF (classic or BigTIFF, either byte order) whose first directory holds ImageWidth/ImageLength."""
    mark = b"II" if order == "<" else b"MM"
    if big:
        head = mark + struct.pack(order + "HHHQ", 43, 8, 0, 16)
        entries = b"".join(struct.pack(order + "HHQQ", tag, 16, 1, v) for tag, v in ((256, w), (257, h)))
        return head + struct.pack(order + "Q", 2) + entries + struct.pack(order + "Q", 0)
    head = mark + struct.pack(order + "HI", 42, 8)
    entries = (struct.pack(order + "HHIHH", 256, 3, 1, w, 0) if w < 65536 else struct.pack(order + "HHII", 256, 4, 1, w))
    entries += struct.pack(order + "HHII", 257, 4, 1, h)
    return head + struct.pack(order + "H", 2) + entries + struct.pack(order + "I", 0)


BOMBS = {"big.png": png_bomb(), "big.jpg": jpeg_bomb(), "big.bmp": bmp_bomb(), "big.tif": tiff_bomb()}


# --------------------------------------------------------------------------------------------------
# the header reader
# --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("suffix, array", [
    (".png", np.zeros((37, 53, 3), np.uint8)), (".png", np.zeros((37, 53), np.uint16)),
    (".jpg", np.full((37, 53, 3), 90, np.uint8)), (".jpg", np.zeros((37, 53), np.uint8)),
    (".tif", np.zeros((37, 53, 3), np.uint16)), (".tif", np.zeros((37, 53, 3), np.float32)),
    (".bmp", np.zeros((37, 53, 3), np.uint8)), (".bmp", np.zeros((37, 53), np.uint8))])
def test_header_size_matches_what_opencv_decodes(suffix, array):
    ok, buf = cv2.imencode(suffix, array)
    assert ok
    data = buf.tobytes()
    decoded = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    assert header_size(data) == (decoded.shape[1], decoded.shape[0]) == (53, 37)


def test_header_size_of_hand_built_headers_and_garbage():
    assert header_size(png_bomb(123, 45)) == (123, 45)
    assert header_size(jpeg_bomb(700, 300)) == (700, 300)
    assert header_size(bmp_bomb(70, -30)) == (70, 30) == header_size(bmp_bomb(70, 30))
    assert header_size(bmp_bomb(70, 30, core=True)) == (70, 30)
    for order in "<>":
        for big in (False, True):
            assert header_size(tiff_bomb(70_000, 30, order, big)) == (70_000, 30)
    for junk in (b"", b"junk", b"\x89PNG\r\n\x1a\n not really a png", b"\xff\xd8\xff this is not a jpeg",
                 png_bomb()[:20], bmp_bomb(0, 5), b"GIF89a", tiff_bomb()[:12]):
        assert header_size(junk) is None, junk


# --------------------------------------------------------------------------------------------------
# the reader refuses before decoding
# --------------------------------------------------------------------------------------------------
def test_default_is_the_schema_value():
    assert DEFAULT_MAX_PIXELS == PAPER.data.max_pixels == 2**26 == pixel_limit(None)


@pytest.mark.parametrize("name", sorted(BOMBS))
def test_reader_refuses_a_bomb_without_decoding(tmp_path, monkeypatch, name):
    path = tmp_path / name
    path.write_bytes(BOMBS[name])

    def no_decoding(*a, **k):
        raise AssertionError("cv2.imdecode called on a file above the pixel limit")

    monkeypatch.setattr(cv2, "imdecode", no_decoding)
    w, h = header_size(BOMBS[name])
    for read in (lambda: read_rgb(path), lambda: read_mask(path), lambda: load_rgb(path, 32, DecodeCache(None)),
                 lambda: read_rgb(path, max_pixels=w * h - 1)):
        with pytest.raises(BadFileError) as e:
            read()
        assert e.value.path == str(path) and f"{w} x {h} = {w * h:,} pixels" in e.value.reason
        assert "max-pixels" not in e.value.reason and "max_pixels" not in e.value.reason  # the listed reason
        assert e.value.render(CLI) == f"{e.value.path}: {e.value.reason} (raise --max-pixels to read it)"
        assert str(e.value) == f"{e.value.path}: {e.value.reason} (raise max_pixels= to read it)"
    # at the limit it is the decoder's turn (here: our stand-in)
    with pytest.raises(AssertionError, match="imdecode called"):
        read_rgb(path, max_pixels=w * h)


def test_a_cached_image_is_refused_under_a_lower_limit(tmp_path):
    path = tmp_path / "a.png"
    cv2.imwrite(str(path), np.zeros((20, 30, 3), np.uint8))
    cache = DecodeCache(tmp_path / "cache")
    assert load_rgb(path, 16, cache).native_hw == (20, 30)
    with pytest.raises(BadFileError, match="20 = 600 pixels in its header, above the limit of 599"):
        load_rgb(path, 16, cache, max_pixels=599)
    assert cache.hits == 0  # refused on the header, before the cache was asked


def test_corrupt_files_keep_their_wording(tmp_path):
    path = tmp_path / "bad.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n not really a png")
    with pytest.raises(BadFileError, match="corrupt or undecodable image") as e:
        read_rgb(path)
    assert str(e.value) == e.value.render(CLI)  # no option named: one rendering


# --------------------------------------------------------------------------------------------------
# the convention: the caller's terms
# --------------------------------------------------------------------------------------------------
def test_an_error_names_the_option_in_the_callers_terms():
    e = InputError("{}: must be >= 1 (and {} is {{fine}})", MAX_PIXELS(0), SKIP_BAD)
    assert e.render(CLI) == "--max-pixels 0: must be >= 1 (and --skip-bad is {fine})"
    assert e.render(API) == str(e) == "max_pixels=0: must be >= 1 (and skip_bad=True is {fine})"
    assert InputError("plain {braces} stay").render(CLI) == "plain {braces} stay" == str(InputError("plain {braces} stay"))
    for bad in (0, -5, 1.5, True, "many"):
        with pytest.raises(InputError) as err:
            pixel_limit(bad)
        assert err.value.render(CLI).startswith(f"--max-pixels {bad}: must be a whole number")
        assert str(err.value).startswith(f"max_pixels={bad!r}: must be a whole number")
    # a line rendered by a command in a subprocess (a distill project's stage) is spelled again
    line = "x/a.png: 9 pixels, above the limit of 4 (raise --max-pixels to read it; pass --skip-bad to leave it out)"
    back = InputError.from_line(line)
    assert back.render(CLI) == line
    assert str(back) == "x/a.png: 9 pixels, above the limit of 4 (raise max_pixels= to read it; pass skip_bad=True " \
                        "to leave it out)"
    # pickled across processes (Ray workers): both renderings survive
    for err in (e, BadFileError("a.png", "too big", "raise {} to read it", MAX_PIXELS)):
        again = pickle.loads(pickle.dumps(err))
        assert type(again) is type(err) and again.render(CLI) == err.render(CLI) and str(again) == str(err)


def test_the_bad_file_policy_refuses_in_the_callers_terms(tmp_path):
    path = tmp_path / "big.png"
    path.write_bytes(png_bomb())
    with pytest.raises(BadFileError) as bad:
        read_rgb(path)
    with pytest.raises(InputError) as e:
        BadInputPolicy(False).report_error("big", bad.value)
    cli, api = e.value.render(CLI), str(e.value)
    assert cli == (f"{path}: {bad.value.reason} (raise --max-pixels to read it; pass --skip-bad, or set "
                   "data.skip_bad: true in params.yaml, to leave it out)")
    assert "max_pixels=" in api and "skip_bad=True" in api and "--" not in api
    policy = BadInputPolicy(True)
    policy.report_error("big", bad.value)
    assert policy.rows() == [("big", str(path), bad.value.reason)]


# --------------------------------------------------------------------------------------------------
# the commands: label, distill, prepare (folder reader)
# --------------------------------------------------------------------------------------------------
@pytest.fixture
def folder(tmp_path):
    """images/: two small images and a PNG bomb; masks/: a mask for each (the SIMULATOR's references)."""
    images, masks = tmp_path / "images", tmp_path / "masks"
    images.mkdir()
    masks.mkdir()
    for i in range(2):
        img = np.full((40, 48, 3), 20, np.uint8)
        img[10:25, 12:30] = 200
        cv2.imwrite(str(images / f"img{i}.png"), img)
        cv2.imwrite(str(masks / f"img{i}.png"), (img[..., 0] > 100).astype(np.uint8) * 255)
    (images / "big.png").write_bytes(png_bomb())
    cv2.imwrite(str(masks / "big.png"), np.zeros((8, 8), np.uint8))
    return images, masks


def _cli(*args):
    from pipeline.cli.main import main

    return CliRunner().invoke(main, [str(a) for a in args])


def _error_lines(output: str) -> list[str]:
    return [ln for ln in output.splitlines() if "error" in ln.lower()]


LABEL = ["--backend", "simulated", "--set", "data.resolution=32", "--device", "cpu", "--format", "png"]


def test_label_refuses_the_bomb_in_one_line_exit_2(folder, tmp_path, monkeypatch):
    images, masks = folder
    res = _cli("label", images, "--out", tmp_path / "out", "--reference-masks", masks, *LABEL)
    assert res.exit_code == 2, res.output
    assert _error_lines(res.output) == [
        f"geodistill label: error: {images / 'big.png'}: {SIDE} x {SIDE} = {SIDE * SIDE:,} pixels in its header, "
        f"above the limit of {DEFAULT_MAX_PIXELS:,} (raise --max-pixels to read it; pass --skip-bad, or set "
        "data.skip_bad: true in params.yaml, to leave it out)"], res.output
    # --max-pixels lowers the limit below the good images too; a bad value is one line naming the flag
    (images / "big.png").unlink()
    res = _cli("label", images, "--out", tmp_path / "out2", "--reference-masks", masks, "--max-pixels", 100, *LABEL)
    assert res.exit_code == 2 and f"{images / 'img0.png'}: 48 x 40 = 1,920 pixels in its header, above the limit " \
        "of 100 (raise --max-pixels" in res.output, res.output
    res = _cli("label", images, "--out", tmp_path / "out3", "--reference-masks", masks, "--max-pixels", 0, *LABEL)
    assert res.exit_code == 2 and _error_lines(res.output) == [
        f"geodistill label: error: --max-pixels 0: must be a whole number of pixels >= 1 (width x height; default "
        f"{DEFAULT_MAX_PIXELS:,})"], res.output


def test_label_skip_bad_skips_and_lists_the_bomb(folder, tmp_path):
    images, masks = folder
    out = tmp_path / "out"
    res = _cli("label", images, "--out", out, "--reference-masks", masks, "--skip-bad", *LABEL)
    assert res.exit_code == 0, res.output
    skipped = pd.read_csv(out / "skipped.csv")
    row = skipped[skipped["path"] == str(images / "big.png")]
    assert len(row) == 1 and f"{SIDE} x {SIDE} = {SIDE * SIDE:,} pixels in its header" in row["reason"].iloc[0]
    assert row["image_id"].iloc[0] == "big"
    assert sorted(pd.read_csv(out / "labels.csv")["image_id"]) == ["img0", "img1"]
    assert f"label: skipped 1 bad file(s) (first: {images / 'big.png'}: {SIDE} x {SIDE}" in res.output


def test_the_python_api_names_keywords(folder, tmp_path):
    import pipeline

    images, masks = folder
    common = dict(out=tmp_path / "out", backend="simulated", reference_masks=masks, formats="png",
                  overrides={"data.resolution": 32}, device="cpu")
    with pytest.raises(InputError) as e:
        pipeline.label(images, **common)
    msg = str(e.value)
    assert msg.startswith(f"{images / 'big.png'}: {SIDE} x {SIDE}") and "max_pixels=" in msg and "skip_bad=True" in msg
    assert "--" not in msg, msg
    with pytest.raises(InputError) as e:
        pipeline.label(images, **common, max_pixels=0)
    assert str(e.value).startswith("max_pixels=0: must be a whole number") and "--" not in str(e.value)
    res = pipeline.label(images, **common, skip_bad=True, max_pixels=10 ** 6)
    assert [Path(p).name for p, _ in res.skipped if "pixels in its header" in _] == ["big.png"]


def test_distill_passes_max_pixels_to_its_project(folder, tmp_path):
    images, _ = folder
    out = tmp_path / "run"
    res = _cli("distill", images, "--out", out, "--backend", "imported", "--imported-dir", tmp_path, "--no-run",
               "--max-pixels", 12345, "--device", "cpu")
    assert res.exit_code == 0, res.output
    assert yaml.safe_load((out / "params.yaml").read_text())["data"]["max_pixels"] == 12345
    res = _cli("distill", images, "--out", tmp_path / "run2", "--backend", "imported", "--imported-dir", tmp_path,
               "--no-run", "--max-pixels", -1)
    assert res.exit_code == 2 and _error_lines(res.output) == [
        f"geodistill distill: error: --max-pixels -1: must be a whole number of pixels >= 1 (width x height; "
        f"default {DEFAULT_MAX_PIXELS:,})"], res.output


def _prepare(out: Path, root: Path, *extra: str):
    from stages.prepare import main as prepare

    args = ["--params", str(REPO / "params.yaml"), "--out-dir", str(out)]
    for s in ("data.resolution=32", "data.source=folder", f"data.root={root}", f"data.cache_dir={out.parent / 'c'}",
              "data.contact_sheet_images=2"):
        args += ["--set", s]
    return CliRunner().invoke(prepare, [*args, *extra])


def test_the_folder_reader_refuses_and_skips_the_bomb(folder, tmp_path):
    images, masks = folder
    (masks / "big.png").unlink()  # an unlabeled training image: only the image is read
    res = _prepare(tmp_path / "a", images.parent)
    assert res.exit_code == 2, res.output
    assert _error_lines(res.output) == [
        f"geodistill prepare: error: {images / 'big.png'}: {SIDE} x {SIDE} = {SIDE * SIDE:,} pixels in its header, "
        f"above the limit of {DEFAULT_MAX_PIXELS:,} (raise --max-pixels to read it; pass --skip-bad, or set "
        "data.skip_bad: true in params.yaml, to leave it out)"], res.output
    res = _prepare(tmp_path / "b", images.parent, "--skip-bad")
    assert res.exit_code == 0, res.output
    from pipeline.artifacts.store import open_artifact

    skipped = open_artifact(tmp_path / "b" / "skipped_files.parquet", "skipped_files").df
    reasons = dict(zip(skipped["path"].map(lambda p: Path(p).name), skipped["reason"]))
    assert "pixels in its header, above the limit" in reasons["big.png"]
    assert "big" not in set(open_artifact(tmp_path / "b" / "manifest.parquet", "manifest").df["image_id"])
    # data.max_pixels is the folder reader's limit
    res = _prepare(tmp_path / "c", images.parent, "--skip-bad", "--set", "data.max_pixels=100")
    assert res.exit_code == 2 and "no usable images left" in res.output, res.output


# --------------------------------------------------------------------------------------------------
# shared options live in pipeline/cli/conventions.py
# --------------------------------------------------------------------------------------------------
def test_no_stage_imports_a_sibling_stage():
    """A stage script or a user command imports shared options and helpers from pipeline/cli/conventions.py
    (a stage also through stages/_common.py), never from a stage (``label`` took ``--workers`` from ``stages.teacher``)."""
    import ast

    found = []
    for path in sorted([*(REPO / "stages").glob("*.py"), *(REPO / "pipeline" / "cli").glob("*.py")]):
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            found += [(path.name, n) for n in names if n.startswith("stages.") and n != "stages._common"]
    assert found == []
    from pipeline.cli import label

    flags = {o for p in label.main.params for o in p.opts}
    assert {"--workers", "--address", "--max-pixels", "--skip-bad", "--overwrite"} <= flags


def test_segment_refuses_and_skips_the_bomb(tmp_path):
    """segment reads images through the same header check: one line naming the file and --max-pixels,
    exit 2, nothing written; --skip-bad lists it in skipped.csv and segments the rest."""
    from pipeline.cli.segment import main as segment_main
    from tests.builders.deploy import make_checkpoint

    ckpt = make_checkpoint(tmp_path / "ckpt")
    images = tmp_path / "in"
    images.mkdir()
    cv2.imwrite(str(images / "ok.png"), np.full((20, 24, 3), 90, np.uint8))
    (images / "big.png").write_bytes(png_bomb())

    def run(out, *extra):
        return CliRunner().invoke(segment_main, ["--device", "cpu", "--checkpoint", str(ckpt), "--input", str(images),
                                                 "--output", str(tmp_path / out), "--resolution", "32", "--tau", "0.5",
                                                 *map(str, extra)])

    res = run("out")
    assert res.exit_code == 2, res.output
    assert [ln for ln in res.output.splitlines() if "error" in ln] == [
        f"geodistill segment: error: {images / 'big.png'}: {SIDE} x {SIDE} = {SIDE * SIDE:,} pixels in its header, "
        f"above the limit of {DEFAULT_MAX_PIXELS:,} (raise --max-pixels to read it; pass --skip-bad to leave it out)"]
    res = run("out2", "--skip-bad")
    assert res.exit_code == 0, res.output
    assert (tmp_path / "out2" / "ok.png.mask.png").is_file() and not (tmp_path / "out2" / "big.png.mask.png").exists()
    rows = pd.read_csv(tmp_path / "out2" / "skipped.csv")
    assert list(rows["path"]) == [str(images / "big.png")] and "pixels in its header" in rows["reason"].iloc[0]
    # a limit below the small image refuses it too
    res = run("out3", "--max-pixels", 100, "--skip-bad")
    assert res.exit_code == 2 and "skipped 2 bad file(s)" in res.output and "above the limit of 100" in res.output
    assert "none of the 2 file(s) could be read" in res.output, res.output


def test_segmenter_predict_refuses_the_bomb_naming_its_keyword(tmp_path):
    import pipeline
    from pipeline.runtime.errors import InputError
    from tests.builders.deploy import make_checkpoint

    ckpt = make_checkpoint(tmp_path / "ckpt")
    bomb = tmp_path / "big.png"
    bomb.write_bytes(png_bomb())
    seg = pipeline.Segmenter.from_bundle(ckpt, resolution=32, tau=0.5)
    with pytest.raises(InputError, match="max_pixels=") as err:
        seg.predict(bomb)
    assert "--max-pixels" not in str(err.value)
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.full((20, 24, 3), 90, np.uint8))
    assert seg.predict(small).shape == (20, 24)
    with pytest.raises(InputError, match="above the limit of 100"):
        pipeline.Segmenter.from_bundle(ckpt, resolution=32, tau=0.5, max_pixels=100).predict(small)
