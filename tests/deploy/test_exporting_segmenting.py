"""The export and segment stages' logic, called directly (pipeline.deploy.export, pipeline.deploy.image_files): the
stage scripts only wire options to these functions."""

from __future__ import annotations

import csv

import json

import numpy as np
import pytest
from PIL import Image

from pipeline.artifacts.lineage import make_meta
from pipeline.artifacts.store import open_artifact
from pipeline.catalog import bundle_file
from pipeline.runtime.errors import InputError
from pipeline.deploy.bundle import is_deploy_bundle
from pipeline.deploy.export import export_lines, plan_export, write_export
from pipeline.params import load_params
from pipeline.deploy.image_files import check_options, model_resolution, segment_images
from tests.builders.deploy import PARAMS, RES, make_checkpoint, make_thresholds


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A tiny checkpoint, its thresholds row, and the bundle plan_export + write_export make of it."""
    root = tmp_path_factory.mktemp("export")
    ckpt = make_checkpoint(root / "ckpt")
    thr = make_thresholds(root / "thresholds.parquet", [["geodistill", 42, 0.42, 0.7]])
    params = load_params(PARAMS, ["data.resolution=32"])
    plan = plan_export(ckpt, params, thresholds=thr, onnx=False)
    meta = make_meta("deploy", "export", "test", plan.params)
    info = write_export(plan, root / "deploy", meta)
    return root, ckpt, thr, params, plan, info


def test_plan_export_picks_the_calibrated_tau_and_the_resolution(exported):
    root, ckpt, thr, params, plan, info = exported
    assert (plan.tau, plan.resolution, plan.resolution_source) == (0.42, RES, "data.resolution")
    assert plan.tau_source == f"calibrated on the validation split ({thr}: geodistill, seed 42)"
    assert [a.meta.schema for a in plan.inputs] == ["checkpoint", "thresholds"]      # lineage
    assert plan.params["tau"] == 0.42 and plan.params["deploy"]["onnx"] is False
    assert plan.calibration_images is None and plan.calibration_note == "--no-onnx"
    # --tau wins and the table is then not an input
    forced = plan_export(ckpt, params, thresholds=thr, tau=0.3, onnx=False)
    assert (forced.tau, forced.tau_source) == (0.3, "--tau") and len(forced.inputs) == 1
    # no thresholds: the params' fixed tau, saying why
    fixed = plan_export(ckpt, load_params(PARAMS, ["calibrate.fixed_tau=0.45"]), onnx=False)
    assert (fixed.tau, fixed.tau_source) == (0.45, "calibrate.fixed_tau (no --thresholds given)")
    no_art = plan_export(ckpt, params, thresholds=thr, onnx=True)
    assert no_art.calibration_note.startswith("no --artifacts given")


def test_write_export_writes_the_bundle_and_export_lines_report_it(exported):
    root, ckpt, thr, params, plan, info = exported
    out = root / "deploy"
    assert is_deploy_bundle(out) and not is_deploy_bundle(root) and not is_deploy_bundle(root / "missing")
    assert (out / bundle_file("torchscript")).exists() and not (out / bundle_file("onnx")).exists()
    written = json.loads((out / bundle_file("deploy_json")).read_text())
    assert written["tau"] == 0.42 and written["source"]["bundle_fingerprint"] == open_artifact(out).meta.fingerprint
    assert written["source"]["thresholds"] == str(thr) and written["source"]["resolution_source"] == "data.resolution"
    lines = export_lines(plan, info, out)
    assert lines[0].startswith(f"export: geodistill seed 42, tau=0.42, {RES}px -> {out} (torchscript: max|dZ|=")
    assert lines[-1] == f"export: int8 model skipped: no {bundle_file('onnx')} (disabled)"


def test_segment_images_writes_masks_with_the_bundle_tau(exported, tmp_path):
    root, *_ = exported
    images = tmp_path / "in"
    images.mkdir()
    rng = np.random.default_rng(0)
    for name in ("a.png", "b.png"):
        Image.fromarray(rng.integers(0, 255, (40, 50, 3), dtype=np.uint8)).save(images / name)
    said = []
    result = segment_images(root / "deploy", images, tmp_path / "out", engine="torch", device="cpu", echo=said.append)
    assert len(result.written) == 2
    mask = np.asarray(Image.open(tmp_path / "out" / "a.png.mask.png"))
    assert mask.shape == (40, 50) and set(np.unique(mask)) <= {0, 255}
    assert said[0] == f"segment: engine torch, 2 image(s), {RES}px ({root / 'deploy' / bundle_file('deploy_json')}), " \
                      "tau=0.42 (deploy bundle (calibrated on the validation split (" + \
                      f"{root / 'thresholds.parquet'}: geodistill, seed 42)))"
    assert said[1].startswith(f"segment: wrote 2 mask(s) to {tmp_path / 'out'}; per-frame confidence in "
                              "confidence.csv (lowest ") and "ms/image" in said[-1]
    # the frame confidence of each mask: the Segmenter's own score of that image (flight software's "trust it?")
    from pipeline.deploy.segmenter import Segmenter

    rows = list(csv.DictReader(open(tmp_path / "out" / "confidence.csv")))
    seg = Segmenter.from_bundle(root / "deploy", engine="torch")
    assert [r["mask"] for r in rows] == ["a.png.mask.png", "b.png.mask.png"]
    assert [float(r["confidence"]) for r in rows] == pytest.approx([seg.score(images / n) for n in ("a.png", "b.png")],
                                                                   abs=1e-6)
    assert min(result.scores) == pytest.approx(float(said[1].split("(lowest ")[1].split(":")[0]), abs=1e-3)


def test_segment_options_and_resolution_are_checked_before_anything_is_written(exported, tmp_path):
    root, ckpt, *_ = exported
    with pytest.raises(InputError, match="checkpoint= missing"):  # Python's terms (click requires the flag itself)
        check_options(None, "x", "y", 8, None)
    with pytest.raises(InputError, match="--batch-size 0"):
        check_options("c", "x", "y", 0, None)
    with pytest.raises(InputError, match="--resolution 4: must be >= 8"):
        segment_images(ckpt, tmp_path, tmp_path / "o", resolution=4)
    said = []
    assert model_resolution(RES, 64, root / "deploy", said.append) == (64, "--resolution")
    assert said and "differs from the 32px" in said[0]
    with pytest.raises(InputError, match="records no training resolution; pass --resolution N"):
        model_resolution(None, None, ckpt)
    assert not (tmp_path / "o").exists()
