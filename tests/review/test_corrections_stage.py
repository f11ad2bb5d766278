"""The corrections stage and review.mode on the tiny artifacts: replace puts the corrected masks into the
targets (and marks the run NOT annotation-free), validate moves the images to validation, bad inputs
are one line with exit 2, and without review.corrections nothing changes (dvc.yaml included)."""

from __future__ import annotations

import shutil

import numpy as np
import pandas as pd
import pytest
import yaml
from click.testing import CliRunner

from pipeline import catalog
from pipeline.artifacts.lineage import make_meta
from pipeline.artifacts.store import open_artifact, write_parquet
from pipeline.augment import recompute_geometry
from pipeline.orchestration.dag import optional_stages_on, render_dvc_yaml
from pipeline.labeling.formats import rle_encode
from pipeline.methods import HUMAN_TARGETS_LABEL, get_method, run_annotation_free, run_label
from pipeline.training.inputs import load_inputs
from stages.corrections import main as corrections_main
from tests.builders.training import REPO, tiny_cfg


def _corrections(path, masks: dict, size=(32, 32)):
    rows = [{"image_id": iid, "file": f"{iid}.png", "width": size[1], "height": size[0],
             "rle": rle_encode(m)["counts"], "pixels": int(m.sum()), "source": "png", "iou_to_voted": 0.5,
             "rank": k + 1} for k, (iid, m) in enumerate(masks.items())]
    write_parquet(path, pd.DataFrame(rows), make_meta("corrections", "review import", "test", {"export_id": "x"}))
    return path


def _run(art, tmp_path, corrections, mode, source="synthetic", flag=True):
    params = tmp_path / "params.yaml"
    params.write_text((REPO / "params.yaml").read_text())
    return CliRunner().invoke(corrections_main, [
        "--params", str(params), "--set", f"review.corrections={corrections}", "--set", f"review.mode={mode}",
        "--set", f"review.human_targets={'true' if flag else 'false'}", "--set", f"data.source={source}",
        *(["--set", f"data.root={tmp_path}"] if source == "folder" else []),
        "--artifacts", str(art), "--out", str(catalog.path("corrected", art))])


@pytest.fixture()
def art(tiny, tmp_path):
    out = tmp_path / "artifacts"
    shutil.copytree(tiny, out)
    return out


def _truth(art):
    return np.asarray(open_artifact(catalog.path("reference", art), "reference")["mask"], bool)


def test_replace_puts_the_corrected_masks_into_the_targets(art, tmp_path):
    truth = _truth(art)
    fixed = {"img001": truth[1], "img002": truth[2]}
    res = _run(art, tmp_path, _corrections(tmp_path / "c.parquet", fixed), "replace")
    assert res.exit_code == 0, res.output
    corrected = open_artifact(catalog.path("corrected", art), "corrected")
    assert corrected.attrs["mode"] == "replace" and list(corrected["row"][:]) == [1, 2]
    cfg, review = tiny_cfg(), {"corrections": "c.parquet", "mode": "replace", "human_targets": True}
    before, _, opened0 = load_inputs(art, get_method("geodistill"), cfg)
    after, _, opened = load_inputs(art, get_method("geodistill"), cfg, review=review)
    assert sorted(a.meta.schema for a in opened) == sorted([a.meta.schema for a in opened0] + ["corrected"])
    voted = np.asarray(before.mask)
    for k, iid in enumerate(after.image_ids):
        want = fixed[iid] if iid in fixed else voted[k]
        assert np.array_equal(after.mask[k], want), iid
    k = after.image_ids.index("img001")
    assert not np.array_equal(voted[k], truth[1])  # the test would not notice a no-op otherwise
    sdf, skel, area = recompute_geometry(truth[1], after.geometry)
    assert np.array_equal(after.sdf[k], sdf) and np.array_equal(after.skeleton[k], skel)
    assert after.gate[k] == 1.0 and after.area[k] == pytest.approx(area)
    assert after.stats["human_corrections"] == 2 and after.stats["annotation_free"] is False
    plain = get_method("plain")
    assert not run_annotation_free(plain, review) and run_label(plain, review).endswith(HUMAN_TARGETS_LABEL)
    assert run_annotation_free(plain, {**review, "mode": "validate"}) and run_label(plain, None) == plain.label


def test_validate_moves_the_corrected_images_to_validation(art, tmp_path):
    truth = _truth(art)
    res = _run(art, tmp_path, _corrections(tmp_path / "c.parquet", {"img003": truth[3]}), "validate",
               source="folder", flag=False)
    assert res.exit_code == 0, res.output
    review = {"corrections": "c.parquet", "mode": "validate", "human_targets": False}
    data0, val0, _ = load_inputs(art, get_method("plain"), tiny_cfg())
    data, val, _ = load_inputs(art, get_method("plain"), tiny_cfg(), review=review)
    assert "img003" in data0.image_ids and "img003" not in data.image_ids and len(data) == len(data0) - 1
    assert val.image_ids == val0.image_ids + ["img003"] and np.array_equal(val.masks[-1], truth[3])
    assert data.stats.get("annotation_free", True) and run_annotation_free(get_method("plain"), review)
    # the corrected artifact was written for validate: a params file now saying replace is refused
    with pytest.raises(Exception, match="rerun the corrections stage"):
        load_inputs(art, get_method("plain"), tiny_cfg(), review={**review, "mode": "replace"})


@pytest.mark.parametrize("case, words", [
    ("unknown", "unknown image 'nope'"), ("size", "differs from the manifest's 32x32"),
    ("val", "is a 'val' image"), ("benchmark", "spacecraft-disjoint"), ("flag", "human_targets"),
])
def test_bad_corrections_are_one_line_exit_2(art, tmp_path, case, words):
    m = _truth(art)[1]
    masks, size, mode, source, flag = {"img001": m}, (32, 32), "replace", "synthetic", True
    if case == "unknown":
        masks = {"nope": m}
    elif case == "size":
        masks, size = {"img001": np.pad(m, ((0, 0), (0, 1)))}, (32, 33)
    elif case == "val":
        masks = {"img009": m}
    elif case == "benchmark":
        mode = "validate"
    elif case == "flag":
        flag = False
    res = _run(art, tmp_path, _corrections(tmp_path / "c.parquet", masks, size), mode, source, flag)
    assert res.exit_code == 2 and words in res.output and len(res.output.strip().splitlines()) == 1, res.output
    assert not catalog.path("corrected", art).exists()


def test_the_stage_is_in_dvc_yaml_only_when_review_corrections_is_set():
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    assert optional_stages_on(params) == ()  # the demo: dvc.yaml as committed (test_params_and_dag)
    on = optional_stages_on({**params, "review": {**params["review"], "corrections": "artifacts/c.parquet"}})
    doc = yaml.safe_load(render_dvc_yaml(optional=on))["stages"]
    assert "corrections" in doc and "corrections" not in yaml.safe_load(render_dvc_yaml())["stages"]
    assert "${review.corrections}" in doc["corrections"]["deps"]
    assert catalog.dvc_path("corrected") in doc["train_plain"]["deps"]
    assert "review.mode" in doc["train_plain"]["params"]
