"""params.yaml profiles and overrides, stage CLI conventions, and a real `dvc repro` on a small DAG."""

from __future__ import annotations

import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import click
import pytest
import yaml
from click.testing import CliRunner

from pipeline.errors import InputError
from pipeline.params import load_params, parse_override, require
from stages._common import stage_command

ROOT = Path(__file__).resolve().parent.parent


def test_repo_params_profiles_resolve():
    demo = load_params(ROOT / "params.yaml")
    paper = load_params(ROOT / "params.yaml", ["profile=paper"])
    assert demo["profile"] == "demo" and paper["profile"] == "paper"
    assert paper["data"]["resolution"] == 384 and demo["data"]["resolution"] < 384
    # the paper's constants are the base values
    assert paper["train"]["lambda_sdf"] == 0.002 and paper["train"]["epochs_stage1"] == 20
    assert paper["geometry"]["conf_offset"] == 0.35 and paper["consensus"]["vote_threshold"] == 0.5
    assert len(paper["teacher"]["prompts"]) == 6
    # every profile overrides only keys that exist in the base sections (no typos)
    raw = yaml.safe_load((ROOT / "params.yaml").read_text())

    def check(over, base, where):
        for k, v in over.items():
            assert k in base, f"profiles: {where}.{k} does not exist in the base params"
            if isinstance(v, dict):
                check(v, base[k], f"{where}.{k}")

    for name, prof in raw["profiles"].items():
        check(prof, raw, name)
    # dvc.yaml tracks profiles.${profile}.<section>: every profile must define every tracked section
    sections = {s for prof in raw["profiles"].values() for s in prof}
    for name, prof in raw["profiles"].items():
        assert set(prof) == sections, f"profile {name} lacks {sections - set(prof)}"


def test_overrides(tmp_path):
    p = tmp_path / "params.yaml"
    p.write_text(yaml.safe_dump({"profile": "a", "s": {"x": 1, "y": {"z": 2}},
                                 "profiles": {"a": {"s": {"x": 10}}, "b": {"s": {"x": 20}}}}))
    assert load_params(p)["s"] == {"x": 10, "y": {"z": 2}}
    assert load_params(p, ["profile=b"])["s"]["x"] == 20
    assert load_params(p, ["s.y.z=[1, 2]", "s.x=0.5"])["s"] == {"x": 0.5, "y": {"z": [1, 2]}}
    assert parse_override("a.b=null") == (["a", "b"], None)
    with pytest.raises(InputError, match="profile 'c'"):
        load_params(p, ["profile=c"])
    with pytest.raises(InputError, match="key.path=value"):
        load_params(p, ["nonsense"])
    with pytest.raises(InputError, match="not found"):
        load_params(tmp_path / "missing.yaml")
    with pytest.raises(InputError, match=r"s\.x=-1 out of range"):
        require({"x": -1}, "x", "s", kind=(int, float), lo=0)


@stage_command("toy")
@click.option("--n", type=int, default=1)
def _toy(params, device, n):
    """A toy stage."""
    if n < 0:
        raise InputError(f"--n {n}: must be >= 0")
    click.echo(f"x={params['s']['x']} n={n} device={device}")


def test_stage_command_conventions(tmp_path):
    p = tmp_path / "params.yaml"
    p.write_text(yaml.safe_dump({"s": {"x": 1}}))
    r = CliRunner().invoke(_toy, ["--params", str(p), "--set", "s.x=7", "--n", "2"])
    assert r.exit_code == 0 and "x=7 n=2 device=auto" in r.output
    r = CliRunner().invoke(_toy, ["--params", str(p), "--n", "-3"])
    assert r.exit_code == 2
    assert r.output.strip().splitlines() == ["geodistill toy: error: --n -3: must be >= 0"]
    r = CliRunner().invoke(_toy, ["--params", str(tmp_path / "nope.yaml")])
    assert r.exit_code == 2 and "nope.yaml" in r.output and "Traceback" not in r.output


def test_console_script_lists_stage_commands():
    from stages.cli import main

    r = CliRunner().invoke(main, ["--help"])
    assert r.exit_code == 0
    for name in ("prepare", "teacher", "consensus", "geometry", "train"):
        if (ROOT / "stages" / f"{name}.py").exists():
            assert name in r.output


STAGE_A = """
import sys, pandas as pd
from pipeline.params import load_params
from pipeline.artifacts import make_meta, write_parquet
p = load_params("params.yaml")
df = pd.DataFrame({"path": [str(p["a"]["x"])], "reason": ["a"]})
write_parquet("out/a.parquet", df, make_meta("skipped_files", "a", "v1", p["a"]))
"""
STAGE_B = """
import pandas as pd
from pipeline.params import load_params
from pipeline.artifacts import make_meta, open_artifact, write_parquet
p = load_params("params.yaml")
a = open_artifact("out/a.parquet")
df = pd.DataFrame({"path": [a.df.path[0] + "+" + str(p["b"]["y"])], "reason": ["b"]})
write_parquet("out/b.parquet", df, make_meta("skipped_files", "b", "v1", p["b"], [a]))
"""


@pytest.mark.slow
def test_real_dvc_repro_noop_and_partial_rerun(tmp_path):
    if shutil.which("git") is None:
        pytest.skip("git not available")
    dvc = [sys.executable, "-m", "dvc"]
    env_run = dict(cwd=tmp_path, capture_output=True, text=True, check=True)
    subprocess.run(["git", "init", "-q"], **env_run)
    subprocess.run(dvc + ["init", "-q"], **env_run)
    subprocess.run(dvc + ["config", "core.analytics", "false"], **env_run)
    (tmp_path / "a.py").write_text(STAGE_A)
    (tmp_path / "b.py").write_text(STAGE_B)
    (tmp_path / "out").mkdir()
    (tmp_path / "params.yaml").write_text(yaml.safe_dump({
        "profile": "demo", "a": {"x": 1}, "b": {"y": 2},
        "profiles": {"demo": {"a": {"x": 1}, "b": {"y": 2}}, "paper": {"a": {"x": 5}, "b": {"y": 6}}}}))
    (tmp_path / "dvc.yaml").write_text(textwrap.dedent(f"""
        stages:
          a:
            cmd: {sys.executable} a.py
            deps: [a.py]
            params: [profile, a, "profiles.${{profile}}.a"]
            outs: [out/a.parquet]
          b:
            cmd: {sys.executable} b.py
            deps: [b.py, out/a.parquet]
            params: [profile, b, "profiles.${{profile}}.b"]
            outs: [out/b.parquet]
    """))
    import os
    env = {**os.environ, "PYTHONPATH": str(ROOT)}

    def repro():
        r = subprocess.run(dvc + ["repro"], cwd=tmp_path, capture_output=True, text=True, env=env)
        assert r.returncode == 0, r.stdout + r.stderr
        return r.stdout

    out1 = repro()
    assert "Running stage 'a'" in out1 and "Running stage 'b'" in out1
    out2 = repro()
    assert "Running stage" not in out2
    status = subprocess.run(dvc + ["status"], cwd=tmp_path, capture_output=True, text=True, env=env).stdout
    assert "up to date" in status
    # change a param only stage b reads: only b reruns
    params = yaml.safe_load((tmp_path / "params.yaml").read_text())
    params["b"]["y"] = 3
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    out3 = repro()
    assert "Running stage 'b'" in out3 and "Running stage 'a'" not in out3
    # the inactive profile's values are not tracked: editing them reruns nothing
    params["profiles"]["paper"]["a"]["x"] = 99
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    assert "Running stage" not in repro()
    # the active profile's override of a: both rerun
    params["profiles"]["demo"]["a"]["x"] = 4
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    out4 = repro()
    assert "Running stage 'a'" in out4 and "Running stage 'b'" in out4
    from pipeline.artifacts import open_artifact

    assert open_artifact(tmp_path / "out" / "b.parquet").df.path[0] == "4+2"
