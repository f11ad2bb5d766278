"""``geodistill run`` on Ray (pipeline/cluster/): the plan from DVC's public commands, then a tiny DVC
project shaped like ours (teacher -> two training runs -> benchmark -> report) run on one shared local
Ray session with fake GPUs, against a serial ``dvc repro``; a SIGKILLed driver; a second driver."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.cluster import plan

ROOT = Path(__file__).resolve().parents[2]

DOT = """strict digraph {
"prepare";
"teacher";
"train_plain@42";
"train_plain@7";
"export";
"benchmark";
"report";
"analyze_teacher";
"data.dvc";
"data.dvc" -> "prepare";
"prepare" -> "teacher";
"teacher" -> "train_plain@42";
"teacher" -> "train_plain@7";
"teacher" -> "analyze_teacher";
"train_plain@42" -> "export";
"export" -> "benchmark";
"benchmark" -> "report";
"analyze_teacher" -> "report";
}
"""


def test_plan_from_dvc_dag_and_status():
    order, needs = plan.parse_dot(DOT)
    assert order[0] == "prepare" and "data.dvc" not in needs  # imported data is no stage
    assert needs["report"] == {"benchmark", "analyze_teacher"} and needs["prepare"] == set()
    # stale: the teacher -> it and everything downstream; prepare (up to date) is not submitted
    assert plan.to_submit(needs, {"teacher"}) == set(order) - {"prepare"}
    assert plan.to_submit(needs, {"teacher"}, targets=["export"]) == {"teacher", "train_plain@42", "export"}
    assert plan.to_submit(needs, set()) == set()
    # the benchmark runs alone: after every stage that is not downstream of it
    alone = plan.run_alone(needs)
    assert alone["benchmark"] == set(order) - {"benchmark", "report"} and alone["report"] == needs["report"]
    # longest remaining path first: train_plain@42 (-> export -> benchmark -> report) before @7
    seq = plan.submission_order(alone, order=order)
    assert seq.index("train_plain@42") < seq.index("train_plain@7")
    assert all(seq.index(u) < seq.index(n) for n in seq for u in alone[n])
    # last run's seconds move a long independent stage ahead
    assert plan.submission_order(needs, costs={"train_plain@7": 100.0}, order=order).index("train_plain@7") \
        < plan.submission_order(needs, costs={"train_plain@7": 100.0}, order=order).index("train_plain@42")
    with pytest.raises(ValueError, match="cycle"):
        plan.topological({"a": {"b"}, "b": {"a"}})


def test_a_stage_ready_early_does_not_take_the_core_the_critical_path_needs_next():
    """Two cores; the ceilings need only the data, Plain needs teacher -> consensus -> geometry.  Handed to Ray
    all at once, ceiling@7 (ready since prepare) took the core the teacher freed before consensus (FIFO)."""
    needs = {"prepare": set(), "teacher": {"prepare"}, "consensus": {"teacher"}, "geometry": {"consensus"},
             **{f"train_supervised_ceiling@{s}": {"prepare"} for s in (42, 7)},
             **{f"train_plain@{s}": {"geometry"} for s in (42, 7)},
             **{f"train_geodistill@{s}": {f"train_plain@{s}"} for s in (42, 7)},
             "evaluate": {f"train_{m}@{s}" for m in ("geodistill", "supervised_ceiling") for s in (42, 7)}}
    seq = plan.submission_order(needs, costs={"teacher": 10, **{f"train_{m}@{s}": 600 for m in
                                                                 ("plain", "supervised_ceiling") for s in (42, 7)}})
    res = {n: {"num_cpus": 1.0, "num_gpus": 0.0} for n in needs}
    cap = plan.Sizing(node_cpus=2).capacity
    one = {"num_cpus": 1.0, "num_gpus": 0.0}
    assert plan.startable(seq, needs, [], {}, res, cap) == ["prepare"]
    # prepare done: the teacher and one ceiling fill the two cores
    assert plan.startable(seq, needs, ["prepare"], {}, res, cap) == ["teacher", "train_supervised_ceiling@42"]
    # the teacher done: its core goes to consensus, not to the other ceiling
    running = {"train_supervised_ceiling@42": one}
    assert plan.startable(seq, needs, ["prepare", "teacher"], running, res, cap) == ["consensus"]
    # geometry done: Plain before the waiting ceiling
    assert plan.startable(seq, needs, ["prepare", "teacher", "consensus", "geometry"], running, res, cap)[0] \
        == "train_plain@42"
    # a stage larger than the cluster still runs, alone
    big = {**res, "prepare": {"num_cpus": 8.0, "num_gpus": 0.0}}
    assert plan.startable(seq, needs, [], {}, big, cap) == ["prepare"]
    assert plan.Sizing(node_cpus=2, cluster_cpus=6).capacity["num_cpus"] == 6


def test_pinned_train_threads_read_from_params(tmp_path):
    from pipeline.cluster.driver import pinned_train_threads

    assert pinned_train_threads(tmp_path) == 0  # no params.yaml
    (tmp_path / "params.yaml").write_text("train:\n  num_threads: 2\n")
    assert pinned_train_threads(tmp_path) == 2
    (tmp_path / "params.yaml").write_text("train:\n  num_threads: 0\n")
    assert pinned_train_threads(tmp_path) == 0


def test_the_guard_runs_a_command_as_python_c_and_returns_its_exit_code():
    """pipeline.cluster.guard.command: CMD runs under the guard (``python -c``, no script in the library);
    the guard's exit code is CMD's; a malformed command line is the usage line and exit 2."""
    from pipeline.cluster import guard

    r = subprocess.run(guard.command(os.getpid(), [sys.executable, "-c", "print('ran'); raise SystemExit(3)"]),
                       capture_output=True, text=True, start_new_session=True, timeout=60)
    assert (r.returncode, r.stdout.strip()) == (3, "ran")
    r = subprocess.run([sys.executable, "-c", guard.ENTRY, "1"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "usage" in r.stderr


def test_stage_resources_follow_the_cluster():
    gpu = plan.Sizing(node_cpus=16, gpus=2, stage_cpus=4, train_gpu_fraction=0.25)
    assert plan.stage_resources("teacher", gpu) == {"num_cpus": 1.0, "num_gpus": 1.0}
    assert plan.stage_resources("train_geodistill@42", gpu) == {"num_cpus": 1.0, "num_gpus": 0.25}
    assert plan.stage_resources("geometry", gpu) == {"num_cpus": 4.0, "num_gpus": 0.0}
    assert plan.stage_resources("benchmark", gpu) == {"num_cpus": 16.0, "num_gpus": 0.0}  # a whole node
    cpu = plan.Sizing(node_cpus=2, gpus=0, stage_cpus=8)
    assert plan.stage_resources("teacher", cpu) == {"num_cpus": 2.0, "num_gpus": 0.0}  # capped at a node
    # a training run pinned to 2 torch threads takes 2 cores, not the 1 a CPU stage gets (two such runs on
    # 2 cores would run 4 busy threads); unpinned (0) it takes the CPU stage's share; never over a node
    pinned = plan.Sizing(node_cpus=2, gpus=0, stage_cpus=1, train_threads=2)
    assert plan.stage_resources("train_plain@42", pinned) == {"num_cpus": 2.0, "num_gpus": 0.0}
    assert plan.stage_resources("train_plain", pinned) == {"num_cpus": 2.0, "num_gpus": 0.0}  # a seed group
    assert plan.stage_resources("calibrate", pinned) == {"num_cpus": 1.0, "num_gpus": 0.0}
    assert plan.stage_resources("train_plain@42", plan.Sizing(node_cpus=2, stage_cpus=1)) == {"num_cpus": 1.0,
                                                                                             "num_gpus": 0.0}
    assert plan.stage_resources("train_plain@42", plan.Sizing(node_cpus=2, stage_cpus=1, train_threads=8)) \
        == {"num_cpus": 2.0, "num_gpus": 0.0}
    assert plan.outcome("Running stage 'a':\n> x") == "ran"
    assert plan.outcome("Stage 'a' is cached - skipping run, checking out outputs") == "restored"
    assert plan.outcome("Stage 'a' didn't change, skipping") == "up_to_date"
    assert plan.error_line("x\nERROR: failed to reproduce 'a': boom\n\n") == "ERROR: failed to reproduce 'a': boom"


# --------------------------------------------------------------------------------------------------
# a tiny DVC project with our stage names, on one shared Ray session
# --------------------------------------------------------------------------------------------------
_IMPORTS = "import os, sys, time; "
DVC_YAML = """\
stages:
  teacher:
    cmd: python -c "{teacher}"
    deps: [seed.txt]
    outs: [teacher.txt]
  train_plain:
    matrix:
      seed: [1, 2]
    cmd: python -c "{train}" ${{item.seed}}
    deps: [teacher.txt]
    outs: ["train_${{item.seed}}.txt"]
  benchmark:
    cmd: python -c "{bench}"
    deps: [train_1.txt]
    outs: [bench.txt]
  report:
    cmd: cat teacher.txt train_1.txt train_2.txt bench.txt > report.txt
    deps: [teacher.txt, train_1.txt, train_2.txt, bench.txt]
    outs: [report.txt]
""".format(
    teacher=_IMPORTS + "open('teacher.txt', 'w').write(open('seed.txt').read() * 2); "
            "open('teacher_gpu.txt', 'w').write(os.environ.get('CUDA_VISIBLE_DEVICES', '-'))",
    # with GEODISTILL_TEST_MEET (forwarded by the driver), each run waits up to 120 s for the other to start and
    # marks that it met it: overlap without timing, which a loaded machine's worker start-up breaks ("lambda:" without
    # a space: ": " would end a YAML plain scalar)
    train=_IMPORTS + "s = sys.argv[1]; d = os.environ.get('GEODISTILL_TEST_MEET'); "
          "d and open(os.path.join(d, 'in_' + s), 'w').close(); t = time.time(); "
          "seen = lambda:sum(n.startswith('in_') for n in os.listdir(d)) if d else 2; "
          "[time.sleep(0.05) for _ in iter(lambda:seen() < 2 and time.time() - t < 120, False)]; "
          "d and seen() == 2 and open(os.path.join(d, 'met_' + s), 'w').close(); "
          "open(f'train_{s}.txt', 'w').write(open('teacher.txt').read() + s)",
    bench=_IMPORTS + "open('bench.txt', 'w').write(open('train_1.txt').read()[::-1]); "
          "open('bench_threads.txt', 'w').write(os.environ.get('OMP_NUM_THREADS', '-'))")
OUTS = ("teacher.txt", "train_1.txt", "train_2.txt", "bench.txt", "report.txt")


def _env():
    return {**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}", "PYTHONPATH": str(ROOT)}


def _sh(repo, *argv, **kw):
    return subprocess.run(list(argv), cwd=repo, env=_env(), capture_output=True, text=True, **kw)


def _project(path: Path, dvc_yaml: str = DVC_YAML) -> Path:
    path.mkdir(parents=True)
    (path / "seed.txt").write_text("s")
    (path / "dvc.yaml").write_text(dvc_yaml)
    for argv in (["git", "init", "-q"], [sys.executable, "-m", "dvc", "init", "-q"],
                 [sys.executable, "-m", "dvc", "config", "core.analytics", "false"]):
        assert _sh(path, *argv).returncode == 0
    return path


@pytest.fixture(scope="module")
def ray_session():
    ray = pytest.importorskip("ray")
    if shutil.which("git") is None:
        pytest.skip("git not available")
    ray.init(num_cpus=2, num_gpus=2, include_dashboard=False, log_to_driver=False, logging_level="WARNING",
             runtime_env={"env_vars": {"PYTHONPATH": str(ROOT)}})
    # two warm workers: on a loaded 2-core machine starting a second worker can take longer than a stage
    def nap(seconds):  # defined here: pickled by value (the tests folder is not on the workers' path)
        time.sleep(seconds)

    ray.get([ray.remote(num_cpus=1)(nap).remote(2.0) for _ in range(2)])
    yield ray
    ray.shutdown()


def test_run_on_ray_equals_serial_dvc_repro_and_dvc_records_it(ray_session, tmp_path, monkeypatch):
    from pipeline.cluster.driver import run_pipeline

    monkeypatch.setenv("PATH", _env()["PATH"])
    meet = tmp_path / "meet"
    meet.mkdir()
    monkeypatch.setenv("GEODISTILL_TEST_MEET", str(meet))
    repo, serial = _project(tmp_path / "ray"), _project(tmp_path / "serial")
    result = run_pipeline(repo, echo=lambda s: None)
    monkeypatch.delenv("GEODISTILL_TEST_MEET")
    assert result.ok and result.count("ran") == 5, result.results
    t = json.loads((repo / "artifacts" / "logs" / "run" / "timeline.json").read_text())["stages"]
    assert sorted(os.listdir(meet)) == ["in_1", "in_2", "met_1", "met_2"]  # the two training runs overlapped
    assert t["train_plain@1"]["num_gpus"] == 0.25 and t["teacher"]["num_gpus"] == 1.0
    assert (repo / "teacher_gpu.txt").read_text() not in ("", "-")  # Ray gave the teacher a (fake) GPU
    bench = t["benchmark"]
    assert all(s["end"] <= bench["start"] or s["start"] >= bench["end"] for n, s in t.items() if n != "benchmark")
    assert (repo / "bench_threads.txt").read_text() == "2"  # alone, with every core
    # the same outputs as one `dvc repro` in a copy; DVC recorded everything; a second run does nothing
    assert _sh(serial, sys.executable, "-m", "dvc", "repro").returncode == 0
    for f in OUTS:
        assert (repo / f).read_bytes() == (serial / f).read_bytes(), f
    status = _sh(repo, sys.executable, "-m", "dvc", "status", "--json")
    assert status.returncode == 0 and json.loads(status.stdout) == {}, status.stdout
    again = run_pipeline(repo, echo=lambda s: None)
    assert again.results == {}
    # a changed dep reruns its stage and downstream; a failing stage stops only its dependents
    (repo / "seed.txt").write_text("t")
    (repo / "dvc.yaml").write_text(DVC_YAML.replace("deps: [train_1.txt]", "deps: [train_1.txt, missing.txt]"))
    failed = run_pipeline(repo, echo=lambda s: None)
    st = {n: r["status"] for n, r in failed.results.items()}
    assert st == {"teacher": "ran", "train_plain@1": "ran", "train_plain@2": "ran", "benchmark": "failed",
                  "report": "not_run"}, st
    assert "missing.txt" in failed.results["benchmark"]["error"]


def test_second_driver_refuses_and_missing_ray_is_one_line(tmp_path):
    from pipeline.cluster.driver import RunLock

    repo = _project(tmp_path / "p")
    with RunLock(repo):
        second = _sh(repo, sys.executable, "-m", "pipeline.cli", "run")
    lines = second.stderr.strip().splitlines()
    assert second.returncode == 2 and len(lines) == 1 and "another geodistill run" in lines[0], second.stderr
    no_ray = _sh(repo, sys.executable, "-c",
                 "import sys; sys.modules['ray'] = None; sys.argv = ['geodistill', 'run']; "
                 "from pipeline.cli.main import main; main()")
    lines = no_ray.stderr.strip().splitlines()
    assert no_ray.returncode == 2 and len(lines) == 1 and "[cluster]" in lines[0] and "dvc repro" in lines[0]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    stat = Path(f"/proc/{pid}/stat")
    return not (stat.exists() and stat.read_text().split(")")[-1].split()[0] == "Z")  # a zombie is dead


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="parent-death signals are Linux")
def test_dvc_status_works_during_a_run_and_a_sigkilled_driver_leaves_no_stage_process(tmp_path):
    pytest.importorskip("ray")
    slow = ("stages:\n  slow:\n    cmd: python -c \"import os, time; "
            "open('pids', 'w').write(f'{os.getpid()} {os.getppid()}'); time.sleep(300)\"\n    outs: [out]\n"
            "  done:\n    cmd: echo d > done.txt\n    outs: [done.txt]\n")
    repo = _project(tmp_path / "p", slow)
    assert _sh(repo, sys.executable, "-m", "dvc", "repro", "done").returncode == 0  # up to date before the run
    driver = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "run"], cwd=repo, env=_env(),
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 180
        while not (repo / "pids").exists() or len((repo / "pids").read_text().split()) < 2:
            assert time.time() < deadline and driver.poll() is None, "the stage never started"
            time.sleep(0.5)
        stage_pid, dvc_pid = map(int, (repo / "pids").read_text().split())
        assert _alive(stage_pid) and _alive(dvc_pid)
        # DVC's repository lock is free meanwhile: status of a stage that is not running works (a running
        # stage's outputs are busy under DVC's per-path lock, as during `dvc repro`)
        status = _sh(repo, sys.executable, "-m", "dvc", "status", "--json", "done")
        assert status.returncode == 0 and json.loads(status.stdout) == {}, status.stderr
    finally:
        driver.send_signal(signal.SIGKILL)
        driver.wait()
    deadline = time.time() + 60
    while (_alive(stage_pid) or _alive(dvc_pid)) and time.time() < deadline:
        time.sleep(0.5)
    assert not _alive(stage_pid) and not _alive(dvc_pid), "a stage process outlived its driver"
