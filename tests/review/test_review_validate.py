"""Human corrections past training: in ``review.mode: validate`` calibrate reads the corrected training
images as validation images (and says so), in ``replace`` mode every report label marks the runs NOT
annotation-free; without corrections neither changes anything (dvc.yaml included)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import yaml

from pipeline import catalog
from pipeline.artifacts.lineage import make_meta
from pipeline.artifacts.store import open_artifact, write_zarr
from pipeline.orchestration.dag import optional_stages_on, render_dvc_yaml
from pipeline.evaluation.inference import CORRECTED_VALIDATION, save_checkpoint
from pipeline.methods import HUMAN_TARGETS_LABEL, get_method
from pipeline.report import tables as T
from pipeline.report.build import Inputs, corrections_note, load_inputs, recorded_review, threshold_section
from pipeline.report.document import Table
from pipeline.review.apply import write_corrected
from tests.builders.evaluation import build_tiny_artifacts, invoke, write_params
from tests.builders.training import REPO

FIXED = ("train_s0_v1", "train_s2_v0")  # training images of tests/builders/evaluation.py's manifest


@pytest.fixture(scope="module")
def art(tmp_path_factory):
    art = build_tiny_artifacts(tmp_path_factory.mktemp("review_validate") / "artifacts", methods=("plain",), seeds=(1,))
    manifest = open_artifact(catalog.path("manifest", art), "manifest").df
    rows = np.array([int(np.flatnonzero(manifest["image_id"] == i)[0]) for i in FIXED])
    truth = np.asarray(open_artifact(catalog.path("reference", art), "reference")["mask"], bool)
    meta = make_meta("corrected", "corrections", "test", {})
    write_corrected(catalog.path("corrected", art), list(FIXED), rows, ~truth[rows], "validate", meta)
    return art


def _calibrate(art, tmp_path, *sets):
    from stages.calibrate import main as calibrate

    out = tmp_path / f"thresholds{len(sets)}.parquet"
    res = invoke(calibrate, ["--params", str(write_params(tmp_path / "params.yaml")), *sets, "--artifacts", str(art),
                             "--checkpoints", str(art / "checkpoints"), "--out", str(out)])
    return res, out


VALIDATE = ("--set", "review.corrections=c.parquet", "--set", "review.mode=validate")


def test_calibrate_reads_the_corrected_images_as_validation_images(art, tmp_path):
    res0, out0 = _calibrate(art, tmp_path)
    res, out = _calibrate(art, tmp_path, *VALIDATE)
    assert res0.exit_code == 0 and res.exit_code == 0, res0.output + res.output
    before, after = open_artifact(out0, "thresholds"), open_artifact(out, "thresholds")
    n_val = int(before.df["n_val"].iloc[0])
    assert int(after.df["n_val"].iloc[0]) == n_val + len(FIXED)
    # the corrected masks (here inverted references) are what tau was calibrated on: the curve moves
    assert not np.allclose(before.df["curve"].iloc[0], after.df["curve"].iloc[0])
    assert after.meta.extra[CORRECTED_VALIDATION] == len(FIXED)
    assert CORRECTED_VALIDATION not in (before.meta.extra or {})  # default: the artifact as before
    assert str(catalog.path("corrected", art)) in {i["path"] for i in after.meta.inputs}
    assert str(catalog.path("corrected", art)) not in {i["path"] for i in before.meta.inputs}
    # the report: tau was calibrated (on the corrected masks) even where no reference mask is a validation mask
    inp = Inputs(art, {"thresholds": after}, {}, no_masks=True, corrected_validation=len(FIXED))
    blocks = threshold_section(inp, {}).blocks
    assert any(isinstance(b, Table) and b.key == "tab:thresholds" for b in blocks)
    assert "validation images" in corrections_note(inp) and "NOT annotation-free" not in corrections_note(inp)
    assert not any("fixed tau" in getattr(b, "text", "") for b in blocks)


def _linked_artifacts(art, tmp_path, names):
    """A new artifacts folder beside the test's, with ``names`` linked to the test's own."""
    other = tmp_path / "artifacts"
    other.mkdir()
    for name in names:
        catalog.path(name, other).symlink_to(catalog.path(name, art))
    return other


def test_corrections_calibrate_a_folder_without_validation_masks(art, tmp_path):
    other = _linked_artifacts(art, tmp_path, ("manifest", "images", "checkpoints", "corrected"))
    ref = open_artifact(catalog.path("reference", art), "reference")
    split = open_artifact(catalog.path("manifest", art), "manifest").df["split"].to_numpy()
    write_zarr(catalog.path("reference", other), {"mask": np.asarray(ref["mask"]), "has_mask": split != "val"},
               make_meta("reference", ref.meta.stage, "test", {}), {"image_ids": list(ref.attrs["image_ids"])})
    res0, out0 = _calibrate(other, tmp_path)
    res, out = _calibrate(other, tmp_path, *VALIDATE)
    assert res0.exit_code == 0 and res.exit_code == 0, res0.output + res.output
    assert open_artifact(out0, "thresholds").df["n_val"].tolist() == [0]  # the fixed tau, as before
    after = open_artifact(out, "thresholds").df
    assert after["n_val"].tolist() == [len(FIXED)] and "curve" in after.columns


def test_calibrate_refuses_corrections_written_for_the_other_mode(art, tmp_path):
    other = _linked_artifacts(art, tmp_path, ("manifest", "images", "reference", "checkpoints"))
    corrected = open_artifact(catalog.path("corrected", art), "corrected")
    write_corrected(catalog.path("corrected", other), list(FIXED), np.asarray(corrected["row"]),
                    np.asarray(corrected["mask"]), "replace", make_meta("corrected", "corrections", "test", {}))
    res, out = _calibrate(other, tmp_path, *VALIDATE)
    assert res.exit_code == 2 and "rerun the corrections stage" in res.output
    assert len(res.output.strip().splitlines()) == 1 and not out.exists(), res.output


def test_calibrate_reads_the_corrections_in_dvc_yaml_only_when_they_are_set():
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    default = yaml.safe_load(render_dvc_yaml())["stages"]["calibrate"]
    on = optional_stages_on({**params, "review": {**params["review"], "corrections": "artifacts/c.parquet"}})
    calibrate = yaml.safe_load(render_dvc_yaml(optional=on))["stages"]["calibrate"]
    corrected = catalog.dvc_path("corrected")
    assert corrected in calibrate["deps"] and corrected not in default["deps"]
    assert {"review.corrections", "review.mode"} <= set(calibrate["params"])
    assert not any(p.startswith("review.") for p in default["params"])


def _human_trained_checkpoint(art, method="plain", seed=7, n=3):
    from pipeline.model import TinyUNet

    meta = make_meta("checkpoint", "train", "test", {}, annotation_free=False, corrections_mode="replace",
                     human_corrections=n)
    log = pd.DataFrame({"epoch": [1], "stage": [1], "loss": [0.5], "val_iou": [0.5], "val_bf1": [0.5], "lr": [1e-3]})
    save_checkpoint(art / "checkpoints" / method / str(seed), TinyUNet(channels=(4, 8, 8)), meta, log,
                    method=method, seed=seed, stage=1, selected_epoch=1)


def test_every_report_label_marks_runs_trained_on_corrections(tmp_path):
    art = build_tiny_artifacts(tmp_path / "artifacts", methods=("geodistill",), seeds=(1,))
    assert recorded_review(art / "checkpoints") == {}  # annotation-free runs: labels as before
    _human_trained_checkpoint(art)
    review = recorded_review(art / "checkpoints")
    assert review == {"plain": {"corrections": 3, "mode": "replace"}}
    plain, geo, ceiling = (get_method(m).label for m in ("plain", "geodistill", "supervised_ceiling"))
    thr = pd.DataFrame({"method": ["plain", "geodistill"], "seed": [7, 1], "tau": [0.5, 0.45],
                        "val_iou": [0.6, 0.7], "fixed_val_iou": [0.55, 0.65], "n_val": [4, 4]})
    assert T.label("plain") == plain
    with T.human_trained(review):
        assert T.label("plain") == f"{plain} {HUMAN_TARGETS_LABEL}"
        assert T.label("geodistill") == geo and T.label("supervised_ceiling") == ceiling
        table = T.thresholds_table(thr, 0.5)
    assert T.label("plain") == plain  # outside the block: as before
    assert [r[0] for r in table.rows] == [geo, f"{plain} {HUMAN_TARGETS_LABEL}"]
    inp = load_inputs(art)
    assert inp.run_review == review and inp.corrected_validation == 0
    note = corrections_note(inp)
    assert note is not None and "NOT annotation-free" in note and "validation images" not in note
