"""Weights as safetensors + JSON (pipeline.artifacts.weights): what a checkpoint and a bundle hold, that the bytes are
the same for the same weights, and that checkpoints and bundles of older versions (one torch-pickle
``model.pt``) are still read by every reader: load_student, open_artifact, the Stage-II warm start, export
and the Segmenter."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from safetensors import safe_open

import pipeline
from pipeline import catalog
from pipeline.artifacts.store import open_artifact
from pipeline.runtime.errors import ArtifactError
from pipeline.evaluation.inference import load_student
from pipeline.artifacts.weights import read_weights, write_weights
from tests.builders.deploy import RES, make_checkpoint, run_export, tiny_model


@pytest.fixture(autouse=True)
def quiet(monkeypatch):
    monkeypatch.setenv("GEODISTILL_QUIET", "1")


def to_legacy(ckpt):
    """Rewrite a checkpoint/bundle directory the way older versions wrote it: one model.pt (torch.save of
    the payload dict), no safetensors, no model.json."""
    payload = read_weights(ckpt)
    (ckpt / catalog.WEIGHTS_FILE).unlink()
    (ckpt / catalog.WEIGHTS_CONFIG_FILE).unlink()
    torch.save(payload, ckpt / catalog.LEGACY_WEIGHTS_FILE)
    return ckpt


def test_checkpoint_is_safetensors_plus_json(tmp_path):
    model = tiny_model(3, geometry=True)
    ckpt = make_checkpoint(tmp_path / "ck", seed=3, geometry=True)
    assert not (ckpt / "model.pt").exists()
    with safe_open(ckpt / "model.safetensors", framework="pt") as f:      # a plain safetensors file
        keys = set(f.keys())
    assert keys == set(model.state_dict())                                  # mask path + geometry heads
    cfg = json.loads((ckpt / "model.json").read_text())
    assert cfg["config"] == json.loads(json.dumps(model.config)) and cfg["method"] == "geodistill"
    payload = read_weights(ckpt)
    for k, v in model.mask_path_state_dict().items():
        assert torch.equal(payload["state_dict"][k], v), k
    for k, v in model.geometry_heads.state_dict().items():
        assert torch.equal(payload["geometry_state_dict"][k], v), k
    assert payload["selected_epoch"] == 1 and payload["stage"] == 2


def test_same_weights_same_bytes(tmp_path):
    """Two writes of the same weights are byte-identical (the header's metadata is fixed)."""
    model = tiny_model(1)
    for d in ("a", "b", "c", "d"):
        (tmp_path / d).mkdir()
        write_weights(tmp_path / d, model.mask_path_state_dict(), model.config, None, tau=0.5, method="plain")
    for name in (catalog.WEIGHTS_FILE, catalog.WEIGHTS_CONFIG_FILE):
        assert len({(tmp_path / d / name).read_bytes() for d in ("a", "b", "c", "d")}) == 1, name


def test_missing_config_is_one_clear_error(tmp_path):
    ckpt = make_checkpoint(tmp_path / "ck")
    (ckpt / "model.json").unlink()
    with pytest.raises(ArtifactError, match="model.json"):
        load_student(ckpt)
    (ckpt / "model.safetensors").write_bytes(b"not a safetensors file")
    with pytest.raises(ArtifactError, match="model.safetensors"):
        load_student(ckpt)


def test_old_model_pt_checkpoint_is_still_read(tmp_path):
    """A checkpoint of an older version (model.pt only): it validates, loads to the same model, warm-starts
    Stage II, and exports to a bundle that carries safetensors."""
    from pipeline.training.inputs import load_init

    new = make_checkpoint(tmp_path / "new", seed=5, geometry=True)
    old = to_legacy(make_checkpoint(tmp_path / "old", seed=5, geometry=True))
    assert sorted(p.name for p in old.iterdir()) == ["log.parquet", "meta.json", "model.pt"]
    assert open_artifact(old, "checkpoint").meta.schema == "checkpoint"
    x = torch.rand(2, 3, RES, RES)
    with torch.no_grad():
        want = load_student(new)[0](x)
        model, payload = load_student(old)
        assert torch.equal(model(x), want)
    assert payload["method"] == "geodistill" and payload["geometry_state_dict"] is not None
    state, art = load_init(old)                                           # Stage-II warm start
    assert all(torch.equal(state[k], v) for k, v in load_init(new)[0].items())
    r = run_export(old, tmp_path / "deploy")
    assert r.exit_code == 0, r.output
    assert (tmp_path / "deploy" / "model.safetensors").is_file() and not (tmp_path / "deploy" / "model.pt").exists()


def test_old_model_pt_bundle_is_still_read(tmp_path):
    """A deploy bundle of an older version (model.pt, model.ts, deploy.json): validates and segments the
    same as the bundle it was made from."""
    ckpt = make_checkpoint(tmp_path / "ck")
    assert run_export(ckpt, tmp_path / "deploy").exit_code == 0
    img = (np.random.default_rng(0).random((40, 50, 3)) * 255).astype(np.uint8)
    want = pipeline.Segmenter.from_bundle(tmp_path / "deploy", engine="torch").predict(img)
    old = to_legacy(tmp_path / "deploy")
    assert open_artifact(old, "deploy").meta.schema == "deploy"
    got = pipeline.Segmenter.from_bundle(old, engine="torch").predict(img)
    assert got.shape == (40, 50) and np.array_equal(got, want)
