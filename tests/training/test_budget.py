"""`distill --time`: the time becomes Stage I's step budget once, in the project's params (issue 43)."""

from __future__ import annotations

import pytest
import yaml
from click.testing import CliRunner

import pipeline
from pipeline.training import budget
from pipeline.runtime.errors import InputError
from pipeline.profiles import load_profile
from tests.builders.teacher import checkpoint_folder, make_image_folder


def test_durations():
    assert [budget.parse_duration(t) for t in ("90s", "20m", "1.5h", "1h30m")] == [90, 1200, 5400, 5400]
    for bad in ("", "20", "soon", "0m", "-5m"):
        with pytest.raises(InputError, match="--time"):
            budget.parse_duration(bad)
    assert budget.steps_for(60, 0.5) == 120 and budget.steps_for(1, 5.0) == 1


def test_the_probe_times_real_steps():
    cfg = load_profile("distill", ["train.channels=[4,8,16]"])["train"]
    assert budget.step_seconds(cfg, 32) > 0


def test_time_is_converted_once_and_reused(monkeypatch):
    params = load_profile("distill")
    monkeypatch.setattr(budget, "step_seconds", lambda cfg, res, device="cpu": 0.5)
    out = budget.with_time_budget(params, "10s")
    assert out["train"]["step_budget"] == 20 and out["train"]["time_budget"] == "10s"
    assert out["train"]["until"] == "plateau"

    def no_probe(*a, **k):
        raise AssertionError("measured again")

    monkeypatch.setattr(budget, "step_seconds", no_probe)
    assert budget.with_time_budget(params, "10s", previous=out)["train"]["step_budget"] == 20
    assert budget.with_time_budget(params, None) is params


def test_half_side_epochs_are_priced_at_their_own_step_time():
    """Under `progressive` (160 of 220 epochs at half the side, decay 0.2): with t_f = 1 s, t_h = 0.25 s and 2
    steps an epoch, 100 s buy E = 100 stable epochs and D = 25 decay epochs: 2 (100 x 0.25 + 25 x 1) = 100 s,
    so 250 steps where pricing every step at full side gave 100 (a run of 40 s)."""
    from pipeline.methods import STAGE_ONE, get_method
    from pipeline.training.schedule import stable_cap
    from pipeline.training.settings import Settings

    train = load_profile("distill")["train"]
    assert budget.scheduled_steps(100, 1.0, 0.25, train, 2) == 250
    assert budget.scheduled_steps(100, 1.0, 1.0, train, 2) == 100  # no cheaper side: the old price
    run = Settings.from_params(get_method(STAGE_ONE), {**train, "step_budget": 250}, 0.5)
    assert stable_cap(run, 2) == 100  # the run plans exactly the epochs that were priced
    # past the epochs cap (176 stable + 44 decay = 2 (160 x 0.25 + 60 x 1) = 200 s), the rest buys full-side steps
    assert budget.scheduled_steps(300, 1.0, 0.25, train, 2) == 440 + 100


def test_distill_time_prices_the_schedule_over_the_folder_s_training_images(tmp_path, monkeypatch):
    make_image_folder(tmp_path / "data", n=10, masks=True)
    images, masks = tmp_path / "data" / "images", tmp_path / "data" / "masks"
    (masks / sorted(p.name for p in masks.iterdir())[0]).unlink()  # 9 masked images: 1 trains
    assert budget.training_images(images, masks, 0.1) == 1
    assert budget.training_images(images, None, 0.1) == 10 - 2  # the plateau rule holds 2 of 10 out
    sides = []

    def probe(cfg, res, device="cpu"):
        sides.append(res)
        return 1.0 if res == 384 else 0.25

    monkeypatch.setattr(budget, "step_seconds", probe)
    pipeline.distill(images, out=tmp_path / "run", checkpoint=checkpoint_folder(tmp_path / "sam3"), run=False,
                     time="90s")
    assert sorted(sides) == [192, 384]  # the distill profile's side, and its half
    # 8 training images, batch 8: one step an epoch.  E = 168 stable epochs (160 at half side) and D = 42:
    # 160 x 0.25 + (8 + 42) x 1 = 90 s; E = 169 takes 91 s.  Priced at full side, 90 s gave 90 steps.
    assert yaml.safe_load((tmp_path / "run" / "params.yaml").read_text())["train"]["step_budget"] == 168 + 42


def test_distill_time_writes_the_budget_into_the_project(tmp_path, monkeypatch):
    from pipeline.cli.main import main

    make_image_folder(tmp_path / "data", n=3, masks=False)
    images, sam3, out = tmp_path / "data" / "images", checkpoint_folder(tmp_path / "sam3"), tmp_path / "run"
    monkeypatch.setattr(budget, "step_seconds", lambda cfg, res, device="cpu": 2.0)
    args = ["distill", str(images), "--out", str(out), "--checkpoint", str(sam3), "--no-run", "--time", "20m"]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    train = yaml.safe_load((out / "params.yaml").read_text())["train"]
    assert train["step_budget"] == 600 and train["time_budget"] == "20m" and train["recipe"] == "progressive"
    text = (out / "params.yaml").read_text()
    monkeypatch.setattr(budget, "step_seconds", lambda cfg, res, device="cpu": 1.0)  # another measurement ...
    assert CliRunner().invoke(main, args).exit_code == 0
    assert (out / "params.yaml").read_text() == text  # ... is not taken: the same --time, the same params
    pipeline.distill(images, out=out, checkpoint=sam3, run=False, time="40m")  # a longer budget, in Python
    assert yaml.safe_load((out / "params.yaml").read_text())["train"]["step_budget"] == 2400
    r = CliRunner().invoke(main, [*args[:-1], "later"])
    assert r.exit_code == 2 and "--time 'later'" in r.output
    r = CliRunner().invoke(main, [*args, "--val-masks", str(tmp_path / "none")])  # the images are counted first
    assert r.exit_code == 2 and "--val-masks" in r.output and "Traceback" not in r.output


@pytest.mark.parametrize("precision, channels_last", [("fp32", False), ("bf16", True), ("auto", True)])
def test_the_probe_times_the_precision_and_memory_format_that_will_train(monkeypatch, precision, channels_last):
    """The probe's forward runs under the autocast the training step uses and on channels_last inputs and
    weights exactly when ``train.channels_last`` is set (it timed fp32 NCHW whatever trained)."""
    import torch

    from pipeline.runtime.device import autocast_dtype
    from pipeline.training import loop

    seen = []
    build = loop.build_model

    def recording_model(*a, **k):
        model = build(*a, **k)
        forward = model.forward_train

        def forward_train(x):
            seen.append((torch.is_autocast_enabled("cpu") and torch.get_autocast_dtype("cpu"),
                         x.is_contiguous(memory_format=torch.channels_last),
                         all(w.is_contiguous(memory_format=torch.channels_last)
                             for w in model.parameters() if w.dim() == 4)))
            return forward(x)

        model.forward_train = forward_train
        return model

    monkeypatch.setattr(loop, "build_model", recording_model)
    cfg = load_profile("distill", ["train.channels=[4,8,16]", f"train.precision={precision}",
                                   f"train.channels_last={str(channels_last).lower()}"])["train"]
    assert budget.step_seconds(cfg, 16) > 0
    amp = autocast_dtype(torch.device("cpu"), precision)
    assert len(seen) == 3 and all(s[0] == (amp if amp is not None else False) for s in seen), seen
    assert all(s[1] == s[2] == channels_last for s in seen), seen


def test_time_that_allows_more_raises_the_epochs_cap_with_its_schedule(monkeypatch):
    """`progressive` (220 epochs, 160 at half the side, decay 0.2), t_f = 1 s, t_h = 0.25 s, 2 steps an epoch:
    the whole run at cap C costs 2 (L(C) x 0.25 + (C - L(C)) x 1) s, 200 s at 220.  400 s buy the run at 440
    (320 at half the side: 2 (80 + 120) = 400 s), never more than time_cap_factor x 220; less time keeps 220."""
    from pipeline.methods import STAGE_ONE, get_method
    from pipeline.training.schedule import stable_cap
    from pipeline.training.settings import Settings

    train = load_profile("distill")["train"]
    assert budget.raised_cap(400, 1.0, 0.25, train, 2, 4.0) == 440
    from pipeline.training.schedule import decay_epochs, low_res_epochs

    def cost(cap):  # the whole run at ``cap``, priced independently: the most stable epochs that end by it
        e = max(k for k in range(1, cap + 1) if k + decay_epochs(k, 0.2) <= cap)
        low = low_res_epochs(cap, train["low_res_fraction"])
        return 2 * (min(e, low) * 0.25 + (e - min(e, low) + decay_epochs(e, 0.2)) * 1.0)

    for seconds in (401, 555, 777):  # the largest cap whose run fits, also where one more cap costs less
        cap = budget.raised_cap(seconds, 1.0, 0.25, train, 2, 4.0)
        assert cost(cap) <= seconds and all(cost(c) > seconds for c in range(cap + 1, 881))
    assert budget.raised_cap(10_000, 1.0, 0.25, train, 2, 4.0) == 880  # the factor bounds it
    assert budget.raised_cap(10_000, 1.0, 0.25, train, 2, 1.0) == 220  # 1: the cap never moves
    assert budget.raised_cap(100, 1.0, 0.25, train, 2, 4.0) == 220  # the run at the cap does not fit: kept
    monkeypatch.setattr(budget, "step_seconds", lambda cfg, res, device="cpu": 1.0 if res == 384 else 0.25)
    params = load_profile("distill")
    out = budget.with_time_budget(params, "400s", n_train=16)  # batch 8: 2 steps an epoch
    t = out["train"]
    assert (t["epochs_stage1"], t["time_raised_from"], t["step_budget"], t["until"]) == (440, 220, 880, "plateau")
    run = Settings.from_params(get_method(STAGE_ONE), t, 0.5)
    assert run.low_res_epochs == 320 and stable_cap(run, 2) == 352  # 352 + 88 decay = 440: the priced run
    assert params["train"]["epochs_stage1"] == 220  # the params given are not modified

    def no_probe(*a, **k):
        raise AssertionError("measured again")

    monkeypatch.setattr(budget, "step_seconds", no_probe)  # the same --time on the same cap: reused, as recorded
    assert budget.with_time_budget(params, "400s", previous=out, n_train=16)["train"] == t
    before = {**out, "train": {k: v for k, v in params["train"].items()
                               if k not in ("time_cap_factor", "time_raised_from")}}
    before["train"].update(time_budget="400s", step_budget=640)  # a project written before the cap could rise
    assert budget.with_time_budget(params, "400s", previous=before, n_train=16)["train"]["epochs_stage1"] == 220
    with pytest.raises(AssertionError, match="measured again"):  # another cap is priced again
        budget.with_time_budget(load_profile("distill", ["train.epochs_stage1=300"]), "400s", previous=out, n_train=16)
    monkeypatch.setattr(budget, "step_seconds", lambda cfg, res, device="cpu": 1.0 if res == 384 else 0.25)
    kept = budget.with_time_budget(load_profile("distill", ["train.time_cap_factor=1"]), "400s", n_train=16)["train"]
    assert (kept["epochs_stage1"], kept["time_raised_from"], kept["step_budget"]) == (220, 0, 440 + 200)  # the rest buys full-side steps
