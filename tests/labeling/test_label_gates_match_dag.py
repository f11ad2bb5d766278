"""One gate: ``geodistill label`` on a folder and the DAG's teacher -> consensus -> geometry stages on the
same images (all in the training split, the same teacher cache) give the same c, v, a, a0 and gates
(pipeline.pseudo_labels.reliability_gates; the a0 rule: docs/decisions.md, "The area reference a0")."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from pipeline.artifacts.lineage import make_meta
from pipeline.artifacts.store import open_artifact, write_parquet, write_zarr
from pipeline.datasets.loading import load_mask, load_rgb
from pipeline.pseudo_labels import reliability_gates
from pipeline.params import PAPER
from stages.consensus import main as consensus_main
from stages.geometry import main as geometry_main
from tests.builders.teacher import PARAMS, make_image_folder, run_stage

SIZE = 32
SETS = ["teacher.backend=simulated", f"data.resolution={SIZE}"]
GATES = ["c", "v", "a", "a0", "g_conf", "g_valid", "g_area", "g", "n_valid"]


def dag_artifacts(root, images, masks) -> dict[str, str]:
    """manifest (every image in the training split, sha256 of the file as label keys its cache),
    images.zarr and reference.zarr of the folder at the working resolution, read as label reads them."""
    files = sorted(images.glob("*.png"))
    loaded = [load_rgb(f, SIZE) for f in files]
    refs = [load_mask(masks / f.name, SIZE).array.astype(bool) for f in files]
    ids = [f.stem for f in files]
    df = pd.DataFrame({"image_id": ids, "dataset": "folder", "domain": "folder", "split": "train", "group": "train",
                       "spacecraft": "sc", "image_path": [str(f) for f in files], "mask_path": None,
                       "part_path": None, "width": SIZE, "height": SIZE, "sha256": [x.sha256 for x in loaded]})
    paths = {k: str(root / v) for k, v in dict(manifest="manifest.parquet", images="images.zarr",
                                                reference="reference.zarr", out="teacher.zarr",
                                                scores="teacher_scores.parquet").items()}
    meta = lambda schema: make_meta(schema, "prepare", "test", {})  # noqa: E731
    write_parquet(paths["manifest"], df, meta("manifest"))
    write_zarr(paths["images"], {"image": np.stack([x.array for x in loaded])}, meta("images"),
               attrs={"image_ids": ids})
    write_zarr(paths["reference"], {"mask": np.stack(refs), "has_mask": np.ones(len(ids), bool)},
               meta("reference"), attrs={"image_ids": ids})
    return paths


def test_label_and_the_geometry_stage_give_equal_gates(tmp_path):
    import pipeline

    images, masks = make_image_folder(tmp_path / "data", n=8)
    result = pipeline.label(images, out=tmp_path / "labels", backend="simulated", reference_masks=masks,
                            params=PARAMS, overrides=SETS, device="cpu", formats="png")
    cache = tmp_path / "labels" / ".cache" / "teacher"
    assert cache.is_dir()

    paths = dag_artifacts(tmp_path, images, masks)
    sets = SETS + [f"teacher.cache_dir={cache}"]
    assert run_stage(paths, cache, sets=sets).exit_code == 0
    common = ["--params", PARAMS, "--device", "cpu"] + [a for s in sets for a in ("--set", s)]
    cons = str(tmp_path / "consensus.zarr")
    res = CliRunner().invoke(consensus_main, common + ["--teacher", paths["out"], "--out", cons])
    assert res.exit_code == 0, res.output
    gates = str(tmp_path / "gates.parquet")
    res = CliRunner().invoke(geometry_main, common + ["--consensus", cons, "--manifest", paths["manifest"],
                                                      "--out", str(tmp_path / "geometry.zarr"), "--gates", gates])
    assert res.exit_code == 0, res.output

    label = result.table.set_index("image_id")[GATES]
    dag = open_artifact(gates, "gates").df.set_index("image_id")[GATES].loc[label.index]
    assert (label["a"] > 0).sum() >= 2 and label["g"].gt(0).any()  # a real median, real gates
    pd.testing.assert_frame_equal(label, dag, check_dtype=False, rtol=0, atol=0)


def test_a0_rule_training_split_non_empty_votes_and_what_a_missing_a0_gives():
    """a0 = median area over the training split's non-empty votes; with none, the gates of a0 = 0
    (g_area 1 on an empty mask, the floor on a non-empty one) and ``missing``."""
    geo = PAPER.geometry.model_dump()
    c, n_valid = np.array([0.9, 0.8, 0.0, 0.7]), np.array([6, 6, 0, 6])
    a = np.array([0.1, 0.3, 0.0, 0.5])
    gates = reliability_gates(c, n_valid, a, np.array([True, True, True, False]), geo)
    assert gates.a0 == pytest.approx(0.2) and not gates.missing   # median of 0.1 and 0.3: empty and val left out
    none = reliability_gates(c, n_valid, a, np.array([False, False, True, False]), geo)
    assert none.missing and none.a0 == 0.0
    assert none.factors.area[2] == 1.0 and np.allclose(none.factors.area[[0, 1, 3]], geo["area_floor"])
    assert none.factors.g[2] == 0.0
