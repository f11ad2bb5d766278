"""Stage I that stops at the plateau or a step budget (train.until: plateau; issue 43 item 2)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from pipeline.training import loop as training
from pipeline.methods import get_method
from tests.builders.training import REPO, assert_same_state, clone_state, load_arrays, tiny_cfg
from pipeline.training import schedule
from pipeline.training.settings import Settings
from pipeline.training.checkpointing import NoCheckpointer
from tests.builders.training import MemoryCheckpointer


def test_plateau_rule_is_a_doubling_that_gains_too_little():
    rising = [0.1 * i for i in range(1, 9)]
    assert not schedule.plateau_reached(rising, 0.005, 4)
    flat = [0.62, 0.621, 0.619, 0.62, 0.62, 0.619, 0.621, 0.6205]  # gain +0.0001, its 95 % bound +0.0013
    assert schedule.plateau_reached(flat, 0.005, 4) and not schedule.plateau_reached(flat, 0.001, 4)
    assert not schedule.plateau_reached(flat[:3], 0.005, 4)  # too early to tell
    assert not schedule.plateau_reached([float("nan")] * 8, 0.005, 4)  # nothing scored: no stop
    # 64^2 Plain runs' stable phases (reduced profile): the best of each half (seed 42, an early spike at epoch 8)
    # and the mean of each half (seed 2026, 4 noisy epochs a side) both called these a plateau, yet the decayed
    # weights gained +0.05 to +0.08 within two epochs; the noise (about 0.03 an epoch) keeps the bound above 0.005
    spiky = [0.264, 0.322, 0.338, 0.341, 0.338, 0.394, 0.374, 0.437, 0.411, 0.357, 0.384, 0.352, 0.373, 0.379,
             0.396, 0.439]
    early = [0.274, 0.313, 0.329, 0.326, 0.276, 0.317, 0.347, 0.307]
    assert not schedule.plateau_reached(spiky, 0.005, 8) and not schedule.plateau_reached(early, 0.005, 8)


def test_stable_cap_fits_the_decay_into_the_budget():
    s = Settings.from_params(get_method("plain"), tiny_cfg(epochs_stage1=100, step_budget=500, until="plateau",
                                                                      decay_fraction=0.2), 0.5)
    assert schedule.stable_cap(s, 10) == 40 and schedule.decay_epochs(40, 0.2) == 10  # 50 epochs = 500 steps
    assert schedule.stable_cap(dataclasses.replace(s, step_budget=0), 10) == 80  # the epochs cap alone: 80 + 20


def _run(tiny, checkpointer=None, val=True, **over):
    # plateau_min_steps 0: the tiny runs test the rule's epochs (the window in steps: test_with_few_images_the_least_window_is_in_steps)
    cfg = tiny_cfg(**{"until": "plateau", "epochs_stage1": 40, "warmup_epochs": 1, "average_last": 1,
                      "schedule": "wsd", "plateau_min_steps": 0, **over})
    data, v = load_arrays(tiny, "plain", cfg)
    return training.train(get_method("plain"), cfg, data, v if val else None, 5,
                          checkpointer=checkpointer or NoCheckpointer(), show_progress=False)


def test_stops_at_the_plateau_then_decays(tiny):
    res = _run(tiny, plateau_min_epochs=2, plateau_gain=1.0)  # any doubling gains less than 1.0
    assert res.info["stable_epochs"] == 4 and res.info["stopped"].startswith("plateau")  # 2 epochs a half at least
    assert res.info["epochs"] == 5 and res.info["steps_run"] == 5 * 2  # 8 images, batch 4
    assert len(res.log) == 5
    from types import SimpleNamespace

    run = SimpleNamespace(steps_per_epoch=2, settings=SimpleNamespace(warmup_epochs=1),
                          until={"stable_end": None, "epochs": 40})
    factor = schedule.until_lambda(run.until, run.steps_per_epoch, run.settings.warmup_epochs * run.steps_per_epoch)
    assert [factor(i) for i in (0, 1, 5)] == [0.5, 1.0, 1.0]  # warm-up, then the stable rate
    run.until.update(stable_end=2, epochs=3)  # stopped after epoch 2: one decay epoch, linear to 0
    assert [factor(i) for i in (3, 4, 5, 6)] == [1.0, 1.0, 0.5, 0.0]


#: plateau_min_epochs past any tiny run: the rule never fires, the budget stops the run
NEVER = 10**6


def test_a_stop_at_the_plateau_is_not_resumed_under_another_rule(tiny):
    ckpt = MemoryCheckpointer()
    assert _run(tiny, ckpt, plateau_min_epochs=2, plateau_gain=1.0).info["stopped"].startswith("plateau")
    other = _run(tiny, ckpt, plateau_min_epochs=NEVER, step_budget=8)  # another rule: trained, not the saved stop
    assert other.info["stopped"].startswith("the step budget") and other.info["steps_run"] == 8


def test_a_budget_stops_it_and_a_larger_one_continues_the_saved_run(tiny):
    ckpt = MemoryCheckpointer()
    short = _run(tiny, ckpt, plateau_min_epochs=NEVER, step_budget=8)  # never a plateau: the budget binds
    assert short.info["stopped"].startswith("the step budget") and short.info["steps_run"] == 8
    assert short.info["stable_epochs"] == 3
    again = _run(tiny, ckpt, plateau_min_epochs=NEVER, step_budget=8)  # a rerun: the finished state, no training
    assert_same_state(clone_state(again.model), clone_state(short.model))
    longer = _run(tiny, ckpt, plateau_min_epochs=NEVER, step_budget=16)  # continues the stable phase from epoch 3
    fresh = _run(tiny, None, plateau_min_epochs=NEVER, step_budget=16)
    assert longer.info["steps_run"] == fresh.info["steps_run"] == 16 and longer.info["stable_epochs"] == 6
    assert_same_state(clone_state(longer.model), clone_state(fresh.model))
    assert not all(torch.equal(a, b) for a, b in zip(longer.model.state_dict().values(),
                                                      short.model.state_dict().values()))


def test_without_validation_masks_it_scores_held_out_pseudo_labels(tiny):
    cfg = tiny_cfg(until="plateau")
    data, _ = load_arrays(tiny, "plain", cfg)
    rest, val = schedule.holdout(data, 0.25)
    assert len(val) == 2 and len(rest) == len(data) - 2
    assert not set(val.image_ids) & {f"holdout:{i}" for i in rest.image_ids}
    assert val.masks.dtype == bool and "against their vote" in rest.stats["plateau_scored_on"]
    res = _run(tiny, val=False, plateau_min_epochs=2, plateau_gain=1.0)
    assert res.info["stopped"].startswith("plateau") and "against their vote" in res.info["plateau_scored_on"]
    assert res.log["val_iou"].isna().all()  # the held-out pseudo-labels are no validation set
    never = _run(tiny, val=False, plateau_min_epochs=NEVER, step_budget=8)
    assert never.info["stopped"].startswith("the step budget")  # a rule that never fires: the budget stops it


def test_the_paper_recipe_keeps_its_fixed_length(tiny):
    cfg = tiny_cfg()
    assert cfg["until"] == "epochs"
    data, val = load_arrays(tiny, "plain", cfg)
    res = training.train(get_method("plain"), cfg, data, val, 5, checkpointer=NoCheckpointer(),
                         show_progress=False)
    assert "stopped" not in res.info and res.info["epochs"] == cfg["epochs_stage1"]


@pytest.mark.parametrize("value", ["sometimes", 3])
def test_until_is_checked(value):
    from pipeline.runtime.errors import InputError
    from pipeline.profiles import load_profile

    with pytest.raises(InputError, match="train.until"):
        load_profile("paper", [f"train.until={value}"])


def test_the_epochs_cap_holds_without_room_for_a_decay(tiny):
    res = _run(tiny, epochs_stage1=1)
    assert res.info["epochs"] == 1 and res.info["steps_run"] == 2 and len(res.log) == 1


def _replayed_stop(curve: list[float], low_res: int, window: int, gain: float) -> int | None:
    """The full-side stable epoch at which the rule stops, replaying a recorded validation curve (None: never)."""
    scores = []
    for v in curve[low_res:]:
        scores.append(v)
        if schedule.plateau_reached(scores, gain, window):
            return len(scores)
    return None


def test_with_few_images_the_least_window_is_in_steps():
    """Replay the committed 16-image curves (2 steps an epoch): the epochs-only rule stopped after 8-17 full-side
    epochs; the least window in optimizer steps (train.plateau_min_steps) holds it to at least 256 steps."""
    import json

    from pipeline.params import PAPER, RECIPES

    doc = json.loads((REPO / "reports/scaling/progressive-64-n16-seeds42-3407-2026.json").read_text())
    n_train, epochs = doc["info"]["n_train"]["plain"], doc["info"]["epochs"]
    train = PAPER.train
    spe = schedule.steps_per_epoch(n_train, RECIPES["progressive"]["train"]["batch_size"])
    low_res = schedule.low_res_epochs(epochs, RECIPES["progressive"]["train"]["low_res_fraction"])
    assert spe == 2
    old = schedule.plateau_window(train.plateau_min_epochs, 0, spe)
    new = schedule.plateau_window(train.plateau_min_epochs, train.plateau_min_steps, spe)
    assert (old, new) == (8, 128)
    early = [_replayed_stop(r["val_iou_cal_curve"], low_res, old, train.plateau_gain) for r in doc["runs"]]
    late = [_replayed_stop(r["val_iou_cal_curve"], low_res, new, train.plateau_gain) for r in doc["runs"]]
    # the recorded runs: three stopped 8-17 full-side epochs after the schedule, as the replay does
    stopped = [r["stopped"].startswith("plateau") for r in doc["runs"]]
    assert [e is not None and e <= 17 for e in early] == stopped and sum(stopped) == 3
    # the window in steps: no stop before 128 full-side epochs (256 steps)
    assert all(e is None or e >= new for e in late)
    # 270 images at batch 8 (34 steps an epoch): the window stays the 8 epochs it was
    assert schedule.plateau_window(train.plateau_min_epochs, train.plateau_min_steps,
                                   schedule.steps_per_epoch(270, 8)) == 8


def test_a_decay_of_the_whole_run_is_refused_under_plateau():
    from pipeline.params import validate_section
    from pipeline.runtime.errors import InputError

    with pytest.raises(InputError, match="decay_fraction must be < 1 under until: plateau"):
        validate_section("train", tiny_cfg(until="plateau", decay_fraction=1.0))
    assert validate_section("train", tiny_cfg(until="epochs", decay_fraction=1.0))["decay_fraction"] == 1.0
