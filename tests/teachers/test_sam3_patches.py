"""The exact savings patched into transformers' SAM 3 (pipeline.teachers.sam3.exact_savings, issue 65 item 1):
every patch target still exists with the source its replacement was written against, and the answers are bit for
bit those of transformers' own code, in fp32 and in bf16."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.bench_teacher import AsOf3056231, fidelity
from pipeline.teachers.sam3 import (FUSED_MLP_TARGET, SAM3_PATCHES, Sam3Teacher, exact_savings,
                                    fused_mlp_activations, upstream_source_digest)

pytest.importorskip("transformers")


@pytest.mark.parametrize("owner, name", sorted(SAM3_PATCHES))
def test_every_patch_target_exists_with_the_source_it_was_written_for(owner, name):
    """A transformers that renames, removes or rewrites a patched function fails here (at run time that patch
    is then skipped: the saving is lost, never the answer)."""
    digest = upstream_source_digest(owner, name)
    assert digest is not None, f"transformers' modeling_sam3 has no {owner}.{name} any more"
    assert digest == SAM3_PATCHES[owner, name][1], (
        f"transformers' {owner}.{name} changed: check that {SAM3_PATCHES[owner, name][0].__name__} still computes "
        "the same and record the new digest")


def test_the_fused_mlp_target_exists_with_the_source_it_was_written_for():
    owner, name, digest = FUSED_MLP_TARGET
    assert upstream_source_digest(owner, name) == digest, (
        f"transformers' {owner}.{name} changed: check that _fused_mlp_forward still computes the same and record "
        "the new digest")


@pytest.mark.parametrize("act", ["relu", "gelu"])
def test_the_fused_mlp_computes_upstreams_mlp_within_bf16_rounding_and_leaves_the_rest_alone(act):
    """oneDNN's fused activation against ``Sam3MLP``'s own forward: within a bf16 rounding of the output (GELU
    applied before the rounding, not after); fp32 and training run upstream's code bit for bit; the context
    restores every forward."""
    import copy
    import types

    import torch
    import transformers.models.sam3.modeling_sam3 as modeling

    torch.manual_seed(0)
    mlp32 = modeling.Sam3MLP(types.SimpleNamespace(hidden_act=act, hidden_size=32, intermediate_size=96,
                                                   hidden_dropout=0.0)).eval()
    mlp16 = copy.deepcopy(mlp32).bfloat16()
    model = torch.nn.ModuleDict({"a": mlp32, "b": mlp16})
    x = torch.randn(2, 50, 32)
    with torch.inference_mode():
        ref32, ref16 = mlp32(x), mlp16(x.bfloat16())
        with fused_mlp_activations(model) as fused:
            got16, got32 = mlp16(x.bfloat16()), mlp32(x)
            mlp32.train()
            trained = mlp32(x)
            mlp32.eval()
    assert fused == 2 and "forward" not in vars(mlp16) and "forward" not in vars(mlp32)
    assert got16.dtype == torch.bfloat16 and got16.shape == ref16.shape
    assert not torch.equal(got16, torch.zeros_like(got16))
    assert torch.allclose(got16.float(), ref16.float(), rtol=2e-2, atol=2e-2)
    assert (got16.float() - ref32).abs().max() <= 2 * (ref16.float() - ref32).abs().max() + 1e-3
    assert torch.equal(got32, ref32) and torch.equal(trained, ref32)


@pytest.mark.parametrize("dtype", ["float32", "bfloat16"])
def test_rope_and_window_partition_replacements_are_bit_identical(dtype):
    """The RoPE rotation and the window partition against transformers' own, at SAM 3's layout (batch, heads,
    tokens, head size as a transposed view of the projection) and with and without window padding."""
    import torch
    import transformers.models.sam3.modeling_sam3 as modeling

    from pipeline.teachers import sam3

    dt = getattr(torch, dtype)
    g = torch.Generator().manual_seed(0)
    lin = torch.randn(3, 20, 4 * 16, generator=g).to(dt)
    q = lin.view(3, 20, 4, 16).transpose(1, 2)
    k = (lin * 0.5 - 1).view(3, 20, 4, 16).transpose(1, 2)
    freqs = torch.rand(20, 2, 4, generator=g) * 30
    rec = lambda f: torch.cat([f[:, 0], f[:, 1]], -1)[None].repeat_interleave(2, -1)  # noqa: E731
    cos, sin = rec(freqs.cos()), rec(freqs.sin())
    for ref, got in zip(modeling.apply_rotary_pos_emb_2d(q, k, cos, sin), sam3._rope_fewer_passes(q, k, cos, sin)):
        assert ref.dtype == got.dtype and torch.equal(ref, got)
    for hw in (8, 7):  # 8 x 8 tokens in windows of 4: no padding; 7 x 7: padded to 8 x 8
        x = torch.randn(2, hw, hw, 6, generator=g).to(dt)
        (ref, ref_pad), (got, got_pad) = modeling.window_partition(x, 4), sam3._window_partition_no_empty_pad(x, 4)
        assert ref_pad == got_pad and torch.equal(ref, got)


@pytest.mark.parametrize("dtype", ["float32", "bfloat16"])
def test_rope_as_a_complex_product_is_bit_identical_where_it_applies(dtype):
    """The complex product against transformers' rotation at head size 64 (SAM 3's), at shapes and thread counts
    where ATen's thread split lands mid-vector (the product must not apply there) and where it does not; the
    real window shape at 2 threads takes it. Fails when a torch build fuses the vectorised product's terms."""
    import torch
    import transformers.models.sam3.modeling_sam3 as modeling

    from pipeline.teachers import sam3

    dt = getattr(torch, dtype)
    g = torch.Generator().manual_seed(1)
    threads, applied = torch.get_num_threads(), []
    try:
        for batch, heads, tokens, threads_now in [(9, 16, 576, 2), (1, 3, 1111, 2), (1, 3, 1111, 3),
                                                  (1, 3, 1111, 5), (2, 2, 9, 4), (1, 1, 1025, 7)]:
            torch.set_num_threads(threads_now)
            lin = (torch.randn(batch, tokens, heads * 64, generator=g) * 8).to(dt)
            q = lin.view(batch, tokens, heads, 64).transpose(1, 2)
            k = (lin * 0.25 + 1).view(batch, tokens, heads, 64).transpose(1, 2)
            freqs = torch.rand(tokens, 2, 16, generator=g) * 40
            rec = lambda f: torch.cat([f[:, 0], f[:, 1]], -1)[None].repeat_interleave(2, -1)  # noqa: E731
            cos, sin = rec(freqs.cos()), rec(freqs.sin())
            applied.append(sam3._complex_rotation_is_exact(q, cos, sin, threads_now))
            before = q.clone()
            for ref, got in zip(modeling.apply_rotary_pos_emb_2d(q, k, cos, sin),
                                sam3._rope_fewer_passes(q, k, cos, sin)):
                assert ref.dtype == got.dtype
                assert [st for st, n in zip(ref.stride(), ref.shape) if n > 1] == [  # the same layout
                    st for st, n in zip(got.stride(), got.shape) if n > 1]
                assert torch.equal(ref.view(torch.int16 if dt == torch.bfloat16 else torch.int32),
                                   got.view(torch.int16 if dt == torch.bfloat16 else torch.int32))
            assert torch.equal(q, before)  # the input is not rotated in place (fp32: no copy by .float())
    finally:
        torch.set_num_threads(threads)
    assert applied == [True, True, True, False, True, True]
    cos_unpaired = torch.rand(1, 576, 64, generator=g)
    assert not sam3._complex_rotation_is_exact(q, cos_unpaired, cos_unpaired, 2)


@pytest.mark.parametrize("dtype", ["fp32", "bf16"])
def test_the_default_path_gives_the_answers_of_3056231_bit_for_bit(fitted_tiny_sam3, dtype):
    """The teacher with the savings (views instead of repeated FPN levels for one image per forward, the patches)
    against the code of 3056231 (transformers as is, levels repeated): masks and scores identical, one and
    three images per forward; so the bf16 gate (test_teacher_cpu_dtype) and the cache fingerprint hold."""
    from pipeline.params import PAPER_PROMPTS
    from pipeline.teachers.base import TeacherInput
    from pipeline.teachers.tiny_sam3 import box_scenes

    items = [TeacherInput(f"img{i}", f"sha{i}", img) for i, (img, _) in enumerate(box_scenes(
        np.random.default_rng(3), 3))]
    for batch in (1, 3):
        teacher = Sam3Teacher(fitted_tiny_sam3, device="cpu", dtype=dtype, batch_size=batch, resolution=(40, 40),
                              score_threshold=0.0)
        masks, scores = teacher.predict(items, PAPER_PROMPTS)
        ref_masks, ref_scores = AsOf3056231(teacher).predict(items, PAPER_PROMPTS)
        np.testing.assert_array_equal(masks, ref_masks)
        np.testing.assert_array_equal(scores, ref_scores)
        assert fidelity(masks, scores, ref_masks, ref_scores)["mean_iou"] == 1.0


def test_a_windowed_backbone_gives_the_same_outputs_with_the_savings():
    """The full model with windowed backbone layers (the suite's tiny SAM 3 has global ones only), 70 px input:
    5 x 5 tokens in windows of 2, so the padded branch runs: every output equal with and without the context,
    which leaves transformers' functions as they were."""
    import torch
    import transformers.models.sam3.modeling_sam3 as modeling
    from transformers import Sam3Model

    from pipeline.teachers.tiny_sam3 import tiny_sam3_config

    config = tiny_sam3_config(image_size=70)
    config.vision_config.backbone_config.global_attn_indexes = [1]
    torch.manual_seed(0)
    model = Sam3Model(config).eval()
    assert model.vision_encoder.backbone.layers[0].window_size == 2
    pixels = torch.randn(2, 3, 70, 70)
    ids = torch.randint(2, 100, (2, 8))
    before = modeling.apply_rotary_pos_emb_2d, modeling.window_partition
    with torch.inference_mode():
        ref = model(pixel_values=pixels, input_ids=ids)
        with exact_savings(model):
            assert modeling.window_partition is not before[1] and "_get_rpb_matrix" in vars(model.detr_decoder)
            got = model(pixel_values=pixels, input_ids=ids)
    assert (modeling.apply_rotary_pos_emb_2d, modeling.window_partition) == before
    assert "_embed_pixels" not in vars(model.mask_decoder) and "_get_rpb_matrix" not in vars(model.detr_decoder)
    for name in ("pred_masks", "pred_logits", "presence_logits", "semantic_seg"):
        assert torch.equal(getattr(ref, name), getattr(got, name)), name
