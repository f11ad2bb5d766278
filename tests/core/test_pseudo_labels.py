"""The consensus and geometry stages' work called directly (pipeline.pseudo_labels), and the stages as
wiring: the CLI writes what the library writes, whatever the block size."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from pipeline.artifacts.lineage import make_meta
from pipeline.artifacts.store import open_artifact, write_zarr
from pipeline.consensus import vote
from pipeline.runtime.errors import InputError
from pipeline.geometry import image_gates
from pipeline.params import PAPER, load_params, section
from pipeline.pseudo_labels import write_consensus, write_geometry
from stages.consensus import main as consensus_main
from stages.geometry import main as geometry_main
from tests.builders.teacher import PARAMS, build_artifacts, run_stage


def _meta(schema):
    return make_meta(schema, "test", "test", {})


@pytest.fixture(scope="module")
def teacher(tmp_path_factory):
    """The tiny teacher artifacts (tests/builders/teacher.py) and their paths."""
    root = tmp_path_factory.mktemp("pseudo")
    paths = build_artifacts(root, n=8)
    assert run_stage(paths, root / "cache").exit_code == 0
    return root, paths


def _cli(main, *args):
    r = CliRunner().invoke(main, ["--params", PARAMS, *map(str, args)], catch_exceptions=False)
    assert r.exit_code == 0, r.output


def test_consensus_is_the_vote_of_every_image_in_any_block_size(teacher, tmp_path):
    root, paths = teacher
    t = open_artifact(paths["out"], "teacher")
    write_consensus(t, 0.5, tmp_path / "c1.zarr", _meta, chunk_images=3)
    c = open_artifact(tmp_path / "c1.zarr", "consensus")
    for i in range(8):
        one = vote(t.numpy("masks")[i], t.numpy("scores")[i], 0.5)
        np.testing.assert_array_equal(c.numpy("voted")[i], one.voted)
        np.testing.assert_array_equal(c.numpy("agreement")[i], one.agreement)
        assert c.numpy("n_valid")[i] == one.n_valid
    assert c.attrs["prompts"] == t.attrs["prompts"] and c.attrs["image_ids"] == t.attrs["image_ids"]
    _cli(consensus_main, "--teacher", paths["out"], "--out", tmp_path / "c2.zarr", "--chunk-images", 32)
    staged = open_artifact(tmp_path / "c2.zarr", "consensus")
    for name in ("agreement", "voted", "n_valid"):
        np.testing.assert_array_equal(staged.numpy(name), c.numpy(name))


def test_geometry_targets_and_gates_match_the_stage_in_any_block_size(teacher, tmp_path):
    root, paths = teacher
    write_consensus(open_artifact(paths["out"], "teacher"), 0.5, tmp_path / "c.zarr", _meta)
    cons, man = open_artifact(tmp_path / "c.zarr", "consensus"), open_artifact(paths["manifest"], "manifest")
    cfg = section(load_params(PARAMS), "geometry")
    table = write_geometry(cons, man, cfg, tmp_path / "g.zarr", tmp_path / "gates.parquet", _meta, chunk_images=3)
    geo = open_artifact(tmp_path / "g.zarr", "geometry")
    voted = cons.numpy("voted")
    assert ((geo.numpy("sdf") > 0) == voted).all()  # eq:sdf-target: the sign of D agrees with M
    assert not (geo.numpy("skeleton") & ~voted).any()  # K inside M
    v, gf = image_gates(table["c"].to_numpy(), cons.numpy("n_valid"), table["a"].to_numpy(), table["a0"].iloc[0], cfg)
    np.testing.assert_array_equal(table["g"].to_numpy(), gf.g)
    assert table["image_id"].tolist() == man.df["image_id"].tolist()
    assert open_artifact(tmp_path / "gates.parquet", "gates").df.equals(table)

    _cli(geometry_main, "--consensus", tmp_path / "c.zarr", "--manifest", paths["manifest"],
         "--out", tmp_path / "g2.zarr", "--gates", tmp_path / "gates2.parquet")
    staged = open_artifact(tmp_path / "g2.zarr", "geometry")
    for name in ("sdf", "skeleton"):
        np.testing.assert_array_equal(staged.numpy(name), geo.numpy(name))
    assert open_artifact(tmp_path / "gates2.parquet", "gates").df.equals(table)


def test_geometry_refuses_a_count_of_valid_prompts_beyond_the_prompts(teacher, tmp_path):
    root, paths = teacher
    write_consensus(open_artifact(paths["out"], "teacher"), 0.5, tmp_path / "c.zarr", _meta)
    cons = open_artifact(tmp_path / "c.zarr", "consensus")
    bad = cons.numpy("n_valid").copy()
    bad[0] = len(PAPER.teacher.prompts) + 1
    write_zarr(tmp_path / "bad.zarr", {"agreement": cons.numpy("agreement"), "voted": cons.numpy("voted"),
                                       "n_valid": bad}, _meta("consensus"), attrs=dict(cons.attrs))
    with pytest.raises(InputError, match="n_valid outside"):
        write_geometry(open_artifact(tmp_path / "bad.zarr", "consensus"), open_artifact(paths["manifest"], "manifest"),
                       section(load_params(PARAMS), "geometry"), tmp_path / "g.zarr", tmp_path / "gates.parquet", _meta)
