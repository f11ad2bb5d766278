"""``geodistill segment`` on files of odd sizes and formats, a corrupt file among good ones, both a
checkpoint and a deploy bundle, and the rule that outputs never overwrite inputs."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from pipeline import deploy
from pipeline.datasets.loading import read_rgb, resize_image
from pipeline.inference import load_student
from stages.segment import main as segment_main
from test_deploy import HAS_ONNX, make_checkpoint, make_thresholds, run_export

RES = 32


@pytest.fixture(autouse=True)
def quiet(monkeypatch):
    monkeypatch.setenv("GEODISTILL_QUIET", "1")


def write_inputs(folder: Path) -> dict[str, tuple[int, int]]:
    """Odd-sized RGB, grey, RGBA, 16-bit and JPEG images; returns name -> (height, width)."""
    rng = np.random.default_rng(0)
    folder.mkdir(parents=True, exist_ok=True)
    yy, xx = np.mgrid[0:53, 0:37]
    blob = (((yy - 26) ** 2 + (xx - 18) ** 2) < 120)[..., None]
    rgb = np.where(blob, 210, 25).astype(np.uint8) + rng.integers(0, 20, (53, 37, 3), dtype=np.uint8)
    cv2.imwrite(str(folder / "odd.png"), rgb)                                              # 53 x 37
    cv2.imwrite(str(folder / "grey.png"), rng.integers(0, 255, (41, 29), dtype=np.uint8))  # grey
    cv2.imwrite(str(folder / "alpha.png"), rng.integers(0, 255, (30, 70, 4), dtype=np.uint8))  # RGBA
    cv2.imwrite(str(folder / "deep.tif"), rng.integers(0, 65535, (33, 35, 3), dtype=np.uint16))  # 16-bit
    sub = folder / "sub"
    sub.mkdir()
    cv2.imwrite(str(sub / "odd.jpg"), rgb)
    cv2.imwrite(str(sub / "odd.png"), rgb[:37])  # same stem as odd.jpg in the same folder
    return {"odd": (53, 37), "grey": (41, 29), "alpha": (30, 70), "deep": (33, 35),
            "sub/odd_jpg": (53, 37), "sub/odd_png": (37, 37)}


def segment(*args):
    return CliRunner().invoke(segment_main, ["--device", "cpu", *map(str, args)])


def reference_probs(ckpt: Path, path: Path) -> np.ndarray:
    """The documented recipe, computed here: area-resize to R x R, logits, sigmoid, bilinear back."""
    model, _ = load_student(ckpt)
    img = read_rgb(path)
    x = torch.from_numpy(resize_image(img, RES)).permute(2, 0, 1)[None].float() / 255
    with torch.no_grad():
        p = torch.sigmoid(model(x))[0, 0].numpy()
    return cv2.resize(p, (img.shape[1], img.shape[0]), interpolation=cv2.INTER_LINEAR)


def test_segment_checkpoint_folder_odd_sizes_formats_and_corrupt_file(tmp_path):
    ckpt = make_checkpoint(tmp_path / "ckpt")
    thr = make_thresholds(tmp_path / "thr.parquet", [("geodistill", 42, 0.5, 0.8)])
    sizes = write_inputs(tmp_path / "in")
    (tmp_path / "in" / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n not really a png")
    (tmp_path / "in" / "empty.jpg").write_bytes(b"")
    (tmp_path / "in" / "notes.txt").write_text("not an image, not a candidate")
    before = {p: p.read_bytes() for p in (tmp_path / "in").rglob("*") if p.is_file()}
    r = segment("--checkpoint", ckpt, "--input", tmp_path / "in", "--output", tmp_path / "out",
                "--thresholds", thr, "--resolution", RES, "--save-prob", "--overlay", "--batch-size", 3)
    assert r.exit_code == 0, r.output
    out = tmp_path / "out"
    for name, (h, w) in sizes.items():
        mask = cv2.imread(str(out / f"{name}_mask.png"), cv2.IMREAD_UNCHANGED)
        assert mask.shape == (h, w) and mask.dtype == np.uint8 and set(np.unique(mask)) <= {0, 255}
        assert cv2.imread(str(out / f"{name}_overlay.png")).shape == (h, w, 3)
        prob = cv2.imread(str(out / f"{name}_prob.png"), cv2.IMREAD_UNCHANGED)
        assert prob.shape == (h, w)
    # content: the mask is [P >= tau] of the documented recipe at the original size
    for name, src in (("odd", "odd.png"), ("alpha", "alpha.png"), ("deep", "deep.tif"), ("grey", "grey.png")):
        p = reference_probs(ckpt, tmp_path / "in" / src)
        mask = cv2.imread(str(out / f"{name}_mask.png"), cv2.IMREAD_UNCHANGED) > 0
        decided = np.abs(p - 0.5) > 1e-4
        assert np.array_equal(mask[decided], (p >= 0.5)[decided])
        prob = cv2.imread(str(out / f"{name}_prob.png"), cv2.IMREAD_UNCHANGED)
        assert np.abs(prob.astype(float) - p * 255).max() <= 0.51
    # the corrupt and zero-byte files are reported and skipped; the text file is not a candidate
    rows = list(csv.DictReader(open(out / "skipped.csv")))
    assert sorted(Path(r["path"]).name for r in rows) == ["broken.png", "empty.jpg"]
    assert all(r["reason"] for r in rows)
    assert "broken.png" in r.output and "empty.jpg" in r.output
    # inputs untouched
    assert all(p.read_bytes() == b for p, b in before.items())


def test_segment_deploy_bundle_backends_agree_and_use_bundle_tau(tmp_path):
    ckpt = make_checkpoint(tmp_path / "ckpt", seed=4)
    thr = make_thresholds(tmp_path / "thr.parquet", [("geodistill", 42, 0.47, 0.8)])
    assert run_export(ckpt, tmp_path / "deploy", "--thresholds", str(thr)).exit_code == 0
    write_inputs(tmp_path / "in")
    backends = ["torch", "torchscript"] + (["onnx"] if HAS_ONNX else [])
    masks = {}
    for b in backends:
        r = segment("--checkpoint", tmp_path / "deploy", "--input", tmp_path / "in" / "odd.png",
                    "--output", tmp_path / f"out_{b}", "--backend", b)
        assert r.exit_code == 0, r.output
        assert "tau=0.47" in r.output and f"{b} backend" in r.output
        masks[b] = cv2.imread(str(tmp_path / f"out_{b}" / "odd_mask.png"), cv2.IMREAD_UNCHANGED)
        assert masks[b].shape == (53, 37)
    for b in backends[1:]:
        assert np.array_equal(masks[b], masks["torch"]), b
    # --tau overrides the bundle's tau: tau = 0 keeps every pixel
    r = segment("--checkpoint", tmp_path / "deploy", "--input", tmp_path / "in" / "grey.png",
                "--output", tmp_path / "all", "--tau", 0)
    assert r.exit_code == 0 and (cv2.imread(str(tmp_path / "all" / "grey_mask.png"), 0) == 255).all()
    info = json.loads((tmp_path / "deploy" / "deploy.json").read_text())
    assert info["resolution"] == RES


def test_segment_never_overwrites_inputs_and_rejects_bad_options(tmp_path):
    ckpt = make_checkpoint(tmp_path / "ckpt")
    write_inputs(tmp_path / "in")
    base = ["--checkpoint", ckpt, "--resolution", RES, "--tau", 0.5]
    cases = [
        (["--input", tmp_path / "in", "--output", tmp_path / "in"], "inside the input folder"),
        (["--input", tmp_path / "in", "--output", tmp_path / "in" / "masks"], "inside the input folder"),
        (["--checkpoint", tmp_path / "missing", "--input", tmp_path / "in", "--output", tmp_path / "o"], "missing"),
        (["--input", tmp_path / "nowhere", "--output", tmp_path / "o"], "nowhere"),
        (["--input", tmp_path / "in", "--output", tmp_path / "o", "--tau", 2], "--tau"),
        (["--input", tmp_path / "in", "--output", tmp_path / "o", "--backend", "onnx"], "deploy bundle"),
        (["--input", tmp_path / "in"], "--output"),
    ]
    for extra, needle in cases:
        r = segment(*base, *extra)
        assert r.exit_code == 2, (extra, r.output)
        lines = r.output.strip().splitlines()
        assert len(lines) == 1 and needle in lines[0], (extra, r.output)
    assert not (tmp_path / "in" / "masks").exists() and not (tmp_path / "o").exists()
    # an input that is itself named like an output of another input in the same folder
    flat = tmp_path / "flat"
    flat.mkdir()
    img = read_rgb(tmp_path / "in" / "odd.png")
    cv2.imwrite(str(flat / "a.png"), img)
    cv2.imwrite(str(flat / "b.png"), img)
    r = segment(*base, "--input", flat / "a.png", "--output", flat)  # a_mask.png: no collision -> fine
    assert r.exit_code == 0 and (flat / "a_mask.png").exists()
    before = (flat / "a_mask.png").read_bytes()
    r = segment(*base, "--input", flat / "a_mask.png", "--output", tmp_path / "elsewhere")
    assert r.exit_code == 0  # a mask file is an image too; output goes elsewhere
    # a.png's mask would land on the input a_mask.png: refused before anything is written
    with pytest.raises(deploy.InputError, match="overwrite the input"):
        deploy.plan_outputs(flat, [flat / "a.png", flat / "a_mask.png"], flat, False)
    assert (flat / "a_mask.png").read_bytes() == before


def test_segment_all_files_unreadable_is_an_error(tmp_path):
    ckpt = make_checkpoint(tmp_path / "ckpt")
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "x.png").write_bytes(b"junk")
    r = segment("--checkpoint", ckpt, "--input", tmp_path / "in", "--output", tmp_path / "out", "--resolution", RES,
                "--tau", 0.5)
    assert r.exit_code == 2 and "could be read" in r.output.strip().splitlines()[-1]
    assert list(csv.DictReader(open(tmp_path / "out" / "skipped.csv")))[0]["path"].endswith("x.png")
