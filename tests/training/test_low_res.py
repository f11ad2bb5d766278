"""The resolution schedule (train.low_res_epochs, a recipe part of Stage I; docs/decisions.md, Training)."""

from __future__ import annotations

import pytest
import torch

from pipeline.methods import get_method
from pipeline.runtime.errors import InputError
from pipeline.training import loop as training
from tests.builders.training import load_arrays, tiny_cfg


def test_a_batch_at_half_the_side_keeps_a_hard_mask_hard():
    x = torch.arange(16, dtype=torch.float32).view(1, 1, 4, 4).expand(1, 3, 4, 4) / 16
    mask = torch.tensor([[1, 1, 0, 0], [1, 0, 0, 0], [0, 0, 1, 1], [0, 0, 0, 1.0]]).view(1, 1, 4, 4)
    b = {"x": x, "mask": mask, "area": torch.tensor([0.4]), "gate": torch.tensor([1.0])}
    low = training.low_resolution(b)
    assert low["x"].shape == (1, 3, 2, 2) and low["x"][0, 0, 0, 0] == pytest.approx((0 + 1 + 4 + 5) / 64)
    # quarters hold 3, 0, 0 and 3 of 4 foreground pixels: [3/4 >= 1/2]
    assert low["mask"].view(-1).tolist() == [1.0, 0.0, 0.0, 1.0]
    assert low["area"] is b["area"] and low["gate"] is b["gate"] and b["x"].shape[-1] == 4  # b is not changed
    soft = training.low_resolution({**b, "mask": mask * 0.5})  # an agreement map stays soft: its area mean
    assert soft["mask"].view(-1).tolist() == [0.375, 0.0, 0.0, 0.375]


def test_the_first_epochs_train_at_half_the_side_then_full(tiny, monkeypatch):
    cfg = tiny_cfg(epochs_stage1=3, low_res_epochs=2)
    data, val = load_arrays(tiny, "plain", cfg)
    seen = []
    step = training._step

    def spy(run, b, epoch, i):
        seen.append((epoch, b["x"].shape[-1], b["mask"].shape[-1]))
        return step(run, b, epoch, i)

    monkeypatch.setattr(training, "_step", spy)
    res = training.train(get_method("plain"), cfg, data, val, 5, checkpointer=training.NoCheckpointer(),
                         show_progress=False)
    side = data.images.shape[1]
    assert {e: s for e, s, _ in seen} == {1: side // 2, 2: side // 2, 3: side}
    assert all(s == m for _, s, m in seen) and len(res.log) == 3
    # Stage II keeps its resolution: the part is Stage I's
    s2 = training.Settings.from_params(get_method("geodistill"), cfg, 0.5)
    assert s2.low_res_epochs == 0 and training.Settings.from_params(get_method("plain"), cfg, 0.5).low_res_epochs == 2


@pytest.mark.parametrize("over, match", [({"until": "plateau", "low_res_epochs": 1}, "until"),
                                         ({"low_res_epochs": 2}, "below train.epochs_stage1")])
def test_the_schedule_is_checked(over, match):
    with pytest.raises(InputError, match=match):
        training.Settings.from_params(get_method("plain"), tiny_cfg(**over), 0.5)


def test_the_schedule_is_a_recipe_part_every_method_tracks():
    from pipeline.methods import METHODS, param_keys
    from pipeline.params import RECIPES

    assert all(r["train"]["low_res_epochs"] == 0 for r in RECIPES.values())
    assert all("train.low_res_epochs" in param_keys(m) for m in METHODS.values())
