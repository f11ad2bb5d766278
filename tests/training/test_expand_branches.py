"""Capacity that folds away (issue 63 item 3): ``train.expand_branches`` trains each 3x3 convolution with RepVGG's
1x1 and identity branches and folds them into the plain TinyUNet at the end of each stage."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from torch import nn

from pipeline.model import (ConvBNReLU, ExpandedConvBNReLU, ExportMaskPath, TinyUNet, count_parameters,
                            expand_branches, fold_branches, has_branches)
from pipeline.training.checkpointing import NoCheckpointer
from tests.builders.training import MemoryCheckpointer, assert_same_state, clone_state, shape_mask, tiny_cfg

#: the folding error the issue allows: folded against unfolded logits, fp32, eval mode
FOLD_ATOL = 1e-4
SIZE = 24


def _arrays(n_train: int = 6, n_val: int = 2):
    """In-memory training and validation arrays: lit shapes on dark noise, the masks their labels."""
    from pipeline.training import loop as training

    rng = np.random.default_rng(3)
    n = n_train + n_val
    masks = np.stack([shape_mask(rng, SIZE) for _ in range(n)])
    images = np.where(masks[..., None], rng.integers(150, 255, (n, SIZE, SIZE, 3)),
                      rng.integers(0, 60, (n, SIZE, SIZE, 3))).astype(np.uint8)
    data = training.TrainData(image_ids=[f"t{i}" for i in range(n_train)], images=images[:n_train],
                              mask=masks[:n_train], area=masks[:n_train].reshape(n_train, -1).mean(1).astype(np.float32),
                              gate=np.ones(n_train, np.float32))
    val = training.ValData(image_ids=[f"v{i}" for i in range(n_val)], images=images[n_train:], masks=masks[n_train:])
    return data, val


def _x(images: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255.0


def _trained_expanded(steps: int = 8, seed: int = 0) -> tuple[TinyUNet, torch.Tensor]:
    """An expanded TinyUNet after ``steps`` AdamW steps in train mode (running BN statistics far from 0 and 1) and
    the images it saw."""
    torch.manual_seed(seed)
    model = expand_branches(TinyUNet(channels=(8, 16, 32)))
    data, _ = _arrays()
    x, y = _x(data.images), torch.from_numpy(data.mask[:, None]).float()
    opt = torch.optim.AdamW(model.parameters(), lr=5e-3)
    for _ in range(steps):
        loss = nn.functional.binary_cross_entropy_with_logits(model(x), y)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return model.eval(), x


def test_branches_go_beside_every_3x3_convolution_and_the_identity_where_channels_match():
    model = expand_branches(TinyUNet())
    blocks = [m for m in model.modules() if isinstance(m, ExpandedConvBNReLU)]
    assert len(blocks) == 10 and not any(isinstance(m, ConvBNReLU) for m in model.modules())
    assert sum(b.norm_identity is not None for b in blocks) == 5
    assert all((b.norm_identity is not None) == (b.conv.in_channels == b.conv.out_channels) for b in blocks)
    # the deployed network of the paper (channels 24/48/96): trained with more, deployed with exactly its count
    assert count_parameters(model) == 296_905
    assert count_parameters(fold_branches(model)) == count_parameters(TinyUNet()) == 266_017


def test_folded_logits_equal_the_expanded_ones_in_fp32_eval_mode():
    """After training steps (non-trivial BN statistics in every branch) the folded model's logits are the expanded
    model's within 1e-4, with or without the images that measure the folded BN statistics."""
    model, x = _trained_expanded()
    bns = [m for m in model.modules() if isinstance(m, nn.BatchNorm2d)]
    assert min(float((bn.running_var - 1).abs().max()) for bn in bns) > 0.05  # statistics moved off the init
    held_out = torch.rand(3, 3, SIZE + 8, SIZE, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        expanded = model(held_out)  # another size, random images
        reference = model(x)
        for batches in (None, [x[:4], x[4:]]):
            folded = fold_branches(copy.deepcopy(model), batches)
            assert not has_branches(folded) and folded.config == model.config
            assert list(folded.state_dict()) == list(TinyUNet(channels=(8, 16, 32)).state_dict())
            assert float((folded(x) - reference).abs().max()) <= FOLD_ATOL
            assert float((folded(held_out) - expanded).abs().max()) <= FOLD_ATOL


def test_zero_branches_start_as_the_folded_model_and_export_sees_plain_convolutions():
    """A warm start re-expands with branches at zero: the same logits in eval and train mode.  Export refuses an
    expanded model and sees a plain Conv2d everywhere in the folded one."""
    model, x = _trained_expanded(steps=4)
    folded = fold_branches(model, [x])
    again = expand_branches(copy.deepcopy(folded), zero_init=True)
    with torch.no_grad():
        assert torch.equal(again.eval()(x), folded.eval()(x))
        assert torch.equal(again.train()(x), folded.train()(x))
    with pytest.raises(ValueError, match="fold"):
        ExportMaskPath(again)
    exported = ExportMaskPath(folded.eval())
    convs = [m for m in exported.modules() if isinstance(m, nn.Conv2d)]
    assert len(convs) == 11 and all(type(m) is nn.Conv2d for m in convs)
    assert not any(isinstance(m, ExpandedConvBNReLU) for m in exported.modules())


def test_the_part_is_declared_off_refused_under_group_norm_and_in_every_fingerprint():
    from pipeline.methods import COMMON_KEYS, METHODS, RECIPES, departures, param_keys
    from pipeline.params import PAPER, validate_section
    from pipeline.runtime.errors import InputError

    assert PAPER.train.expand_branches is False and all(not r["train"]["expand_branches"] for r in RECIPES.values())
    assert "expand_branches" in COMMON_KEYS and all("train.expand_branches" in param_keys(m) for m in METHODS.values())
    assert departures({"train.expand_branches": True}) == []  # an optimisation change: the loss is the paper's
    with pytest.raises(InputError, match=r"train.expand_branches needs train.norm: batch"):
        validate_section("train", {**PAPER.train.model_dump(), "expand_branches": True, "norm": "group"})


def test_a_run_trains_expanded_resumes_expanded_and_saves_the_folded_model():
    """Stage I with the part on: the resume state holds the expanded weights under a run key that names the part,
    the result is the folded plain TinyUNet after the weight average and its BN recompute (its folding error
    recorded), a resumed run gives the same weights; Stage II re-expands from it at zero, so its epoch 0 is the
    Stage-I model's score; off, the model and its info are today's."""
    from pipeline.methods import get_method
    from pipeline.training import loop as training

    data, val = _arrays()
    cfg = tiny_cfg(epochs_stage1=3, epochs_stage2=1, lr_stage1=3e-3, batch_size=3, average_last=2,
                   channels=[8, 16, 32], expand_branches=True)

    class Killed(Exception):
        pass

    def kill_after_2(epoch, row):
        if epoch == 2:
            raise Killed

    ck = MemoryCheckpointer()
    with pytest.raises(Killed):
        training.train(get_method("plain"), cfg, data, val, 42, checkpointer=ck, callback=kill_after_2,
                       show_progress=False)
    assert ck.state["run_key"]["expand_branches"] is True and any("conv1x1" in k for k in ck.state["model"])
    resumed = training.train(get_method("plain"), cfg, data, val, 42, checkpointer=ck, show_progress=False)
    full = training.train(get_method("plain"), cfg, data, val, 42, checkpointer=NoCheckpointer(),
                          show_progress=False)
    assert_same_state(clone_state(full.model), clone_state(resumed.model))
    model = full.model
    assert not has_branches(model) and model.config == {"in_channels": 3, "channels": [8, 16, 32]}
    folded = full.info["folded"]
    assert folded["fold_max_abs_logit_diff"] <= FOLD_ATOL
    assert folded["parameters_deployed"] == count_parameters(model) < folded["parameters_trained"]
    assert full.info["selection"].startswith("mean weights of the last 2 epochs")

    stage2 = training.train(get_method("continuation"), cfg, data, val, 42, init_state=model.mask_path_state_dict(),
                            checkpointer=NoCheckpointer(), show_progress=False)
    scores = training.validation_scores(model, val, "cpu", precision="fp32", channels_last=True, tolerance=2,
                                        calibrated=False)
    assert stage2.log["val_iou"].iloc[0] == pytest.approx(scores["val_iou"], abs=1e-12)
    assert not has_branches(stage2.model) and "folded" in stage2.info

    off = training.train(get_method("plain"), {**cfg, "expand_branches": False, "epochs_stage1": 1}, data, val, 42,
                         checkpointer=NoCheckpointer(), show_progress=False)
    assert "folded" not in off.info and list(off.model.state_dict()) == list(model.state_dict())


@pytest.mark.filterwarnings("ignore")
def test_the_folded_bundle_passes_the_int8_gate(tmp_path):
    """The folded model of an expanded run exports through the deploy bundle, int8 included: its int8 masks meet
    the schema's deploy.int8_min_mask_iou against PyTorch on the training images."""
    from pipeline.deploy.bundle import write_bundle
    from pipeline.deploy.mask_path import onnx_unavailable_reason
    from pipeline.methods import get_method
    from pipeline.training import loop as training
    from tests.builders.deploy import int8_settings

    if onnx_unavailable_reason() is not None:
        pytest.skip(onnx_unavailable_reason())
    data, val = _arrays()
    cfg = tiny_cfg(epochs_stage1=6, lr_stage1=1e-2, batch_size=3, channels=[8, 16, 32], expand_branches=True)
    model = training.train(get_method("plain"), cfg, data, val, 42, checkpointer=NoCheckpointer(),
                           show_progress=False).model
    info = write_bundle(tmp_path, model, {"method": "plain", "seed": 42}, tau=0.5, tau_source="test",
                        resolution=SIZE, opset=17, atol=1e-4, int8_settings=int8_settings(),
                        calibration_images=data.images)
    q = info["parity"]["int8"]
    assert info["int8"] is not None, info["int8_note"]
    assert q["passed"] and q["mask_iou_mean"] >= int8_settings().int8_min_mask_iou
    assert info["params"] == count_parameters(TinyUNet(channels=(8, 16, 32)))
