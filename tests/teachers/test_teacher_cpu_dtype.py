"""``teacher.dtype: auto`` on a CPU follows a rule on its flags (never a timing probe): bf16 where the CPU has
native bf16 units that pay off (AMX; avx512_bf16 from a vendor measured to gain), fp32 elsewhere; the dtype is in the fingerprint, so a changed ``auto``
makes CPU caches miss (and says so) while a pinned fp32 keeps them; and the fidelity gate's arithmetic."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.bench_teacher import fidelity
from pipeline.metrics import image_ious
from pipeline.runtime import device
from pipeline.teachers.sam3 import TEXT_MAX_LENGTH, Sam3Teacher, resolve_teacher_dtype

pytest.importorskip("transformers")


@pytest.mark.parametrize("flags, vendor, isa, expect", [
    ({"avx2", "fma"}, "GenuineIntel", None, "fp32"),                   # AVX2 only: bf16 would be emulated
    ({"avx2", "avx512f", "avx512_bf16"}, "AuthenticAMD", None, "bf16"),  # avx512_bf16 on the EPYC
    ({"avx2", "avx512f", "avx512_bf16"}, "GenuineIntel", None, "fp32"),  # Intel without AMX: 1.33x fp32's time
    ({"avx2", "avx512f", "avx512_bf16", "amx_tile", "amx_bf16"}, "GenuineIntel", None, "bf16"),  # AMX
    ({"avx2", "avx512f", "avx512_bf16", "amx_tile", "amx_bf16"}, "GenuineIntel", "AVX512_CORE_BF16", "fp32"),
    ({"avx2", "avx512f", "avx512_bf16"}, "AuthenticAMD", "AVX2", "fp32"),  # capped below bf16 (the AVX2 proxy)
    ({"avx2", "avx512f", "avx512_bf16"}, "AuthenticAMD", "avx512_core_amx", "bf16"),  # a cap that keeps bf16
])
def test_auto_on_a_cpu_follows_its_flags(cpu_host, flags, vendor, isa, expect):
    cpu_host(flags, vendor, isa)
    assert device.teacher_cpu_dtype() == expect
    assert resolve_teacher_dtype("auto", "cpu") == (expect, False)
    assert resolve_teacher_dtype("fp32", "cpu") == ("fp32", False)     # pinned: whatever the flags


def test_pinned_fp32_keeps_the_fingerprint_and_auto_bf16_says_caches_miss(tiny_sam3, monkeypatch):
    monkeypatch.setattr(device, "cpu_flags", lambda: frozenset({"avx512_bf16"}))
    monkeypatch.setattr(device, "cpu_vendor", lambda: "AuthenticAMD")
    pinned = Sam3Teacher(tiny_sam3, device="cpu", dtype="fp32", resolution=(40, 40))
    auto = Sam3Teacher(tiny_sam3, device="cpu", dtype="auto", resolution=(40, 40))
    fp = pinned.fingerprint()
    # the same fields and values as before auto could mean bf16 on a CPU: fp32 caches stay valid
    assert fp == {"backend": "sam3", "checkpoint": fp["checkpoint"], "dtype": "fp32", "resolution": [40, 40],
                  "score_threshold": 0.3, "mask_threshold": 0.5, "text_max_length": TEXT_MAX_LENGTH}
    assert auto.fingerprint()["dtype"] == "bf16" and auto.fingerprint() != fp
    assert pinned.cache_note() is None and "teacher.dtype: fp32" in auto.cache_note()
    monkeypatch.setattr(device, "cpu_flags", lambda: frozenset({"avx2"}))
    assert Sam3Teacher(tiny_sam3, device="cpu", resolution=(40, 40)).cache_note() is None


def test_fidelity_leaves_pairs_of_empty_masks_out():
    a = np.zeros((2, 3, 4, 4), bool)
    b = a.copy()
    a[0, 0, :2] = True                  # pair 0: IoU 1/2 against ...
    b[0, 0, :1] = True
    a[1, 2] = b[1, 2] = True            # pair 5: IoU 1; the other four pairs are both empty
    s = np.zeros((2, 3), np.float32)
    g = fidelity(a, s, b, s + 0.001)
    assert g["pairs"] == 6 and g["pairs_both_empty"] == 4 and g["mean_iou"] == pytest.approx(0.75)
    assert not g["passes"] and g["max_score_diff"] == pytest.approx(0.001)
    assert fidelity(a, s, a, s)["passes"] and fidelity(a, s, a, s)["mean_iou"] == 1.0
    none = np.zeros((1, 1, 4, 4), bool)
    assert not fidelity(none, s[:1, :1], none, s[:1, :1])["passes"]   # only empty pairs: nothing measured


def test_bf16_on_the_random_tiny_sam3_keeps_layout_and_prompts(tiny_sam3):
    """The default CPU path (bf16) against fp32 eager on the suite's tiny *random* SAM 3, score_threshold 0.
    A random model amplifies any rounding (its mask logits sit near the threshold over whole 14 x 14 cells):
    its agreement is 0.91-0.96 over three random seeds, and no bf16 variant tried reaches 0.99 on it (only the
    vision encoder in bf16: 0.98; autocast: 0.92-0.98), while rounding only its input to bf16 gives 0.994-0.998.
    So this test bounds it at 0.9 and the scores at 0.03 -- a wrong layout, a lost prompt or an unconverted
    input fails it. The 0.99 gate is tested on the fitted model below."""
    from pipeline.params import PAPER_PROMPTS
    from pipeline.teachers.base import TeacherInput
    from pipeline.teachers.tiny_sam3 import box_scenes

    items = [TeacherInput(f"img{i}", f"sha{i}", img) for i, (img, _) in enumerate(box_scenes(
        np.random.default_rng(0), 4))]
    kw = dict(device="cpu", resolution=(40, 40), score_threshold=0.0)
    ref = Sam3Teacher(tiny_sam3, dtype="fp32", **kw).predict(items, PAPER_PROMPTS)
    got = Sam3Teacher(tiny_sam3, dtype="bf16", **kw).predict(items, PAPER_PROMPTS)
    g = fidelity(*got, *ref)
    assert g["pairs_both_empty"] < g["pairs"] and 0.9 <= g["mean_iou"] <= 1.0 and g["max_score_diff"] <= 0.03, g


@pytest.mark.parametrize("engine", ["torch", "openvino", "onednn"])
def test_bf16_passes_the_fidelity_gate_on_a_fitted_tiny_sam3(fitted_tiny_sam3, engine):
    """The fidelity gate (mean mask IoU >= 0.99 against fp32 eager, score_threshold 0, pairs of two empty masks
    left out; scores within 0.02) on held-out box scenes, for the tiny SAM 3 fitted so that its logits have a
    trained model's margins (weights fitted to synthetic boxes: numerics only). The fp32 answers must find the
    boxes (IoU >= 0.7; 0.85 here), so a model that learned nothing cannot pass by agreeing on noise. Measured
    on an avx512_bf16 host: 0.997, scores within 0.002 (0.995-0.998 over fitting seeds 0-2). Every bf16 engine
    (``teacher.engine``: torch, OpenVINO's attention, oneDNN's fused MLPs) passes it."""
    from pipeline.params import PAPER_PROMPTS
    from pipeline.teachers.base import TeacherInput
    from pipeline.teachers.tiny_sam3 import box_scenes

    scenes = box_scenes(np.random.default_rng(7), 24)
    items = [TeacherInput(f"img{i}", f"sha{i}", img) for i, (img, _) in enumerate(scenes)]
    kw = dict(device="cpu", resolution=(40, 40), score_threshold=0.0)
    ref = Sam3Teacher(fitted_tiny_sam3, dtype="fp32", **kw).predict(items, PAPER_PROMPTS)
    if engine == "openvino":
        pytest.importorskip("openvino")
    teacher = Sam3Teacher(fitted_tiny_sam3, dtype="bf16", engine=engine, **kw)
    assert teacher.engine == engine
    got = teacher.predict(items, PAPER_PROMPTS)
    boxes = np.repeat(np.stack([m for _, m in scenes]), len(PAPER_PROMPTS), axis=0)  # one per (image, prompt)
    found = image_ious(ref[0].reshape(-1, 40, 40), boxes).mean()
    assert found >= 0.7, found
    g = fidelity(*got, *ref)
    assert g["pairs_both_empty"] == 0 and g["passes"], g
