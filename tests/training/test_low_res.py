"""The resolution schedule (train.low_res_fraction, a recipe part of Stage I; docs/decisions.md, Training)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline.methods import get_method
from pipeline.runtime.errors import InputError
from pipeline.training import loop as training
from tests.builders.training import load_arrays, tiny_cfg
from pipeline.training import schedule
from pipeline.training.settings import Settings
from pipeline.training.checkpointing import NoCheckpointer


def test_a_batch_at_half_the_side_keeps_a_hard_mask_hard():
    x = torch.arange(16, dtype=torch.float32).view(1, 1, 4, 4).expand(1, 3, 4, 4) / 16
    mask = torch.tensor([[1, 1, 0, 0], [1, 0, 0, 0], [0, 0, 1, 1], [0, 0, 0, 1.0]]).view(1, 1, 4, 4)
    b = {"x": x, "mask": mask, "area": torch.tensor([0.4]), "gate": torch.tensor([1.0])}
    low = schedule.low_resolution(b)
    assert low["x"].shape == (1, 3, 2, 2) and low["x"][0, 0, 0, 0] == pytest.approx((0 + 1 + 4 + 5) / 64)
    # quarters hold 3, 0, 0 and 3 of 4 foreground pixels: [3/4 >= 1/2]
    assert low["mask"].view(-1).tolist() == [1.0, 0.0, 0.0, 1.0]
    assert low["area"] is b["area"] and low["gate"] is b["gate"] and b["x"].shape[-1] == 4  # b is not changed
    soft = schedule.low_resolution({**b, "mask": mask * 0.5}, soft=True)  # an agreement map stays soft: its area mean
    assert soft["mask"].view(-1).tolist() == [0.375, 0.0, 0.0, 0.375]
    # soft by its type, not by its values: an agreement map whose pixels happen to be 0 or 1 is averaged too
    assert schedule.low_resolution(b, soft=True)["mask"].view(-1).tolist() == [0.75, 0.0, 0.0, 0.75]


def test_a_soft_target_run_trains_its_half_side_epochs_on_the_averaged_map(tiny, monkeypatch):
    cfg = tiny_cfg(epochs_stage1=2, low_res_fraction=0.5, soft_targets=True)
    data, val = load_arrays(tiny, "plain", cfg)
    assert np.dtype(data.mask.dtype).kind == "f"  # the agreement map A (eq:agreement-map)
    seen = []
    step = training._step

    def spy(run, b, epoch, i):
        seen.append((epoch, bool(((b["mask"] > 0) & (b["mask"] < 1)).any())))
        return step(run, b, epoch, i)

    monkeypatch.setattr(training, "_step", spy)
    training.train(get_method("plain"), cfg, data, val, 5, checkpointer=NoCheckpointer(),
                   show_progress=False)
    assert any(fractional for epoch, fractional in seen if epoch == 1)  # not thresholded at half the side


def test_the_first_epochs_train_at_half_the_side_then_full(tiny, monkeypatch):
    cfg = tiny_cfg(epochs_stage1=3, low_res_fraction=0.67)  # round(2.01): 2 epochs
    data, val = load_arrays(tiny, "plain", cfg)
    seen = []
    step = training._step

    def spy(run, b, epoch, i):
        seen.append((epoch, b["x"].shape[-1], b["mask"].shape[-1]))
        return step(run, b, epoch, i)

    monkeypatch.setattr(training, "_step", spy)
    res = training.train(get_method("plain"), cfg, data, val, 5, checkpointer=NoCheckpointer(),
                         show_progress=False)
    side = data.images.shape[1]
    assert {e: s for e, s, _ in seen} == {1: side // 2, 2: side // 2, 3: side}
    assert all(s == m for _, s, m in seen) and len(res.log) == 3 and res.info["low_res_epochs"] == 2
    # Stage II keeps its resolution: the part is Stage I's
    s2 = Settings.from_params(get_method("geodistill"), cfg, 0.5)
    assert s2.low_res_epochs == 0 and Settings.from_params(get_method("plain"), cfg, 0.5).low_res_epochs == 2


def test_the_schedule_scales_with_the_cap_and_keeps_the_last_epoch_at_full_side():
    from pipeline.profiles import load_profile

    assert [schedule.low_res_epochs(e, f) for e, f in ((220, 8 / 11), (40, 0.5), (2, 0.9), (1, 0.5), (10, 0))] \
        == [160, 20, 1, 0, 0]
    for bad in ("1", "-0.1"):
        with pytest.raises(InputError, match="low_res_fraction"):
            load_profile("paper", [f"train.low_res_fraction={bad}"])


def test_under_until_plateau_the_rule_scores_the_epochs_after_the_schedule(tiny, monkeypatch):
    cfg = tiny_cfg(until="plateau", epochs_stage1=40, warmup_epochs=1, average_last=1, schedule="wsd",
                   plateau_min_epochs=2, plateau_min_steps=0, plateau_gain=1.0, low_res_fraction=0.075)  # 3 epochs  # any doubling gains less than 1.0
    data, val = load_arrays(tiny, "plain", cfg)
    sides = {}
    step = training._step

    def spy(run, b, epoch, i):
        sides[epoch] = b["x"].shape[-1]
        return step(run, b, epoch, i)

    monkeypatch.setattr(training, "_step", spy)
    res = training.train(get_method("plain"), cfg, data, val, 5, checkpointer=NoCheckpointer(),
                         show_progress=False)
    # the rule waits for 4 scored epochs (4-7) after the 3 at half the side; then 2 decay epochs at full side
    assert res.info["stable_epochs"] == 7 and res.info["stopped"].startswith("plateau") and res.info["epochs"] == 9
    side = data.images.shape[1]
    assert sides == {e: side // 2 if e <= 3 else side for e in range(1, 10)}


def test_a_cap_inside_the_schedule_decays_at_full_resolution(tiny, monkeypatch):
    cfg = tiny_cfg(until="plateau", epochs_stage1=5, average_last=1, schedule="wsd", low_res_fraction=0.8,
                   step_budget=6)  # 2 steps an epoch: 2 stable epochs and 1 decay epoch fit
    data, val = load_arrays(tiny, "plain", cfg)
    sides = {}
    step = training._step
    monkeypatch.setattr(training, "_step", lambda run, b, e, i: (sides.__setitem__(e, b["x"].shape[-1]),
                                                                 step(run, b, e, i))[1])
    res = training.train(get_method("plain"), cfg, data, val, 5, checkpointer=NoCheckpointer(),
                         show_progress=False)
    side = data.images.shape[1]  # the budget ends the stable phase inside the schedule; epoch 3 is the decay
    assert res.info["stable_epochs"] == 2 and res.info["epochs"] == 3 and res.info["low_res_epochs"] == 2
    assert sides == {1: side // 2, 2: side // 2, 3: side}


def test_the_schedule_is_a_recipe_part_every_method_tracks():
    from pipeline.methods import METHODS, param_keys
    from pipeline.params import RECIPES

    assert {k for k, r in RECIPES.items() if r["train"]["low_res_fraction"]} == {"progressive"}
    assert all("train.low_res_fraction" in param_keys(m) for m in METHODS.values())


def test_distills_summary_says_how_many_epochs_ran_at_half_the_side(tmp_path):
    import json

    import yaml

    from pipeline import catalog
    from pipeline.orchestration.standalone import PARAMS_FILE, training_line

    (tmp_path / PARAMS_FILE).write_text(yaml.safe_dump({"protocol": {"runs": {"plain": [42]}}}))
    meta = catalog.path("checkpoints", tmp_path / catalog.ARTIFACTS_DIR) / "plain" / "42" / catalog.META_FILE
    meta.parent.mkdir(parents=True)
    extra = {"steps_run": 7480, "epochs": 220, "low_res_epochs": 160, "stopped": "the epochs cap (train.epochs_stage1)"}
    meta.write_text(json.dumps({"extra": extra}))
    assert training_line(tmp_path) == ("Stage I trained 7,480 optimizer steps (220 epochs, the first 160 at half the "
                                       "side), stopped at the epochs cap (train.epochs_stage1)")
    # a cap that --time raised says so
    (tmp_path / PARAMS_FILE).write_text(yaml.safe_dump({"protocol": {"runs": {"plain": [42]}}, "train": {
        "time_budget": "40m", "time_raised_from": 220, "epochs_stage1": 880}}))
    assert training_line(tmp_path).endswith("stopped at the epochs cap (train.epochs_stage1); --time 40m raised the "
                                            "epochs cap from 220 to 880")
    (tmp_path / PARAMS_FILE).write_text(yaml.safe_dump({"protocol": {"runs": {"plain": [42]}}}))
    meta.write_text(json.dumps({"extra": {**extra, "low_res_epochs": 0}}))
    assert "half the side" not in training_line(tmp_path)
    # a Stage I that departed from eq:raw-loss says so (its recorded params)
    meta.write_text(json.dumps({"extra": extra, "params": {"params": {"train.bootstrap_beta": 0.8}}}))
    assert training_line(tmp_path).endswith("; with bootstrapped targets, beta 0.8 (a departure from eq:raw-loss)")
    # the deployed Stage-II run at the same seed: its steps on top, which --time does not bound
    (tmp_path / PARAMS_FILE).write_text(yaml.safe_dump({"protocol": {"runs": {"plain": [42], "geodistill": [42]}}}))
    stage2 = meta.parents[1].parent / "geodistill" / "42" / catalog.META_FILE
    stage2.parent.mkdir(parents=True)
    stage2.write_text(json.dumps({"extra": {"steps_run": 1360, "epochs": 40}}))
    assert training_line(tmp_path).endswith("; then Stage II (geodistill) 1,360 more (40 epochs), which --time does "
                                            "not bound")


def test_half_side_epochs_go_unvalidated_unless_asked_and_the_weights_are_the_same(tiny):
    # until plateau with a weight average (progressive's parts): 3 of the 6 epochs at half the side, read by no rule
    cfg = tiny_cfg(until="plateau", epochs_stage1=6, average_last=1, schedule="wsd", low_res_fraction=0.5)
    data, val = load_arrays(tiny, "plain", cfg)
    runs = {on: training.train(get_method("plain"), {**cfg, "validate_low_res": on}, data, val, 5,
                               checkpointer=NoCheckpointer(), show_progress=False) for on in (False, True)}
    fast, full = runs[False], runs[True]
    assert fast.info["low_res_epochs"] == 3 and fast.info["epochs"] == full.info["epochs"] == 6
    assert all(torch.equal(a, b) for a, b in zip(fast.model.state_dict().values(), full.model.state_dict().values()))
    half = (fast.log["epoch"] <= 3).to_numpy()
    assert fast.log.loc[half, "val_iou"].isna().all() and fast.log.loc[~half, "val_iou"].notna().all()
    assert full.log["val_iou"].notna().all()
    np.testing.assert_array_equal(fast.log.loc[~half, "val_iou_cal"], full.log.loc[~half, "val_iou_cal"])


def test_a_best_validation_pick_without_an_average_still_validates_every_epoch(tiny):
    cfg = tiny_cfg(epochs_stage1=3, low_res_fraction=0.67, validate_low_res=False)  # Plain picks its best val epoch
    data, val = load_arrays(tiny, "plain", cfg)
    res = training.train(get_method("plain"), cfg, data, val, 5, checkpointer=NoCheckpointer(),
                         show_progress=False)
    assert res.info["low_res_epochs"] == 2 and res.log["val_iou"].notna().all()
