"""The convergence benchmark (benchmarks/convergence.py): branch lengths, the plateau rule, and
a tiny end-to-end run whose decay branches start from the stable phase's saved states."""

from __future__ import annotations

import json

import pytest

from benchmarks.convergence import BranchStore, branch_epochs, decay_epochs, main, plateau


def test_lengths_and_the_plateau_rule():
    assert branch_epochs(5, 3) == [5, 10, 20, 40]
    assert decay_epochs(8, 0.2) == 2 and decay_epochs(1, 0.2) == 1  # at least one decay epoch
    assert plateau([0.40, 0.50, 0.53, 0.534, 0.60]) == 2  # 0.53 -> 0.534 gains < 0.005
    assert plateau([0.40, 0.50, 0.56]) is None
    assert plateau([0.50, 0.49]) == 0  # a loss is no gain


def test_tiny_study_runs_both_methods_and_scores_test_once(tiny, tmp_path):
    out = tmp_path / "conv.json"
    doc = main(["--artifacts", str(tiny), "--profile", "demo", "--first", "1", "--doublings", "1",
                "--threads", "1", "--set", "train.precision=fp32", "--out", str(out),
                "--states", str(tmp_path / "s")])
    assert json.loads(out.read_text()) == json.loads(json.dumps(doc))
    for m in ("plain", "supervised_ceiling"):
        r = doc["methods"][m]
        assert [c["stable_epochs"] for c in r["curve"]] == [1, 2]
        assert [c["epochs"] for c in r["curve"]] == [2, 3] and r["curve"][1]["steps"] > r["curve"][0]["steps"]
        assert all(0 <= c["val_iou_cal"] <= 1 for c in r["curve"]) and 0 <= r["test_iou"] <= 1
    # different labels, different curves; a rerun resumes (nothing retrained)
    assert doc["methods"]["plain"]["curve"] != doc["methods"]["supervised_ceiling"]["curve"]
    again = main(["--artifacts", str(tiny), "--profile", "demo", "--first", "1", "--doublings", "1",
                  "--threads", "1", "--set", "train.precision=fp32", "--out", str(out),
                "--states", str(tmp_path / "s")])
    assert again["methods"] == doc["methods"]


def test_more_doublings_continue_the_saved_stable_phase(tiny, tmp_path):
    """A rerun with one more doubling trains only the new branch, from the last saved stable state, and
    gives the curve a study of that length from scratch gives."""
    base = ["--artifacts", str(tiny), "--profile", "demo", "--first", "1", "--threads", "1",
            "--set", "train.precision=fp32", "--methods", "plain"]
    grown = tmp_path / "grown"
    short = main([*base, "--doublings", "1", "--out", str(grown / "c.json"), "--states", str(grown / "s")])
    store = next((grown / "s").iterdir())
    assert sorted(p.name for p in store.iterdir()) == ["decay-00001", "decay-00002", "stable-00001", "stable-00002"]
    # the longer stable run resumes from the last saved state; a state of another run is not used
    saved = BranchStore(store, [1, 2, 4])
    key = saved.state(2)["run_key"]
    assert saved.load({**key, "epochs": 4})["epoch"] == 2
    assert saved.load({**key, "epochs": 4, "seed": key["seed"] + 1}) is None
    longer = main([*base, "--doublings", "2", "--out", str(grown / "c.json"), "--states", str(grown / "s")])
    curve = longer["methods"]["plain"]["curve"]
    assert curve[:2] == short["methods"]["plain"]["curve"]  # the finished branches are kept, not retrained
    assert "stable_seconds" in curve[2] and (store / "stable-00004").is_dir()
    fresh = main([*base, "--doublings", "2", "--out", str(tmp_path / "fresh.json"), "--states", str(tmp_path / "fs")])
    strip = lambda c: [{k: v for k, v in r.items() if not k.endswith("seconds")} for r in c]  # noqa: E731
    assert strip(curve) == strip(fresh["methods"]["plain"]["curve"])
    assert longer["methods"]["plain"]["test_iou"] == fresh["methods"]["plain"]["test_iou"]


def test_a_file_that_is_not_a_study_is_refused_and_kept(tiny, tmp_path):
    """--out naming a user's own file: exit 2, one line, the file untouched."""
    mine = tmp_path / "notes.json"
    mine.write_text("my notes, not JSON")
    with pytest.raises(SystemExit) as e:
        main(["--artifacts", str(tiny), "--profile", "demo", "--out", str(mine), "--states", str(tmp_path / "s")])
    assert e.value.code == 2 and mine.read_text() == "my notes, not JSON"
