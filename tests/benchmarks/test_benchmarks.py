"""The benchmark scripts still run (tiny sizes) and print a ratio against their baseline.

No timing is asserted here: performance targets live in the scripts' output, not in tests.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

from tests.builders.lane import BENCH_CASES

#: the scripts' tiny-size cases (tests/builders/lane.py; the Ray case has its own test below)
CASES = sorted(c for c in BENCH_CASES if not c.endswith("_ray"))


@pytest.mark.slow
@pytest.mark.parametrize("bench_script", CASES, indirect=True)
def test_benchmark_script_runs_and_reports_a_ratio(bench_script):
    """``python -m benchmarks.<name>`` at tiny sizes (run on the tests' second lane: tests/conftest.py)."""
    name, r = bench_script
    assert r.args[2] == f"benchmarks.{name}" and r.args[3:] == BENCH_CASES[name]
    assert r.returncode == 0, r.stderr[-2000:]
    assert re.search(r"\d+(\.\d+)?\s*x", r.stdout), r.stdout[-2000:]  # "<ratio> x" against the baseline


@pytest.mark.slow
def test_teacher_benchmark_on_ray_prints_each_pools_start_up_and_ratio(bench_teacher_ray):
    pytest.importorskip("ray")
    r = bench_teacher_ray  # --ray-workers 1,2 --images 8 --resolution 32 --repeats 1, on the second lane
    assert r.returncode == 0, r.stderr[-2000:]
    for pool in ("serial", "ray x1", "ray x2"):
        assert re.search(rf"{pool}\s+wall median .* images/s", r.stdout), r.stdout[-2000:]
        assert re.search(rf"{pool}\s+start-up median\s+\d+\.\d+ s", r.stdout), r.stdout[-2000:]
    assert re.search(r"ray x2\s+steady median .*\d\.\d\dx the 1-worker pool", r.stdout), r.stdout[-2000:]
    assert re.search(r"\n\s+8 images: ray x2 \d\.\d\dx the 1-worker pool", r.stdout), r.stdout[-2000:]


# ---- in-process smoke tests of the scripts the subprocess cases above do not cover (study_recipe's is
# tests/training/test_recipe_options.py::test_study_runs_end_to_end_on_tiny_artifacts) -------------------------
def test_stability_main_on_tiny_artifacts_prints_and_writes_its_summary(tmp_path, capsys, monkeypatch):
    """stability.main at 32 px, 1 + 1 epochs, seed 0 as is and under 1 thread: the data stages are skipped
    (their last output, gates, is in ``--workdir``: the training tests' tiny artifacts)."""
    import json
    import math

    import torch

    from benchmarks import stability
    from pipeline.thresholds import TAU_RULES
    from tests.builders.training import build_tiny_artifacts

    build_tiny_artifacts(tmp_path / "w" / "artifacts")
    monkeypatch.setenv("OMP_WAIT_POLICY", "PASSIVE")  # main sets it for the process; restored after the test
    out, floor = tmp_path / "stability.json", tmp_path / "noise_floor.json"
    threads = torch.get_num_threads()
    try:
        res = stability.main(["--workdir", str(tmp_path / "w"), "--resolution", "32", "--epochs", "1",
                              "--epochs-stage2", "1", "--seeds", "0", "--perturbations", "threads1",
                              "--recipes", "paper", "--jobs", "1", "--out", str(out), "--noise-floor", str(floor)])
    finally:
        torch.set_num_threads(threads)
    text = capsys.readouterr().out
    for rule in TAU_RULES:
        assert f"== recipe paper, tau rule {rule}: target" in text
    assert re.search(r"recipe\s+rule\s+plainIoU\s+geoIoU\s+contIoU", text), text[-2000:]
    assert f"wrote {floor} (record paper)" in text and f"wrote {out}" in text
    saved = json.loads(out.read_text())
    assert saved["info"]["seeds"] == saved["info"]["pert_seeds"] == [0]
    assert saved["info"]["epochs"] == {"paper": [1, 1]}  # --epochs wins over the recipe's lengths
    assert [(r["recipe"], r["rule"]) for r in saved["table"]] == [("paper", rule) for rule in TAU_RULES]
    for r in res["table"]:  # the moves under 1 thread: measured
        assert math.isfinite(r["move_threads1_iou"]) and math.isfinite(r["pert1_bf1"]), r
        assert 0.0 <= r["plain_iou"] <= 1.0 and 0.0 <= r["geodistill_bf1"] <= 1.0
    # every run is in <out>.runs.jsonl (after one settings line)
    runs = [json.loads(x) for x in (tmp_path / "stability.json.runs.jsonl").read_text().splitlines()]
    assert "info" in runs[0] and sorted((r["seed"], r["perturbation"]) for r in runs[1:]) == [
        (0, "default"), (0, "threads1")]
    assert list(json.loads(floor.read_text())["recipes"]) == ["paper"]


def test_bench_cluster_main_reports_nodes_and_the_outputs_that_differ(tmp_path, capsys, monkeypatch):
    """bench_cluster.main with Ray's Cluster and the driver replaced by recorders (a real two-node cluster
    and a DVC run take minutes; tests/cluster/test_run_ray.py runs the driver on Ray): its own part -- cluster set-up
    and shutdown, the comparison of the two dvc.lock files, what it prints and returns."""
    import json
    import types

    import yaml

    from benchmarks import bench_cluster
    from pipeline.cluster import driver

    calls = []

    class Cluster:
        address = "127.0.0.1:6379"

        def __init__(self, initialize_head, head_node_args):
            calls.append(("head", initialize_head, head_node_args))

        def add_node(self, **kw):
            calls.append(("node", kw))

        def shutdown(self):
            calls.append(("cluster down",))

    ray = types.ModuleType("ray")
    ray.init = lambda **kw: calls.append(("init", kw["address"]))
    ray.shutdown = lambda: calls.append(("ray down",))
    utils = types.ModuleType("ray.cluster_utils")
    utils.Cluster = Cluster
    ray.cluster_utils = utils
    monkeypatch.setitem(sys.modules, "ray", ray)
    monkeypatch.setitem(sys.modules, "ray.cluster_utils", utils)

    def run_pipeline(root, targets, echo):
        calls.append(("run", Path(root), targets))
        return driver.RunResult({"teacher": {"status": "ran", "node_id": "aaaaaaaa1111"},
                                 "train_plain@42": {"status": "ran", "node_id": "bbbbbbbb2222"}}, wall_s=1.0)

    monkeypatch.setattr(driver, "run_pipeline", run_pipeline)

    def lock(root, train_md5):
        root.mkdir()
        stages = {"teacher": {"outs": [{"path": "teacher.zarr", "md5": "t1"}]},
                  "train_plain@42": {"outs": [{"path": "ckpt", "md5": train_md5}]},
                  "report": {"outs": [{"path": "report", "md5": "r1"}]}}
        (root / "dvc.lock").write_text(yaml.safe_dump({"schema": "2.0", "stages": stages}))
        return root

    repo, serial = lock(tmp_path / "copy", "c1"), lock(tmp_path / "done", "c2")
    res = bench_cluster.main(["--repo", str(repo), "--serial", str(serial), "--targets", "train_plain@42",
                              "--cpus", "2", "--gpus", "1"])
    assert calls == [("head", True, {"num_cpus": 2, "num_gpus": 1}), ("node", {"num_cpus": 2, "num_gpus": 1}),
                     ("init", Cluster.address), ("run", repo, ("train_plain@42",)), ("ray down",), ("cluster down",)]
    assert res["ok"] and res["outputs"] == 2 and res["differ"] == ["train_plain@42:ckpt"]
    assert res["nodes"] == {"teacher": "aaaaaaaa", "train_plain@42": "bbbbbbbb"}
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("two nodes x 2 CPU x 1 fake GPU: 2 stages in ") and lines[0].endswith("2 nodes used")
    assert re.match(r"\s+teacher\s+node aaaaaaaa\s+ran$", lines[1]), lines
    assert lines[3] == "outputs equal to the serial dvc repro: 1 of 2; differ: ['train_plain@42:ckpt']"
    assert json.loads(lines[4]) == json.loads(json.dumps(res))


def test_simulator_stats_main_on_tiny_artifacts_prints_the_table(tmp_path, capsys):
    """``python -m benchmarks.simulator_stats`` in-process: the SIMULATOR over 8 drawn 32 px images (no
    params file: the paper's prompts), its statistics beside the paper's."""
    from benchmarks import simulator_stats
    from tests.builders.teacher import build_artifacts

    build_artifacts(tmp_path, n=8)
    assert simulator_stats.main(["--artifacts", str(tmp_path), "--params", str(tmp_path / "none.yaml"),
                                 "--seed", "0"]) == 0
    out = capsys.readouterr().out
    assert "teacher SIMULATOR vs paper" in out and "group test, 2 images" in out
    assert re.search(r"six-prompt vote Image IoU\s+\d\.\d{4}\s+0\.6833", out), out
