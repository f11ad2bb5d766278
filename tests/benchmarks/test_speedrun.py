"""Smoke test of the speedrun benchmark (benchmarks/speedrun.py) on the tiny training artifacts."""

from __future__ import annotations

import json

import pytest

from benchmarks import speedrun
from pipeline.training import schedule


def test_cost_and_pass_rule():
    assert speedrun.run_cost(400, 270, 128) == 108_000 and speedrun.run_cost(100, 270, 64) == 6_750
    # 160 epochs at half the side cost 40: the resolution schedule's candidate matches a quarter of the baseline
    assert speedrun.run_cost(220, 270, 64, low_res_epochs=160) == 6_750
    assert schedule.low_res_epochs(220, speedrun.CANDIDATES["half_res_first"][0]["low_res_fraction"]) == 160
    runs = [{"candidate": "baseline", "seed": s, "V": v, "V_05": v, "cost": 100.0} for s, v in ((1, 0.5), (2, 0.6))]
    runs += [{"candidate": "lr4", "seed": s, "V": v, "V_05": v, "cost": 25.0} for s, v in ((1, 0.56), (2, 0.56))]
    runs += [{"candidate": "lr2", "seed": s, "V": v, "V_05": v, "cost": 25.0} for s, v in ((1, 0.5), (2, 0.54))]
    rows = {r["candidate"]: r for r in speedrun.summarize(runs)}
    assert rows["baseline"]["V"] == pytest.approx(0.55) and rows["baseline"]["passes"] is None
    assert rows["lr4"]["passes"] and rows["lr4"]["cost_ratio"] == 0.25 and not rows["lr2"]["passes"]
    assert "| lr4 | 2 | 0.560 ± 0.000 |" in speedrun.table(list(rows.values()))


def test_candidate_changes_one_lever_on_strong():
    from pipeline.methods import get_method, method_lr

    base = {"lr_stage1": 5e-4, "lr_scale": 1.0, "average_last": 4, "epochs_stage1": 80, "batch_size": 8}
    assert method_lr(get_method("plain"), speedrun.candidate_cfg(base, "lr4")) == pytest.approx(2e-3)
    assert speedrun.candidate_cfg(base, "b32_lr4")["batch_size"] == 32
    assert speedrun.candidate_cfg(base, "ema_lr4")["average_last"] == 0
    assert speedrun.candidate_cfg({**base, "average_last": 0}, "strong_100")["average_last"] == 1


def test_speedrun_runs_and_resumes_on_tiny_artifacts(tiny, tmp_path, monkeypatch, capsys):
    small = {k: ({**v[0], "epochs_stage1": 4 if k == "baseline" else 1}, v[1]) for k, v in speedrun.CANDIDATES.items()}
    monkeypatch.setattr(speedrun, "CANDIDATES", small)
    out = tmp_path / "s.json"
    argv = ["--artifacts", str(tiny), "--resolution", "32", "--candidates", "baseline", "soft_lr4",
            "--seeds", "1", "2", "--out", str(out)]
    doc = speedrun.main(argv)
    rows = {r["candidate"]: r for r in doc["summary"]}
    assert set(rows) == {"baseline", "soft_lr4"} and rows["soft_lr4"]["cost_ratio"] == pytest.approx(0.25)
    assert rows["baseline"]["test_iou"] is None and "not scored" in speedrun.table(doc["summary"])
    assert all(0 <= r["V"] <= 1 for r in doc["runs"]) and len(doc["runs"]) == 4
    assert json.loads(out.read_text())["summary"] == doc["summary"]
    capsys.readouterr()
    again = speedrun.main(argv)  # every run is in --out: nothing trains again
    assert again["runs"] == doc["runs"] and "s1:" not in capsys.readouterr().out


def test_the_confirmation_scores_the_test_images_and_the_schedule_trains(tiny, tmp_path, monkeypatch):
    small = {"half_res_first": ({"epochs_stage1": 2, "low_res_fraction": 0.5}, "the schedule, tiny")}
    monkeypatch.setattr(speedrun, "CANDIDATES", small)
    doc = speedrun.main(["--artifacts", str(tiny), "--resolution", "32", "--candidates", "half_res_first",
                         "--seeds", "3", "--score-test", "--out", str(tmp_path / "c.json")])
    (run,), (row,) = doc["runs"], doc["summary"]
    assert 0 <= run["test_iou"] <= 1 and 0 <= run["test_iou_05"] <= 1 and row["test_iou"] == run["test_iou"]
    assert run["cost"] == speedrun.run_cost(2, 8, 32, low_res_epochs=1)
