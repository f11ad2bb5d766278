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
