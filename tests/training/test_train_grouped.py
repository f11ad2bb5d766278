"""Several seeds of one method in one training stage (params ``protocol.seeds_per_stage``): the DAG's two
shapes (pipeline/orchestration/dag.py) and the grouped train command (stages/train.py), whose checkpoints are the bytes
a process of their own writes (docs/performance.md, "The demo's wall time")."""

from __future__ import annotations

import shutil

import pytest
import yaml

from pipeline.orchestration.dag import project_dvc_yaml, seed_groups, train_stage, train_stage_name, train_stages
from pipeline.methods import METHODS
from pipeline.profiles import profile_params
from tests.builders.training import REPO, train_cli, train_params_file


def _params(runs: dict[str, list[int]], per_stage: int | None) -> dict:
    protocol = {"runs": {**{m: [] for m in METHODS}, **runs}}
    if per_stage is not None:
        protocol["seeds_per_stage"] = per_stage
    return {"protocol": protocol}


def _flag_values(cmd: str, flag: str) -> list[str]:
    words = cmd.split()
    return [words[i + 1] for i, w in enumerate(words) if w == flag]


# --------------------------------------------------------------------------------------------------
# the DAG's shape
# --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("per_stage", [None, 1])
def test_one_stage_per_method_and_seed_by_default(per_stage):
    params = _params({"plain": [42, 7], "geodistill": [42, 7]}, per_stage)
    assert seed_groups(params) is None
    stages = yaml.safe_load(project_dvc_yaml(params))["stages"]
    assert stages["train_plain"]["matrix"] == {"seed": "${protocol.runs.plain}"}  # DVC: train_plain@42, @7
    assert _flag_values(stages["train_geodistill"]["cmd"], "--seed") == ["${item.seed}"]
    # the profiles that `geodistill run` spreads over Ray/GPU workers keep that shape
    for profile in ("reduced", "paper", "distill"):
        assert seed_groups(profile_params(profile)) is None, profile


def test_grouped_stages_keep_one_out_per_method_and_seed():
    params = _params({"plain": [42, 3407, 7], "geodistill": [42, 3407, 7]}, 2)
    assert seed_groups(params) == {"plain": [[42, 3407], [7]], "geodistill": [[42, 3407], [7]]}
    stages = {n: s for n, s in yaml.safe_load(project_dvc_yaml(params))["stages"].items() if n.startswith("train_")}
    assert list(stages) == ["train_plain-42-3407", "train_plain-7", "train_geodistill-42-3407", "train_geodistill-7"]
    ckpt_outs, live_outs = [], []
    for name, st in stages.items():
        assert "matrix" not in st
        seeds = _flag_values(st["cmd"], "--seed")
        method = _flag_values(st["cmd"], "--method")[0]
        assert name == f"train_{method}-" + "-".join(seeds)
        # every per-seed option lines up with --seed, and each is an out (or a dep) of this stage
        assert _flag_values(st["cmd"], "--out") == [f"artifacts/checkpoints/{method}/{s}" for s in seeds]
        assert _flag_values(st["cmd"], "--live-dir") == [f"reports/dvclive/{method}/{s}" for s in seeds]
        ckpt_outs += [o for o in st["outs"] if isinstance(o, str)]
        live_outs += [next(iter(o)) for o in st["outs"] if isinstance(o, dict)]
        assert all(o[next(iter(o))] == {"cache": False} for o in st["outs"] if isinstance(o, dict))
        inits = _flag_values(st["cmd"], "--init")
        assert inits == ([f"artifacts/checkpoints/plain/{s}" for s in seeds] if method == "geodistill" else [])
        assert set(inits) <= set(st["deps"])
    runs = [(m, s) for m in ("plain", "geodistill") for s in (42, 3407, 7)]
    assert sorted(ckpt_outs) == sorted(f"artifacts/checkpoints/{m}/{s}" for m, s in runs)
    assert sorted(live_outs) == sorted(f"reports/dvclive/{m}/{s}" for m, s in runs)


def test_a_group_of_one_seed_is_the_per_seed_stage_with_the_seed_filled_in():
    """The grouped command of one seed is, word for word, the command DVC runs for train_<method>@<seed>:
    each seed's training call is the per-seed shape's."""
    for method in ("plain", "geodistill", "continuation"):
        matrix = train_stage(method)
        one = train_stage(method, seeds=[3407])
        fill = lambda x: yaml.safe_load(yaml.safe_dump(x).replace("${item.seed}", "3407"))  # noqa: E731
        assert one == fill({k: v for k, v in matrix.items() if k != "matrix"})


def test_all_seeds_of_a_method_in_one_stage_and_the_stage_names():
    params = _params({"plain": [42, 7], "continuation": [42, 7]}, 10)
    assert list(train_stages(groups=seed_groups(params))) == ["train_plain", "train_continuation"]
    assert train_stage_name("plain") == "train_plain"
    assert train_stage_name("plain", [42, 7], [42, 7, 1]) == "train_plain-42-7"


def test_the_demo_profile_trains_each_method_in_one_stage():
    """The demo profile turns the grouping on; the committed dvc.yaml is the grouped one (its currency:
    tests/orchestration/test_params_and_dag.py)."""
    demo = profile_params("demo")
    groups = seed_groups(demo)
    assert groups == {m: [seeds] for m, seeds in demo["protocol"]["runs"].items() if seeds}
    stages = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
    assert [n for n in stages if n.startswith("train_")] == [f"train_{m}" for m in groups]


def test_cluster_plan_gives_a_grouped_stage_a_training_share():
    from pipeline.cluster import plan

    gpu = plan.Sizing(node_cpus=8, gpus=1, train_gpu_fraction=0.25)
    for name in ("train_plain", "train_plain-42-7", "train_plain@42"):
        assert plan.stage_resources(name, gpu) == {"num_cpus": 1.0, "num_gpus": 0.25}, name


# --------------------------------------------------------------------------------------------------
# the grouped train command
# --------------------------------------------------------------------------------------------------
def test_per_seed_options_must_line_up_with_the_seeds(tiny, tmp_path):
    params = train_params_file(tmp_path)
    r = train_cli("--params", str(params), "--stage", "1", "--method", "plain", "--seed", "42", "--seed", "7",
                  "--artifacts", str(tiny), "--out", str(tmp_path / "a"), cwd=tmp_path)
    assert r.returncode == 2 and "--out: 1 given for 2 --seed" in r.stderr and "Traceback" not in r.stderr
    r = train_cli("--params", str(params), "--stage", "1", "--method", "plain", "--seed", "7", "--seed", "7",
                  "--artifacts", str(tiny), "--out", str(tmp_path / "a"), "--out", str(tmp_path / "b"), cwd=tmp_path)
    assert r.returncode == 2 and "names a seed twice" in r.stderr
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def _files(d) -> dict[str, bytes]:
    return {str(f.relative_to(d)): f.read_bytes() for f in sorted(d.rglob("*")) if f.is_file()}


@pytest.mark.slow
def test_grouped_seeds_write_the_bytes_of_separate_processes_and_resume(tiny, tmp_path):
    """Seed 7 trained after seed 42 in one process (Stage II, warm-started from the seeds' own Stage-I
    checkpoints) gives the same bytes, checkpoint and DVCLive log, as seed 7 alone in a fresh process;
    a rerun of the group resumes every finished seed from its per-epoch state (what a killed stage
    does) and writes the same bytes again."""
    params = train_params_file(tmp_path, runs={"plain": [42, 7], "geodistill": [42, 7]})
    env = {"SOURCE_DATE_EPOCH": "1700000000"}
    ck, live = tmp_path / "ck", tmp_path / "live"
    common = ["--params", str(params), "--artifacts", str(tiny), "--device", "cpu"]

    def train(stage, method, seeds, jobs=1):
        args = [*common, "--stage", str(stage), "--method", method, "--resume-dir", str(tmp_path / "resume"),
                "--jobs", str(jobs)]
        for s in seeds:
            args += ["--seed", str(s), "--out", str(ck / method / str(s)), "--live-dir", str(live / method / str(s))]
            if stage == 2:
                args += ["--init", str(ck / "plain" / str(s))]
        r = train_cli(*args, cwd=tmp_path, env=env)
        assert r.returncode == 0, r.stderr
        return r.stderr

    train(1, "plain", [42, 7])  # the warm starts
    train(2, "geodistill", [7])  # seed 7 in a process of its own
    alone = {d: _files(d) for d in (ck / "geodistill" / "7", live / "geodistill" / "7")}
    assert set(alone[ck / "geodistill" / "7"]) == {"model.safetensors", "model.json", "log.parquet", "meta.json"}
    for d in [*alone, tmp_path / "resume"]:  # the same paths again, no resume state kept
        shutil.rmtree(d)
    train(2, "geodistill", [42, 7])  # 42 first: 7 runs in a process that trained already
    assert {d: _files(d) for d in alone} == alone
    # a rerun (a killed stage's next run) resumes each finished seed and writes the same bytes
    before = {s: _files(ck / "geodistill" / str(s)) for s in (42, 7)}
    log = train(2, "geodistill", [42, 7])
    assert "resuming geodistill seed 42 after epoch 1" in log and "resuming geodistill seed 7 after epoch 1" in log
    assert {s: _files(ck / "geodistill" / str(s)) for s in (42, 7)} == before
    # the group in two processes side by side (--jobs 2): the same bytes, run ids included
    for d in [*(ck / "geodistill" / str(s) for s in (42, 7)), tmp_path / "resume"]:
        shutil.rmtree(d)
    log = train(2, "geodistill", [42, 7], jobs=2)
    assert "resuming" not in log and {s: _files(ck / "geodistill" / str(s)) for s in (42, 7)} == before


def test_a_group_runs_in_the_cores_over_its_threads_and_the_recorded_command_leaves_jobs_out(monkeypatch):
    from pipeline.cluster.driver import child_env
    from pipeline.runtime.device import STAGE_CPUS_ENV
    from pipeline.training.seeds import auto_jobs, seeds_argv

    monkeypatch.delenv(STAGE_CPUS_ENV, raising=False)
    cores = __import__("os").cpu_count()
    assert auto_jobs({"num_threads": 1}, "cpu", 10) == min(10, cores)
    assert auto_jobs({"num_threads": 1}, "cpu", 1) == 1
    assert auto_jobs({"num_threads": 0}, "cpu", 10) == 1 and auto_jobs({"num_threads": 1}, "cuda", 10) == 1
    # under geodistill run a stage fills the cores Ray gave it, not the node's
    monkeypatch.setenv(STAGE_CPUS_ENV, child_env({}, 3, 0.0)[STAGE_CPUS_ENV])
    assert auto_jobs({"num_threads": 1}, "cpu", 10) == 3 and auto_jobs({"num_threads": 2}, "cpu", 10) == 1
    argv = ["--stage", "2", "--jobs", "2", "--seed", "42", "--init", "a", "--out", "x", "--seed", "7",
            "--init=b", "--out", "y"]
    assert seeds_argv(argv, {1}) == ["--stage", "2", "--seed", "7", "--init=b", "--out", "y"]
    assert seeds_argv(argv, {0, 1}) == argv[:2] + argv[4:]


def test_a_group_in_processes_refuses_a_wrong_method_in_one_line(tiny, tmp_path):
    params = train_params_file(tmp_path)
    r = train_cli("--params", str(params), "--stage", "2", "--method", "plain", "--seed", "42", "--seed", "7",
                  "--jobs", "2", "--artifacts", str(tiny), "--out", str(tmp_path / "a"), "--out", str(tmp_path / "b"),
                  cwd=tmp_path)
    assert r.returncode == 2 and r.stderr.count("belongs to --stage 1") == 1, r.stderr
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
