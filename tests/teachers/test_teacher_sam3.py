"""SAM 3 backend, offline and for real: a tiny randomly initialised SAM 3 (the small Sam3Config of
transformers' own tests) plus a CLIP tokenizer built from a vocabulary written here, saved with
save_pretrained and loaded through the backend."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

pytest.importorskip("transformers")

from pipeline.runtime.errors import InputError  # noqa: E402
from pipeline.params import PAPER_PROMPTS  # noqa: E402
from pipeline.teachers.base import TeacherInput  # noqa: E402
from pipeline.teachers.sam3 import Sam3Teacher, check_checkpoint_dir  # noqa: E402

PROMPTS = PAPER_PROMPTS


@pytest.fixture(scope="module")
def ckpt(tiny_sam3):
    """The session's tiny random SAM 3 (tests/conftest.py), whose vocabulary holds the paper's prompts."""
    return tiny_sam3


@pytest.fixture(scope="module")
def items():
    rng = np.random.default_rng(0)
    out = []
    for i in range(3):
        img = np.full((40, 40, 3), 15, np.uint8)
        y, x = rng.integers(5, 25, size=2)
        img[y:y + 12, x:x + 10] = rng.integers(120, 255, size=3)
        img += rng.integers(0, 20, size=img.shape, dtype=np.uint8)
        out.append(TeacherInput(f"img{i}", f"sha{i}", img))
    return out


def test_batched_prompts_equal_one_prompt_at_a_time(ckpt, items):
    teacher = Sam3Teacher(ckpt, device="cpu", batch_size=3, resolution=(40, 40), score_threshold=0.0)
    masks, scores = teacher.predict(items, PROMPTS)
    assert masks.shape == (3, 6, 40, 40) and masks.dtype == bool
    assert scores.shape == (3, 6) and scores.dtype == np.float32
    ref_masks, ref_scores = teacher.predict_one_prompt_at_a_time(items, PROMPTS)
    np.testing.assert_allclose(scores, ref_scores, rtol=1e-5, atol=1e-6)
    assert (masks != ref_masks).mean() < 1e-3  # identical up to pixels exactly at the threshold
    # the answers depend on the image and the prompt (so a mix-up of the batch order would show)
    assert np.unique(scores.round(5)).size > 6
    assert len({m.tobytes() for m in masks.reshape(18, -1)}) > 6
    assert masks.any() and not masks.all()
    # image batch size does not change the answers
    m1, s1 = Sam3Teacher(ckpt, device="cpu", batch_size=1, resolution=(40, 40), score_threshold=0.0).predict(items, PROMPTS)
    np.testing.assert_allclose(s1, scores, rtol=1e-5, atol=1e-6)
    assert "torchvision" not in sys.modules


def test_encoders_run_once(ckpt, items, monkeypatch):
    teacher = Sam3Teacher(ckpt, device="cpu", batch_size=2, resolution=(40, 40), score_threshold=0.0)
    model = teacher.load()
    calls = {"text": 0, "vision": 0}
    for name, key in (("get_text_features", "text"), ("get_vision_features", "vision")):
        orig = getattr(model, name)

        def wrapped(*a, _orig=orig, _key=key, **kw):
            calls[_key] += 1
            return _orig(*a, **kw)

        monkeypatch.setattr(model, name, wrapped)
    teacher.predict(items, PROMPTS)
    teacher.predict(items[:1], PROMPTS)
    assert calls == {"text": 1, "vision": 3}  # text once per run; vision once per image batch (2 + 1)


def test_compile_wraps_the_vision_encoder_with_torch_compile(ckpt, monkeypatch):
    """``teacher.compile: true`` reaches ``torch.compile(model.vision_encoder)`` in load() (a NameError
    once, found on a GPU only): on a CPU the constructor turns compile off, so the test turns it back on
    after the device check and records torch.compile's calls (returning the module unchanged)."""
    import torch

    calls = []

    def record(module, *args, **kwargs):
        calls.append((module, args, kwargs))
        return module

    monkeypatch.setattr(torch, "compile", record)
    assert Sam3Teacher(ckpt, device="cpu", compile=True).compile is False  # the device check: CUDA only
    teacher = Sam3Teacher(ckpt, device="cpu", compile=True)
    teacher.compile = True  # as on a CUDA device
    model = teacher.load()
    assert len(calls) == 1
    module, args, kwargs = calls[0]
    assert module is model.vision_encoder and type(module).__name__ == "Sam3VisionModel" and not args and not kwargs
    assert teacher.load() is model and len(calls) == 1  # loaded (and compiled) once
    assert Sam3Teacher(ckpt, device="cpu").load() is not None and len(calls) == 1  # off by default


def test_score_threshold_marks_prompts_invalid(ckpt, items):
    base = Sam3Teacher(ckpt, device="cpu", resolution=(40, 40), score_threshold=0.0)
    _, raw = base.predict(items, PROMPTS)
    thr = float(np.median(raw))
    masks, scores = Sam3Teacher(ckpt, device="cpu", resolution=(40, 40), score_threshold=thr).predict(items, PROMPTS)
    invalid = raw <= thr
    assert invalid.any() and (~invalid).any()
    assert (scores[invalid] == 0).all() and not masks[invalid].any()
    np.testing.assert_allclose(scores[~invalid], raw[~invalid], rtol=1e-5)


def test_bf16_runs_and_fingerprint_differs(ckpt, items):
    t32 = Sam3Teacher(ckpt, device="cpu", dtype="fp32", resolution=(40, 40))
    t16 = Sam3Teacher(ckpt, device="cpu", dtype="bf16", resolution=(40, 40), score_threshold=0.0)
    masks, scores = t16.predict(items[:2], PROMPTS)
    assert masks.shape == (2, 6, 40, 40) and np.isfinite(scores).all()
    f32, f16 = t32.fingerprint(), t16.fingerprint()
    assert f32["checkpoint"] == f16["checkpoint"] and f32["dtype"] != f16["dtype"]


def test_checkpoint_hash_is_memoised_until_a_file_changes(tmp_path, ckpt, monkeypatch):
    import os
    import shutil

    from pipeline.teachers import sam3

    copy = shutil.copytree(ckpt, tmp_path / "ckpt")
    memo = tmp_path / "cache" / "checkpoint_hashes.json"
    first = sam3.memoised_checkpoint_hash(copy, memo)
    assert first == sam3.checkpoint_hash(copy) and memo.exists()
    real = sam3.checkpoint_hash

    def no_rehash(directory):
        raise AssertionError("unchanged checkpoint was read again")
    monkeypatch.setattr(sam3, "checkpoint_hash", no_rehash)
    assert sam3.memoised_checkpoint_hash(copy, memo) == first
    assert Sam3Teacher(copy, device="cpu", hash_memo=memo).fingerprint()["checkpoint"] == first
    monkeypatch.setattr(sam3, "checkpoint_hash", real)
    # a changed file (new size and mtime) is hashed again and changes the key
    with open(copy / "config.json", "a") as f:
        f.write(" ")
    os.utime(copy / "config.json", ns=(1, 1))
    second = sam3.memoised_checkpoint_hash(copy, memo)
    assert second != first and second == real(copy)
    # an unreadable memo is ignored, not an error
    memo.write_text("{not json")
    assert sam3.memoised_checkpoint_hash(copy, memo) == second


def test_not_a_checkpoint_is_an_input_error(tmp_path, ckpt):
    with pytest.raises(InputError, match="directory not found"):
        check_checkpoint_dir(tmp_path / "missing")
    with pytest.raises(InputError, match="no config.json"):
        check_checkpoint_dir(tmp_path)
    (tmp_path / "config.json").write_text(json.dumps({"model_type": "sam2"}))
    with pytest.raises(InputError, match="not a SAM 3 checkpoint"):
        check_checkpoint_dir(tmp_path)
    assert check_checkpoint_dir(ckpt) == ckpt


def test_stage_with_sam3_backend(ckpt, tmp_path, monkeypatch):
    from pipeline.artifacts.store import open_artifact
    from tests.builders.teacher import build_artifacts, cache_files, run_stage

    monkeypatch.setenv("GEODISTILL_QUIET", "1")
    paths = build_artifacts(tmp_path / "a", n=4)
    sets = ["teacher.backend=sam3", f"teacher.checkpoint={ckpt}", "teacher.score_threshold=0.0"]
    r = run_stage(paths, tmp_path / "cache", sets=sets)
    assert r.exit_code == 0, r.output
    t = open_artifact(paths["out"], "teacher")
    assert t.attrs["backend"] == "sam3" and t.attrs["simulator"] is False
    assert t.numpy("masks").shape == (4, 6, 32, 32) and t.numpy("vflip_masks").shape == (4, 32, 32)
    assert "reference" not in {i["path"].split("/")[-1].split(".")[0] for i in t.meta.inputs}
    n_entries = len(cache_files(tmp_path / "cache"))
    assert n_entries == 4 * 7
    r = run_stage(paths, tmp_path / "cache", sets=sets)
    assert r.exit_code == 0 and len(cache_files(tmp_path / "cache")) == n_entries


def test_first_self_attention_runs_once_per_image_with_the_same_answers(ckpt, items, monkeypatch):
    """The DETR encoder's first self-attention sees the image only, so it runs on one row per image (its
    q_proj sees 3 rows for 3 images x 6 prompts; the cross-attention after it sees 18) and the answers equal those of the
    model run as transformers runs it, once per (image, prompt)."""
    import contextlib

    from pipeline.teachers import sam3

    teacher = Sam3Teacher(ckpt, device="cpu", batch_size=3, resolution=(40, 40), score_threshold=0.0)
    layers = teacher.load().detr_encoder.layers
    rows = {"self": [], "cross": []}
    hooks = [getattr(layers[0], f"{k}_attn").q_proj.register_forward_hook(
        lambda mod, args, out, k=k: rows[k].append(args[0].shape[0])) for k in rows]
    try:
        masks, scores = teacher.predict(items, PROMPTS)
        assert rows == {"self": [3], "cross": [18]}, rows
        monkeypatch.setattr(sam3, "first_self_attention_once_per_image", lambda model, copies: contextlib.nullcontext())
        ref_masks, ref_scores = teacher.predict(items, PROMPTS)
        assert rows == {"self": [3, 18], "cross": [18, 18]}, rows
    finally:
        for h in hooks:
            h.remove()
    np.testing.assert_array_equal(masks, ref_masks)
    np.testing.assert_allclose(scores, ref_scores, rtol=1e-6, atol=1e-7)
    assert "forward" not in vars(layers[0].self_attn)  # unwrapped after the call
