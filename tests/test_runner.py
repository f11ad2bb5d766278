"""``geodistill run``: the scheduler (pipeline/runner.py) with fake jobs, then the real DAG in a temporary
copy of the repository on the tiny profile of tests/test_end_to_end.py (concurrency, DVC record, failure)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from pipeline.runner import (Job, Placement, Resources, child_env, error_line, overlapping, pick, priorities,
                             read_costs, run_jobs, topological_order, waves, write_timeline)

SH = "/bin/sh"


def job(name, needs=(), cmd="true", **kw):
    return Job(name, (SH, "-c", cmd), frozenset(needs), **kw)


def sleeper(name, needs=(), seconds=0.3, **kw):
    return job(name, needs, f"sleep {seconds}", **kw)


def max_concurrency(report) -> int:
    spans = [(r.start, r.end) for r in report.records.values() if r.start is not None]
    return max(sum(s <= t < e for s, e in spans) for t, _ in spans)


# --------------------------------------------------------------------------------------------------
# pure parts
# --------------------------------------------------------------------------------------------------
def test_topological_order_and_waves_respect_needs():
    jobs = [job("report", ["eval", "bench"]), job("eval", ["train"]), job("bench", ["export"]),
            job("export", ["train"]), job("train")]
    order = topological_order(jobs)
    assert order.index("train") < order.index("eval") < order.index("report")
    assert order.index("export") < order.index("bench")
    assert waves(jobs) == [["train"], ["eval", "export"], ["bench"], ["report"]]


@pytest.mark.parametrize("jobs, message", [
    ([job("a", ["b"])], "unknown"),
    ([job("a", ["b"]), job("b", ["a"])], "cycle"),
    ([job("a"), job("a")], "twice"),
])
def test_bad_graphs_are_errors(jobs, message):
    with pytest.raises(ValueError, match=message):
        topological_order(jobs)


def test_priority_is_the_longest_remaining_path_then_descendants():
    # plain -> {geodistill, gabi} -> calibrate; other (a Stage-I run) -> calibrate; teacher_stats alone
    jobs = [job("teacher_stats"), job("other"), job("plain"), job("geodistill", ["plain"]),
            job("gabi", ["plain"]), job("calibrate", ["geodistill", "gabi", "other"])]
    prio = priorities(jobs)
    assert sorted(prio, key=prio.get) == ["plain", "other", "geodistill", "gabi", "teacher_stats", "calibrate"]
    # measured costs move a long independent job ahead
    costly = priorities(jobs, costs={"teacher_stats": 100.0})
    assert min(costly, key=costly.get) == "teacher_stats"


def test_pick_bounds_processes_and_shares_threads():
    queue = [job(n) for n in "abcde"]
    started = pick(queue, {}, Resources(jobs=3, cores=8))
    assert [j.name for j, _ in started] == ["a", "b", "c"]
    assert [p.threads for _, p in started] == [3, 3, 2] and all(p.device is None for _, p in started)
    # with 7 of 8 cores held, a newcomer still gets cores // jobs threads; a full pool starts nothing
    running = {"x": (job("x"), Placement(None, 7))}
    assert [p.threads for _, p in pick(queue, running, Resources(jobs=2, cores=8))] == [4]
    assert [p.threads for _, p in pick(queue, running, Resources(jobs=8, cores=8))][0] == 1
    running["y"] = (job("y"), Placement(None, 1))
    assert pick(queue, running, Resources(jobs=2, cores=8)) == []


def test_pick_places_gpu_jobs_round_robin_within_slots_and_cpu_jobs_beside_them():
    res = Resources(jobs=8, cores=8, gpu_slots={"0": 2, "1": 1})
    queue = [job(f"t{i}", gpu=True) for i in range(5)] + [job("cpu")]
    started = pick(queue, {}, res)
    devices = {j.name: p.device for j, p in started}
    assert devices == {"t0": "0", "t1": "1", "t2": "0", "cpu": None}  # t3, t4 wait for a GPU slot
    # without GPUs a GPU-capable job is a CPU job
    assert pick([job("t", gpu=True)], {}, Resources(jobs=1, cores=2))[0][1] == Placement(None, 2)


def test_exclusive_job_waits_for_an_empty_pool_and_runs_alone():
    bench = job("bench", exclusive=True)
    running = {"eval": (job("eval"), Placement(None, 1))}
    res = Resources(jobs=4, cores=4)
    assert pick([bench, job("later")], running, res) == []  # drains: nothing starts beside or before it
    assert [j.name for j, _ in pick([job("first"), bench], running, res)] == ["first"]  # higher priority goes
    assert pick([bench, job("later")], {}, res) == [(bench, Placement(None, 4))]  # alone, every core
    assert pick([job("later")], {"bench": (bench, Placement(None, 4))}, res) == []


def test_child_env_sets_threads_and_device():
    env = child_env({"PATH": "/bin", "CUDA_VISIBLE_DEVICES": "0,1"}, job("a", env={"X": "1"}), Placement("1", 3), True)
    assert env["OMP_NUM_THREADS"] == env["MKL_NUM_THREADS"] == "3" and env["X"] == "1"
    assert env["CUDA_VISIBLE_DEVICES"] == "1"
    assert child_env({}, job("a"), Placement(None, 2), True)["CUDA_VISIBLE_DEVICES"] == ""  # CPU job: no GPU
    assert "CUDA_VISIBLE_DEVICES" not in child_env({}, job("a"), Placement(None, 2), False)


def test_error_line_prefers_the_one_line_error():
    log = "INFO starting\nTraceback (most recent call last):\n  x\nValueError: boom\n"
    assert error_line(log) == "ValueError: boom"
    assert error_line("x\ngeodistill calibrate: error: params.yaml: bad key\n\n") == \
        "geodistill calibrate: error: params.yaml: bad key"
    assert error_line("") == "(no output)"


def fake_nvidia_smi(folder: Path, rows: str) -> Path:
    """An ``nvidia-smi`` that prints ``rows`` (index, free MiB) whatever it is asked: GPU paths on a CPU machine."""
    folder.mkdir(parents=True, exist_ok=True)
    exe = folder / "nvidia-smi"
    exe.write_text(f"#!/bin/sh\nprintf '{rows}'\n")
    exe.chmod(0o755)
    return folder


def test_gpu_detection_and_default_slots(tmp_path):
    from stages.run import GPU_JOB_MIB, default_gpu_jobs, detect_gpus, parse_gpus

    bin_dir = str(fake_nvidia_smi(tmp_path, "0, 81000\n1, 2000\n"))
    assert detect_gpus({"PATH": bin_dir}) == {"0": 81000, "1": 2000}
    assert detect_gpus({"PATH": bin_dir, "CUDA_VISIBLE_DEVICES": "1"}) == {"1": 2000}
    assert detect_gpus({"PATH": bin_dir, "CUDA_VISIBLE_DEVICES": ""}) == {}  # GPUs hidden on purpose
    assert detect_gpus({"PATH": bin_dir, "CUDA_VISIBLE_DEVICES": "MIG-abc"}) == {"MIG-abc": 2000}
    assert detect_gpus({"PATH": str(tmp_path / "none")}) == {}
    # an H100 with 16 cores: memory allows 19, the cores 8 (the hand-orchestrated paper run used 8)
    assert default_gpu_jobs(80000, 16, 1) == 8 and default_gpu_jobs(3 * GPU_JOB_MIB, 16, 1) == 3
    assert default_gpu_jobs(100, 2, 1) == 1
    assert parse_gpus(None, {"0": 5}) == {"0": 5} and parse_gpus("none", {"0": 5}) == {}
    assert parse_gpus("0,2", {"0": 5}) == {"0": 5, "2": 0}
    from pipeline.errors import InputError

    with pytest.raises(InputError, match="--gpus"):
        parse_gpus("first", {})


# --------------------------------------------------------------------------------------------------
# the process pool with fake jobs
# --------------------------------------------------------------------------------------------------
def test_run_jobs_respects_needs_and_the_bound(tmp_path):
    jobs = [sleeper("prep", seconds=0.1)] + [sleeper(f"train{i}", ["prep"]) for i in range(4)] + \
           [sleeper("report", [f"train{i}" for i in range(4)], seconds=0.1)]
    recorded = []
    report = run_jobs(jobs, Resources(jobs=2, cores=2), tmp_path / "logs", record=lambda j: recorded.append(j.name),
                      echo=lambda s: None, poll_s=0.02)
    assert report.ok and set(recorded) == {j.name for j in jobs} and recorded[-1] == "report"
    r = report.records
    for j in jobs:
        for m in j.needs:
            assert r[j.name].start >= r[m].end, (j.name, m)
    assert max_concurrency(report) == 2  # the four training runs overlap, two at a time
    assert overlapping(report, ["train0", "train1"])
    assert r["prep"].threads == r["report"].threads == 2  # alone: every core
    assert all(r[f"train{i}"].threads == 1 for i in range(4))  # two at a time: one core each


def test_run_jobs_passes_threads_and_device_to_the_process(tmp_path):
    out = tmp_path / "env.txt"
    jobs = [job("gpu", cmd=f'echo "$OMP_NUM_THREADS $CUDA_VISIBLE_DEVICES" > {out}', gpu=True)]
    report = run_jobs(jobs, Resources(jobs=1, cores=6, gpu_slots={"3": 1}), tmp_path, echo=lambda s: None,
                      base_env={"PATH": os.environ["PATH"]}, poll_s=0.02)
    assert report.ok and out.read_text().split() == ["6", "3"]


def test_prepare_false_skips_the_job_and_its_dependents_still_run(tmp_path):
    marker = tmp_path / "ran"
    jobs = [job("a", cmd=f"touch {marker}"), job("b", ["a"], cmd="true")]
    report = run_jobs(jobs, Resources(jobs=2, cores=2), tmp_path, prepare=lambda j: j.name != "a",
                      echo=lambda s: None, poll_s=0.02)
    assert report.ok and not marker.exists()
    assert report.records["a"].status == "up_to_date" and report.records["b"].status == "ran"


def test_failure_stops_dependents_and_reports_its_error_line(tmp_path):
    jobs = [job("bad", cmd="echo working; echo 'geodistill calibrate: error: thresholds: no runs' >&2; exit 2"),
            sleeper("side", seconds=0.5), job("after_bad", ["bad"]), job("after_side", ["side"])]
    recorded, lines = [], []
    report = run_jobs(jobs, Resources(jobs=2, cores=2), tmp_path, record=lambda j: recorded.append(j.name),
                      echo=lines.append, poll_s=0.02)
    r = report.records
    assert not report.ok and report.failed() == ["bad"]
    assert r["bad"].error == "exit 2: geodistill calibrate: error: thresholds: no runs"
    assert r["side"].status == "ran" and recorded == ["side"]  # the running job finished and was recorded
    assert r["after_bad"].status == "not_run" and r["after_side"].status == "not_run"  # fail-fast
    assert any("FAILED bad" in ln and "no runs" in ln for ln in lines)
    # --keep-going: independent work goes on, the failure's dependents still do not run
    report = run_jobs(jobs, Resources(jobs=2, cores=2), tmp_path, keep_going=True, echo=lambda s: None, poll_s=0.02)
    assert report.records["after_side"].status == "ran" and report.records["after_bad"].status == "not_run"


def test_exceptions_from_the_hooks_fail_the_job(tmp_path):
    def prepare(j):
        if j.name == "b":
            raise RuntimeError("dvc: stage b is broken\nmore")
        return True

    report = run_jobs([job("a"), job("b"), job("c", ["b"])], Resources(jobs=1, cores=1), tmp_path,
                      prepare=prepare, echo=lambda s: None, poll_s=0.02)
    assert report.records["b"].error == "RuntimeError: dvc: stage b is broken"
    assert report.records["c"].status == "not_run"


def test_timeline_keeps_costs_of_jobs_that_did_not_run(tmp_path):
    report = run_jobs([sleeper("a", seconds=0.1), job("b")], Resources(jobs=2, cores=2), tmp_path,
                      prepare=lambda j: j.name == "a", echo=lambda s: None, poll_s=0.02)
    path = write_timeline(report, tmp_path / "timeline.json", costs={"b": 7.0, "gone": 1.0})
    data = json.loads(path.read_text())
    assert data["jobs"]["b"]["status"] == "up_to_date"
    costs = read_costs(path)
    assert costs["b"] == 7.0 and 0.1 <= costs["a"] < 5
    assert read_costs(tmp_path / "missing.json") == {}


# --------------------------------------------------------------------------------------------------
# the real DAG, tiny profile, in a copy of the repository
# --------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_repo(tmp_path_factory):
    import shutil

    from pipeline.params import deep_merge
    from tests.test_end_to_end import TINY_DEMO, _copy_repo

    if shutil.which("git") is None:
        pytest.skip("git not available")
    repo = tmp_path_factory.mktemp("runrepo")
    _copy_repo(repo)
    # one fake GPU: the runner places the GPU stages on it (CUDA_VISIBLE_DEVICES=0), CPU torch ignores it
    gpu_bin = fake_nvidia_smi(tmp_path_factory.mktemp("gpu"), "0, 16000\n")
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}:{gpu_bin}:{os.environ['PATH']}",
           "PYTHONPATH": str(repo), "GEODISTILL_QUIET": "1"}
    env.pop("CUDA_VISIBLE_DEVICES", None)
    run = lambda *a: subprocess.run(list(a), cwd=repo, env=env, capture_output=True, text=True)  # noqa: E731
    # params.yaml and dvc.yaml from the code (that the committed ones are current is test_params_and_dag's job)
    for cmd in (["profile", "demo"], ["dag"]):
        assert run(sys.executable, "-m", "stages.cli", *cmd).returncode == 0
    params = yaml.safe_load((repo / "params.yaml").read_text())
    # two independent training runs (plain@42 and plain@7) so that the runner has something to overlap
    params = deep_merge(params, TINY_DEMO)
    params["protocol"]["runs"]["plain"] = [42, 7]
    (repo / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    for cmd in (["git", "init", "-q"], [sys.executable, "-m", "dvc", "config", "core.analytics", "false"]):
        assert run(*cmd).returncode == 0
    return repo, run


def _geodistill_run(run, *args):
    return run(sys.executable, "-m", "stages.cli", "run", *args)


@pytest.mark.slow
def test_runner_runs_the_dag_concurrently_and_dvc_records_it(tiny_repo):
    repo, run = tiny_repo
    first = _geodistill_run(run, "--jobs", "3", "--gpu-jobs", "2", "--teacher-shards", "2")
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    timeline = json.loads((repo / "artifacts" / "logs" / "run" / "timeline.json").read_text())
    jobs = timeline["jobs"]
    stages = run(sys.executable, "-m", "dvc", "stage", "list", "--name-only").stdout.split()
    assert {"train_plain@42", "train_plain@7", "train_geodistill@42", "report"} <= set(stages)
    assert all(jobs[s]["status"] == "ran" for s in stages), {s: jobs[s]["status"] for s in stages}
    assert overlapping(timeline, ["train_plain@42", "train_plain@7"])  # two training runs at once
    assert jobs["train_geodistill@42"]["start"] >= jobs["train_plain@42"]["end"]
    assert timeline["resources"]["gpu_slots"] == {"0": 2}
    assert jobs["train_plain@42"]["device"] == "0" and "device" not in jobs["geometry"]  # geometry: CPU only
    # the teacher ran as two shard processes; the stage itself then only assembled from the cache
    assert overlapping(timeline, ["teacher#shard0", "teacher#shard1"])
    assert "computed 0 answers" in (repo / "artifacts" / "logs" / "run" / "teacher.log").read_text()
    assert jobs["benchmark"]["threads"] == timeline["resources"]["cores"]
    assert not any(j["start"] < jobs["benchmark"]["end"] and j["end"] > jobs["benchmark"]["start"]
                   for n, j in jobs.items() if n != "benchmark")  # it measured time alone
    # DVC is the record: every stage in dvc.lock, nothing stale, a second dvc repro / run does nothing
    lock = yaml.safe_load((repo / "dvc.lock").read_text())["stages"]
    assert set(stages) <= set(lock)
    status = run(sys.executable, "-m", "dvc", "status")
    assert "up to date" in status.stdout, status.stdout
    again = run(sys.executable, "-m", "dvc", "repro")
    assert again.returncode == 0 and "Running stage" not in again.stdout, again.stdout[-2000:]
    second = _geodistill_run(run)
    assert second.returncode == 0 and " 0 ran," in second.stdout, second.stdout[-2000:]


@pytest.mark.slow
def test_runner_failure_stops_dependents_and_keeps_finished_stages(tiny_repo):
    repo, run = tiny_repo
    if not (repo / "artifacts" / "logs" / "run" / "timeline.json").exists():
        pytest.skip("needs the successful run of the previous test")
    # calibrate fails (its code changed: stale); analyze_teacher also changed and is independent of it
    cal = repo / "stages" / "calibrate.py"
    future = "from __future__ import annotations\n"
    cal.write_text(cal.read_text().replace(future, future + 'raise SystemExit("geodistill calibrate: error: injected failure")\n', 1))
    with open(repo / "stages" / "analyze_teacher.py", "a") as f:
        f.write("\n# changed\n")
    failed = _geodistill_run(run, "--jobs", "2")
    assert failed.returncode == 1
    err = [ln for ln in failed.stderr.splitlines() if ln.startswith("geodistill run: error:")]
    assert len(err) == 1 and "stage calibrate failed" in err[0] and "injected failure" in err[0], failed.stderr
    jobs = json.loads((repo / "artifacts" / "logs" / "run" / "timeline.json").read_text())["jobs"]
    assert jobs["calibrate"]["status"] == "failed"
    for dependent in ("evaluate", "export", "benchmark", "report"):
        assert jobs[dependent]["status"] == "not_run"
    assert jobs["analyze_teacher"]["status"] == "ran" and jobs["train_plain@42"]["status"] == "up_to_date"
    # the finished stage is recorded, the failed one is not: a rerun resumes at calibrate
    status = run(sys.executable, "-m", "dvc", "status", "--json")
    stale = set(json.loads(status.stdout))
    assert "calibrate" in stale and "analyze_teacher" not in stale, stale
