"""``geodistill distill``: a folder in, a student, deploy bundle and report out, through the DAG in a DVC
project generated in --out -- with the tests' tiny random SAM 3, with and without validation masks."""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import cv2
import pandas as pd
import pytest
import yaml
from click.testing import CliRunner

from pipeline import catalog
from tests.builders.lane import DISTILL_FAST as FAST  # demo-like tiny sizes: 32 px, 3 + 1 epochs

pytestmark = pytest.mark.slow


def cli(*args):
    from pipeline.cli.main import main

    return CliRunner().invoke(main, [str(a) for a in args])


def dvc_status(project: Path) -> str:
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    return subprocess.run([sys.executable, "-m", "dvc", "status"], cwd=project, env=env, capture_output=True,
                          text=True).stdout


@pytest.fixture(scope="module")
def folder(distill_folder):
    """20 images and a folder of 8 of their masks (4 validation, 4 test): tests/conftest.py."""
    return distill_folder


@pytest.fixture(scope="module")
def without_masks(distill_without_masks):
    """The project of ``geodistill distill`` (the command, run on the tests' second lane:
    tests/conftest.py) on the folder without masks."""
    out, res = distill_without_masks
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    return out


def test_distill_without_masks_fixed_tau_last_epoch_and_said_so(folder, without_masks, tmp_path):
    from pipeline.deploy.segmenter import Segmenter

    images, _ = folder
    out = without_masks
    deploy = json.loads((out / "artifacts" / "deploy" / "deploy.json").read_text())
    assert deploy["tau"] == 0.5 and "no validation masks" in deploy["tau_source"]
    thr = pd.read_parquet(out / "artifacts" / "thresholds.parquet")
    assert set(thr["method"]) == {"plain", "geodistill"} and (thr["tau"] == 0.5).all() and (thr["n_val"] == 0).all()
    report = (out / "reports" / "distill" / "report.md").read_text()
    assert "No validation or test masks were available" in report
    # what was not computed is said plainly; tau is called what it is; no nan shown as a result (issue 23)
    assert "Not computed: no validation or test masks" in report and "**Missing:" not in report
    assert "the fixed tau = 0.5" in report and "validation-calibrated" not in report
    assert not re.search(r"\bnan\b", report, re.I) and "Val Image IoU change" not in report
    # a good DVC citizen without git: `dvc plots show` shows the runs' DVCLive curves
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    r = subprocess.run([sys.executable, "-m", "dvc", "plots", "show", "-o", str(tmp_path / "p")], cwd=out, env=env,
                       capture_output=True, text=True)
    assert r.returncode == 0 and "training loss" in (tmp_path / "p" / "index.html").read_text(), r.stdout + r.stderr
    manifest = pd.read_parquet(out / "artifacts" / "manifest.parquet")
    assert (manifest["split"] == "train").all() and len(manifest) == 20
    for method in ("plain", "geodistill"):
        payload_log = pd.read_parquet(out / "artifacts" / "checkpoints" / method / "42" / "log.parquet")
        assert payload_log["val_iou"].isna().all()
    stages = yaml.safe_load((out / "dvc.yaml").read_text())["stages"]
    assert "evaluate" not in stages and "analyze_teacher" not in stages
    assert str(images.resolve()) in stages["prepare"]["deps"]
    code = [d for d in stages["prepare"]["deps"] if d.endswith(".py")]
    assert code and all(Path(d).is_absolute() and Path(d).is_file() for d in code)
    params = yaml.safe_load((out / "params.yaml").read_text())
    assert params["data"]["source"] == "folder" and params["teacher"]["backend"] == "sam3"
    assert params["train"]["epochs_stage1"] == 3 and params["protocol"]["runs"]["geodistill"] == [42]
    # the shipped recipe's resolution schedule ran end to end: 2 stable epochs at half the side, the decay at full
    stage_one = json.loads((out / "artifacts" / "checkpoints" / "plain" / "42" / catalog.META_FILE).read_text())["extra"]
    assert params["train"]["recipe"] == "progressive" and stage_one["low_res_epochs"] == 2
    assert stage_one["epochs"] == 3 and stage_one["steps_run"] == 3 * math.ceil(18 / params["train"]["batch_size"])
    # the bundle predicts at the original size
    img = sorted(images.iterdir())[1]
    mask = Segmenter.from_bundle(out / "artifacts" / "deploy").predict(img)
    assert mask.shape == cv2.imread(str(img), cv2.IMREAD_UNCHANGED).shape[:2] and mask.dtype == bool


def test_distill_rerun_resumes(folder, without_masks, tiny_sam3):  # noqa: F811
    images, _ = folder
    assert "up to date" in dvc_status(without_masks)
    before = (without_masks / "artifacts" / "checkpoints" / "geodistill" / "42" / "model.safetensors").stat().st_mtime_ns
    res = cli("distill", images, "--out", without_masks, "--checkpoint", tiny_sam3, *FAST)
    assert res.exit_code == 0, res.output[-3000:]
    assert (without_masks / "artifacts" / "checkpoints" / "geodistill" / "42" / "model.safetensors").stat().st_mtime_ns == before


def test_distill_with_validation_masks(folder, distill_with_masks):
    images, val = folder
    out, res = distill_with_masks  # the command with --val-masks, run on the tests' second lane
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    manifest = pd.read_parquet(out / "artifacts" / "manifest.parquet")
    assert manifest["split"].value_counts().to_dict() == {"train": 12, "val": 4, "test": 4}
    assert not set(manifest.loc[manifest["split"] == "train", "image_id"]) & {p.stem for p in val.iterdir()}
    thr = pd.read_parquet(out / "artifacts" / "thresholds.parquet")
    assert (thr["n_val"] == 4).all() and thr["val_iou"].notna().all()
    deploy = json.loads((out / "artifacts" / "deploy" / "deploy.json").read_text())
    assert deploy["tau_source"].startswith("calibrated on the validation split")
    assert len(pd.read_parquet(out / "artifacts" / "metrics.parquet")) > 0
    assert "No validation or test masks" not in (out / "reports" / "distill" / "report.md").read_text()
    # the summary ends with the deployed student's distillation efficiency (the report stage's DVC metrics)
    # (no ratio over a vote that found almost nothing: pipeline.orchestration.standalone.MIN_VOTE_IOU)
    from pipeline.orchestration.standalone import MIN_VOTE_IOU

    eff = json.loads((out / "reports" / "metrics" / "efficiency" / "test" / "geodistill.json").read_text())
    vote = json.loads((out / "reports" / "metrics" / "teacher" / "test.json").read_text())["iou"]
    if vote >= MIN_VOTE_IOU:
        assert f"distill: the student's test Image IoU is {eff['efficiency']:.2f} × the teacher vote's" in res.stderr
    else:
        assert "distill: no distillation efficiency" in res.stderr and f"{vote:.3f}" in res.stderr
    # and Stage I's length: the steps it ran and why it stopped (the plateau recipe stops there)
    meta = json.loads((out / "artifacts" / "checkpoints" / "plain" / "42" / "meta.json").read_text())["extra"]
    assert f"distill: Stage I trained {meta['steps_run']:,} optimizer steps" in res.stderr and meta["stopped"]


@pytest.mark.parametrize("case, message", [
    ("missing", "folder not found"),
    ("empty", "no images"),
    ("simulated", "SIMULATOR"),
    ("few_masks", "at least 2"),
    ("not_project", "params.yaml exists and was not written by geodistill distill"),
    ("no_teacher", "--checkpoint SAM3_DIR is required"),
    # the export stage would fail at the end of dvc repro: refused before anything runs
    ("export_seed", "deploy.export_seed=42: protocol.runs has no geodistill run with this seed"),
])
def test_distill_errors_are_one_line_exit_2(folder, tmp_path, tiny_sam3, case, message):  # noqa: F811
    images, val = folder
    empty = tmp_path / "empty"
    empty.mkdir()
    one = tmp_path / "one"
    one.mkdir()
    (one / "img00.png").write_bytes((val / "img00.png").read_bytes())
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "params.yaml").write_text("mine")  # the user's file where the project's would go
    ck = ["--checkpoint", tiny_sam3]
    out = ["--out", tmp_path / "o", "--no-run"]
    args = {"missing": [tmp_path / "nope", *out, *ck], "empty": [empty, *out, *ck],
            "simulated": [images, *out, "--backend", "simulated"],
            "few_masks": [images, *out, *ck, "--val-masks", one],
            "not_project": [images, "--out", busy, "--no-run", *ck], "no_teacher": [images, *out],
            "export_seed": [images, *out, *ck, "--set", "protocol.runs.plain=[43]",
                            "--set", "protocol.runs.geodistill=[43]"]}[case]
    res = cli("distill", *args)
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("geodistill distill: error:") and message in lines[0], res.output
    assert not (tmp_path / "o").exists() and (busy / "params.yaml").read_text() == "mine"
    assert sorted(p.name for p in busy.iterdir()) == ["params.yaml"]  # refused before anything was written
