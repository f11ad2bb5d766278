"""The DAG side of the human loop: consensus.zarr records the prompt disagreement h that label records,
and the stage ``review_export`` writes artifacts/review/ through the same ranking and format functions
as ``geodistill review export``."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from pipeline.artifacts.lineage import make_meta
from pipeline.artifacts.store import open_artifact
from pipeline.consensus import vote_batch
from pipeline.pseudo_labels import write_consensus
from pipeline.consensus import agreement_entropy
from pipeline.review.export import CVAT_COCO, LS_TASKS, OUTPUTS, export_run, run_table
from pipeline.review.ranking import rank

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def run_artifacts(tiny, tmp_path_factory) -> Path:
    """The tiny artifacts' manifest and gates with a consensus.zarr written by the consensus stage's function."""
    art = tmp_path_factory.mktemp("review_run")
    for name in ("manifest.parquet", "gates.parquet"):
        shutil.copy(tiny / name, art / name)
    write_consensus(open_artifact(tiny / "teacher.zarr", "teacher"), 0.5, art / "consensus.zarr",
                    lambda schema: make_meta(schema, "consensus", "test", {"consensus.vote_threshold": 0.5}))
    return art


def test_consensus_records_the_label_disagreement(tiny, run_artifacts):
    cons = open_artifact(run_artifacts / "consensus.zarr", "consensus")
    teacher = open_artifact(tiny / "teacher.zarr", "teacher")
    ref = vote_batch(teacher.numpy("masks"), teacher.numpy("scores"), 0.5)
    np.testing.assert_array_equal(cons.numpy("agreement"), ref.agreement)   # the other arrays are untouched
    np.testing.assert_array_equal(cons.numpy("voted"), ref.voted)
    np.testing.assert_array_equal(cons.numpy("n_valid"), ref.n_valid)
    h = cons.numpy("h")
    assert h.shape == (len(ref.agreement),) and (h > 0).any()
    np.testing.assert_array_equal(h, agreement_entropy(ref.agreement))   # label's statistic, same map
    assert h[3] == agreement_entropy(ref.agreement[3])


def _check_export(out: Path, manifest, cons, gates, top: int, ranking: str) -> pd.DataFrame:
    expected = rank(run_table(manifest.df, gates.df, cons.numpy("h")), ranking, top)
    train = manifest.df.loc[manifest.df["split"] == "train", "image_id"].tolist()
    assert set(expected["image_id"]) <= set(train) and len(expected) == min(top, len(train))
    csv = pd.read_csv(out / OUTPUTS["csv"])
    assert csv["image_id"].tolist() == expected["image_id"].tolist()
    assert csv["rank"].tolist() == list(range(1, len(expected) + 1))
    np.testing.assert_allclose(csv["h"], expected["h"], rtol=1e-5)
    tasks = json.loads((out / OUTPUTS["labelstudio"] / LS_TASKS).read_text())
    assert [t["data"]["image_id"] for t in tasks] == expected["image_id"].tolist()
    coco = json.loads((out / OUTPUTS["cvat"] / CVAT_COCO).read_text())
    assert [im["file_name"] for im in coco["images"]] == expected["file"].tolist()
    record = json.loads((out / OUTPUTS["record"]).read_text())
    assert record["complete"] and [r["image_id"] for r in record["images"]] == expected["image_id"].tolist()
    # the voted mask at the image's own size (the tiny images are at the working resolution already)
    row = manifest.df.index[manifest.df["image_id"] == expected["image_id"][0]][0]
    ann = [a for a in coco["annotations"] if a["image_id"] == 1]
    assert ann and ann[0]["area"] == int(cons.numpy("voted")[row].sum())
    return expected


def test_review_export_stage_function_and_cli(run_artifacts, tmp_path):
    manifest, cons, gates = (open_artifact(run_artifacts / f, n) for f, n in (
        ("manifest.parquet", "manifest"), ("consensus.zarr", "consensus"), ("gates.parquet", "gates")))
    res = export_run(manifest, cons, gates, tmp_path / "fn", top=5, ranking="gate")
    expected = _check_export(tmp_path / "fn", manifest, cons, gates, 5, "gate")
    assert res.table["image_id"].tolist() == expected["image_id"].tolist()
    assert expected["image_id"][0] == "img000"   # g = 0: the gate ranking puts it first

    from stages.review_export import main

    out = tmp_path / "cli"
    r = CliRunner().invoke(main, ["--artifacts", str(run_artifacts), "--out", str(out), "--params",
                                  str(ROOT / "params.yaml")], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    _check_export(out, manifest, cons, gates, 50, "combined")   # params.yaml's review.top / review.ranking
    first = (out / OUTPUTS["labelstudio"] / LS_TASKS).read_bytes()
    r = CliRunner().invoke(main, ["--artifacts", str(run_artifacts), "--out", str(out), "--params",
                                  str(ROOT / "params.yaml")], catch_exceptions=False)
    assert r.exit_code == 0 and (out / OUTPUTS["labelstudio"] / LS_TASKS).read_bytes() == first   # deterministic


def test_review_params_name_the_rankings_the_stage_can_run():
    from typing import get_args

    from pipeline.params import ReviewParams
    from pipeline.review.ranking import DEFAULT_RANKING, RANKINGS, STUDENT_COLUMN

    choices = set(get_args(ReviewParams.model_fields["ranking"].annotation))
    assert choices == {n for n, r in RANKINGS.items() if STUDENT_COLUMN not in r.needs}   # no student in the DAG
    assert ReviewParams().ranking == DEFAULT_RANKING
