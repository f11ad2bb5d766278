"""One source of truth: the params schema, generated params.yaml/dvc.yaml, derived code deps, per-key params."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import click
import pytest
import yaml
from click.testing import CliRunner

from pipeline.runtime.errors import InputError
from pipeline.params import PAPER, load_params, parse_override, validate
from pipeline.profiles import load_params_or_profile, load_profile
from pipeline.cli.conventions import stage_command
from tests.builders.lane import committed_text

ROOT = Path(__file__).resolve().parents[2]


# --------------------------------------------------------------------------------------------------
# schema
# --------------------------------------------------------------------------------------------------
def test_committed_params_yaml_is_the_demo_profile():
    from pipeline.orchestration.dag import render_params_yaml

    assert (ROOT / "params.yaml").read_text() == render_params_yaml("demo"), \
        "params.yaml is out of date: run `geodistill profile demo`"
    demo = load_params(ROOT / "params.yaml")
    assert demo["profile"] == "demo" and demo["data"]["resolution"] == 64 and demo["train"]["recipe"] == "stable"


@pytest.mark.parametrize("profile", ["demo", "reduced", "reduced-strong", "paper"])
def test_profiles_validate_and_paper_is_the_schema_default(profile):
    from pipeline.profiles import profile_params

    from pipeline.profiles import DEMO_THREADS, PUBLISHED_THREADS

    p = validate(profile_params(profile))
    # profiles that publish numbers pin threads
    assert p["train"]["num_threads"] == (DEMO_THREADS if profile == "demo" else PUBLISHED_THREADS) > 0
    if profile == "reduced-strong":  # the geometry question at convergence: four runs, three seeds, strong
        assert p["train"]["recipe"] == "strong" and p["train"]["augment"] is True
        assert {m for m, s in p["protocol"]["runs"].items() if s} == \
            {"plain", "geodistill", "continuation", "supervised_ceiling"}
        assert all(len(s) == 3 for s in p["protocol"]["runs"].values() if s)
    if profile == "paper":
        schema = PAPER.model_dump()
        schema["train"] = {**schema["train"], "num_threads": PUBLISHED_THREADS}
        assert {k: v for k, v in p.items() if k not in ("profile", "protocol")} == \
            {k: v for k, v in schema.items() if k not in ("profile", "protocol")}
        assert p["data"]["resolution"] == 384 and p["train"]["epochs_stage1"] == 20
        assert p["protocol"]["runs"]["no_gate"] == [42] and p["protocol"]["runs"]["gabi"] == [42, 3407, 2026]


def test_library_constants_come_from_the_schema():
    from pipeline import consensus, geometry, metrics

    assert geometry.CONF_OFFSET == PAPER.geometry.conf_offset == 0.35
    assert geometry.SDF_QUANTILE == PAPER.geometry.sdf_quantile
    assert consensus.DEFAULT_VOTE_THRESHOLD == PAPER.consensus.vote_threshold
    assert metrics.DEFAULT_TOLERANCE == PAPER.evaluate.bf1_tolerance


@pytest.mark.parametrize("override, key, words", [
    ("geometry.conf_offset=.nan", "geometry.conf_offset", "finite"),
    ("train.lr_stage1=.inf", "train.lr_stage1", "finite"),
    ("train.epochz=5", "train.epochz", "unknown key"),
    ("train.batch_size=two", "train.batch_size", "integer"),
    ("train.batch_size=2.5", "train.batch_size", "integer"),
    ("train.lr_stage1='1e-4'", "train.lr_stage1", "number"),  # quoted: a string (unquoted 1e-4 is a number)
    ("consensus.vote_threshold=1.5", "consensus.vote_threshold", "less than or equal"),
    ("train.schedule=linear", "train.schedule", "cosine"),
    ("data.synthetic.tiny_range=[0.5, 0.1]", "data.synthetic.tiny_range", "lo < hi"),
    ("protocol.runs={geodistill: [7]}", "protocol.runs", "warm-starts from plain"),
    ("protocol.runs={plainn: [1]}", "protocol.runs", "unknown method"),
    ("teacher.backend=sam3", "teacher", "checkpoint is required"),
])
def test_bad_params_name_the_key(override, key, words):
    with pytest.raises(InputError) as e:
        load_params(ROOT / "params.yaml", [override])
    msg = str(e.value)
    assert "\n" not in msg and key in msg and words in msg


def test_bad_param_from_the_cli_exits_2_and_writes_nothing(tmp_path):
    for override in ("geometry.conf_offset=.nan", "train.epochz=5", "consensus.vote_threshold=[1]"):
        out = tmp_path / "consensus.zarr"
        r = subprocess.run([sys.executable, "-m", "stages.consensus", "--params", str(ROOT / "params.yaml"),
                            "--set", override, "--teacher", str(tmp_path / "missing.zarr"), "--out", str(out)],
                           capture_output=True, text=True, cwd=ROOT)
        assert r.returncode == 2, r.stderr
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and override.split("=")[0] in lines[0] and "Traceback" not in r.stderr
        assert not out.exists()


def test_overrides_and_profile_switch(tmp_path):
    assert parse_override("a.b=null") == (["a", "b"], None)
    # only the commands that switch profile (label, distill, the API) read profiles; a stage refuses
    p = load_params_or_profile(ROOT / "params.yaml", ["profile=paper", "train.lr_stage2=0.0002"], "distill")
    assert p["profile"] == "paper" and p["data"]["resolution"] == 384 and math.isclose(p["train"]["lr_stage2"], 2e-4)
    assert load_profile("paper", ["train.lr_stage2=0.0002"]) == p
    assert load_params_or_profile(None, [], "demo") == load_profile("demo")
    assert load_params_or_profile(ROOT / "params.yaml", [], "paper") == load_params(ROOT / "params.yaml")
    with pytest.raises(InputError, match="profile 'nope'"):
        load_params_or_profile(ROOT / "params.yaml", ["profile=nope"], "paper")
    with pytest.raises(InputError, match=r"--set profile=\.\.\.: this command reads its params file"):
        load_params(ROOT / "params.yaml", ["profile=paper"])
    with pytest.raises(InputError, match="key.path=value"):
        load_params(ROOT / "params.yaml", ["nonsense"])
    with pytest.raises(InputError, match="not found"):
        load_params(tmp_path / "missing.yaml")


@stage_command("toy")
@click.option("--n", type=int, default=1)
def _toy(params, device, n):
    """A toy stage."""
    if n < 0:
        raise InputError(f"--n {n}: must be >= 0")
    click.echo(f"lr={params['train']['lr_stage2']} n={n} device={device}")


def test_stage_command_conventions(tmp_path):
    p = ROOT / "params.yaml"
    r = CliRunner().invoke(_toy, ["--params", str(p), "--set", "train.lr_stage2=0.5", "--n", "2"])
    assert r.exit_code == 0 and "lr=0.5 n=2 device=auto" in r.output
    r = CliRunner().invoke(_toy, ["--params", str(p), "--n", "-3"])
    assert r.exit_code == 2
    assert r.output.strip().splitlines() == ["geodistill toy: error: --n -3: must be >= 0"]
    r = CliRunner().invoke(_toy, ["--params", str(tmp_path / "nope.yaml")])
    assert r.exit_code == 2 and "nope.yaml" in r.output and "Traceback" not in r.output
    r = CliRunner().invoke(_toy, ["--params", str(p), "--set", "profile=paper"])  # stages read params.yaml alone
    assert r.exit_code == 2 and r.output.strip().splitlines() == [
        f"geodistill toy: error: --set profile=...: this command reads its params file ({p}); "
        "switch profile with `geodistill profile NAME`"]


def test_console_script_lists_stage_commands():
    from pipeline.cli.main import main

    r = CliRunner().invoke(main, ["--help"])
    assert r.exit_code == 0
    for name in ("prepare", "teacher", "consensus", "geometry", "train", "dag", "profile"):
        assert name in r.output


def test_stages_holds_only_the_dags_stage_scripts():
    """stages/ is the scripts dvc.yaml's stages run (pipeline.orchestration.dag.stage_modules) and their shared
    conventions (_common); the user tools are pipeline/cli/."""
    from pipeline.orchestration.dag import stage_modules

    scripts = {p.stem for p in (ROOT / "stages").glob("*.py")} - {"__init__", "_common"}
    assert scripts == {m.removeprefix("stages.") for m in stage_modules().values()}


# --------------------------------------------------------------------------------------------------
# derived code deps
# --------------------------------------------------------------------------------------------------
def test_module_files_follow_imports_inside_functions_and_packages(tmp_path):
    from pipeline.runtime.codeversion import code_version_of, module_files

    (tmp_path / "stages").mkdir()
    (tmp_path / "pipeline" / "sub").mkdir(parents=True)
    (tmp_path / "stages" / "__init__.py").write_text("")
    (tmp_path / "pipeline" / "__init__.py").write_text("")
    (tmp_path / "pipeline" / "sub" / "__init__.py").write_text("from . import deep\n")
    (tmp_path / "pipeline" / "sub" / "deep.py").write_text("import numpy\n")
    (tmp_path / "pipeline" / "lazy.py").write_text("from .sub import deep\n")
    (tmp_path / "pipeline" / "unused.py").write_text("")
    (tmp_path / "stages" / "s.py").write_text("import os\n\ndef main():\n    from pipeline import lazy\n")
    files = module_files("stages.s", tmp_path)
    assert files == ("pipeline/__init__.py", "pipeline/lazy.py", "pipeline/sub/__init__.py",
                     "pipeline/sub/deep.py", "stages/__init__.py", "stages/s.py")
    before = code_version_of("stages.s", tmp_path)
    (tmp_path / "pipeline" / "sub" / "deep.py").write_text("import numpy  # edited\n")
    module_files.cache_clear()
    assert code_version_of("stages.s", tmp_path) != before  # a transitive edit changes the fingerprint
    (tmp_path / "pipeline" / "unused.py").write_text("x = 1\n")
    assert code_version_of("stages.s", tmp_path) == code_version_of("stages.s", tmp_path)


def _dvc_yaml() -> dict:
    return yaml.safe_load((ROOT / "dvc.yaml").read_text())


def test_dvc_yaml_is_generated_and_current():
    from pipeline.orchestration.dag import project_dvc_yaml

    params = yaml.safe_load((ROOT / "params.yaml").read_text())  # the demo groups its seeds (protocol.seeds_per_stage)
    assert (ROOT / "dvc.yaml").read_text() == project_dvc_yaml(params), "dvc.yaml is out of date: run `geodistill dag`"


def test_dvc_yaml_deps_cover_every_module_each_stage_imports():
    from pipeline.runtime.codeversion import module_files

    for name, stage in _dvc_yaml()["stages"].items():
        module = stage["cmd"].split()[2]
        deps = [d for d in stage["deps"] if not d.startswith("artifacts/")]
        for f in module_files(module):
            assert any(f == d or f.startswith(d.rstrip("/") + "/") for d in deps), \
                f"dvc.yaml stage {name}: {f} (imported by {module}) is not among its deps"


#: Files that only render or choose params (dvc.yaml, params.yaml); editing them must mark no stage stale.
NOT_CODE_DEPS = ("pipeline/orchestration/dag.py", "pipeline/cli/generate.py")


def test_the_dvc_yaml_renderer_is_no_code_dep_of_any_stage():
    for name, stage in _dvc_yaml()["stages"].items():
        stale = [f for f in NOT_CODE_DEPS if f in stage["deps"]]
        assert not stale, f"dvc.yaml stage {name}: editing {stale} would mark it stale"


def test_stage_code_version_is_the_derived_one():
    from pipeline.runtime.codeversion import code_version_of
    from pipeline.cli.conventions import stage_code_version

    assert stage_code_version(str(ROOT / "stages" / "consensus.py")) == code_version_of("stages.consensus")
    assert "pipeline/params.py" in __import__("pipeline.runtime.codeversion").runtime.codeversion.module_files("stages.consensus")


# --------------------------------------------------------------------------------------------------
# params key by key: what `dvc status` marks after one change
# --------------------------------------------------------------------------------------------------
def _dvc(cwd, *args):
    return subprocess.run([sys.executable, "-m", "dvc", *args], cwd=cwd, capture_output=True, text=True)


@pytest.fixture(scope="module")
def paper_repo(tmp_path_factory):
    """A repo with dvc.yaml, the paper profile's params.yaml and a dvc.lock recording those params for
    every stage (as after a complete run; code and data deps are absent, which `dvc status` reports
    separately from params)."""
    if shutil.which("git") is None:
        pytest.skip("git not available")
    from pipeline.orchestration.dag import dvc_stages, project_dvc_yaml, render_params_yaml

    repo = tmp_path_factory.mktemp("paper_repo")
    subprocess.run(["git", "init", "-q"], cwd=repo, check=True)
    assert _dvc(repo, "init", "-q").returncode == 0
    _dvc(repo, "config", "core.analytics", "false")
    (repo / "params.yaml").write_text(render_params_yaml("paper"))
    (repo / "dvc.yaml").write_text(project_dvc_yaml(yaml.safe_load((repo / "params.yaml").read_text())))  # per seed
    params = load_params(repo / "params.yaml")
    from pipeline.params import get_path

    lock = {"schema": "2.0", "stages": {}}
    for name, st in dvc_stages().items():
        seeds = params["protocol"]["runs"][name.removeprefix("train_")] if "matrix" in st else [None]
        for seed in seeds:
            lock["stages"][name if seed is None else f"{name}@{seed}"] = {
                "cmd": "recorded", "params": {"params.yaml": {k: get_path(params, k) for k in st["params"]}}}
    (repo / "dvc.lock").write_text(yaml.safe_dump(lock, sort_keys=False))
    return repo


def _stages_with_changed_params(repo, key, value) -> set[str]:
    text = (repo / "params.yaml").read_text()
    edited = yaml.safe_load(text)
    from pipeline.params import set_path

    set_path(edited, key.split("."), value)
    try:
        (repo / "params.yaml").write_text(yaml.safe_dump(edited, sort_keys=False))
        r = _dvc(repo, "status", "--json")
        assert r.returncode == 0, r.stderr
        status = json.loads(r.stdout)
    finally:
        (repo / "params.yaml").write_text(text)
    return {stage for stage, changes in status.items()
            for c in changes if isinstance(c, dict)
            for dep in c.get("changed deps", {}).values() if isinstance(dep, dict)
            for tracked in dep if key == tracked or key.startswith(tracked + ".")}


@pytest.mark.slow
@pytest.mark.parametrize("key, value, expected", [
    ("train.lr_stage2", 2e-4, {f"train_{m}@42" for m in
                               ("geodistill", "sdf_gated", "sdf_skel_gated", "sdf_area_gated", "no_gate")}
     | {f"train_{m}@{s}" for m in ("geodistill", "continuation") for s in (42, 3407, 2026)}),
    ("train.lr_stage1", 1e-3, {f"train_{m}@{s}" for m in ("plain", "confidence_filtered", "afs_control", "gabi",
                                                           "supervised_ceiling")
                               for s in (42, 3407, 2026)}
     | {"train_full_scratch_10@42", "train_full_scratch_30@42", "train_sdf_scratch@42"}),
    ("train.gabi.lambda_dist", 0.01, {"train_gabi@42", "train_gabi@3407", "train_gabi@2026"}),
    ("consensus.vote_threshold", 0.6, {"consensus"}),
    ("deploy.benchmark_iters", 5, {"benchmark"}),
    ("evaluate.bootstrap_resamples", 100, {"evaluate"}),
    ("report.qualitative_images", 2, {"report"}),
])
def test_dvc_status_marks_exactly_the_stages_that_read_a_param(paper_repo, key, value, expected):
    assert _stages_with_changed_params(paper_repo, key, value) == expected


def test_demo_dag_has_only_active_runs():
    r = _dvc(ROOT, "stage", "list", "--name-only")
    assert r.returncode == 0, r.stderr
    names = set(r.stdout.split())
    train = {n for n in names if n.startswith("train_")}
    from pipeline.profiles import TEN_SEEDS

    # the demo's runs: three methods at the ten seeds whose means it publishes (docs/stability.md), each
    # method's seeds in one stage (protocol.seeds_per_stage; tests/training/test_train_grouped.py)
    assert train == {f"train_{m}" for m in ("plain", "geodistill", "continuation")}
    outs = {o for n in train for o in _dvc_yaml()["stages"][n]["outs"] if isinstance(o, str)}
    assert outs == {f"artifacts/checkpoints/{m}/{s}" for m in ("plain", "geodistill", "continuation") for s in TEN_SEEDS}
    assert {"prepare", "teacher", "consensus", "geometry", "calibrate", "evaluate", "report"} <= names


# --------------------------------------------------------------------------------------------------
# profiles and the dvc.yaml renderer are no stage's code dep
# --------------------------------------------------------------------------------------------------
def _md5(path: Path) -> str:
    import hashlib

    return hashlib.md5(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def code_repo(tmp_path_factory):
    """A copy of this repository's code, data manifests, dvc.yaml and params.yaml whose dvc.lock is the
    committed one with every file dep's md5 set to the file as it is now (the committed lock may lag the
    code: the demo reruns later) and its deps list as dvc.yaml names it -- a lock as after a complete
    run of this code; outputs are absent, which `dvc status` reports apart from code deps."""
    repo = tmp_path_factory.mktemp("code_repo")
    for d in ("pipeline", "stages", "data_manifests"):
        shutil.copytree(ROOT / d, repo / d, ignore=shutil.ignore_patterns("__pycache__"))
    for f in ("dvc.yaml", "params.yaml"):
        shutil.copy(ROOT / f, repo / f)
    assert _dvc(repo, "init", "--no-scm", "-q").returncode == 0
    _dvc(repo, "config", "core.analytics", "false")
    declared = yaml.safe_load((repo / "dvc.yaml").read_text())["stages"]
    committed = yaml.safe_load(committed_text("dvc.lock"))
    lock = {"schema": committed["schema"], "stages": {}}
    for name, entry in committed["stages"].items():
        base, _, seed = name.partition("@")
        if base not in declared or bool(seed) != ("matrix" in declared[base]):  # gone, or now of the other shape
            continue
        old = {d["path"]: d for d in entry.get("deps", [])}
        deps = []
        for path in (p.replace("${item.seed}", seed) for p in declared[base]["deps"]):
            dep = dict(old.get(path, {"path": path}))
            if (repo / path).is_file():
                dep.update(hash="md5", md5=_md5(repo / path), size=(repo / path).stat().st_size)
            deps.append(dep)
        lock["stages"][name] = {**entry, "deps": deps}
    for name, stage in declared.items():   # a stage added since the committed lock: locked as after its first run
        if "cmd" in stage and not any(n.partition("@")[0] == name for n in lock["stages"]):
            lock["stages"][name] = {"cmd": stage["cmd"], "deps": [
                {"path": p, "hash": "md5", "md5": _md5(repo / p), "size": (repo / p).stat().st_size}
                if (repo / p).is_file() else {"path": p} for p in stage.get("deps", [])]}
    (repo / "dvc.lock").write_text(yaml.safe_dump(lock, sort_keys=False))
    return repo


def _changed_code_deps(repo) -> dict[str, set[str]]:
    """``{dep path: stages}`` that `dvc status` reports as changed deps (code and data alike)."""
    r = _dvc(repo, "status", "--json")
    assert r.returncode == 0, r.stderr
    out: dict[str, set[str]] = {}
    for stage, changes in json.loads(r.stdout).items():
        for c in changes:
            if isinstance(c, dict):
                for path in c.get("changed deps", {}):
                    out.setdefault(path, set()).add(stage)
    return out


@pytest.mark.slow
def test_editing_profiles_or_the_dag_renderer_marks_no_stage_stale(code_repo):
    """Profiles are data read by `geodistill profile`/label/distill, and dvc.yaml's renderer runs in
    `geodistill dag`: no stage imports either, so editing them reruns nothing.  The control: the same
    edit of a file the stages do run (pipeline/geometry.py) is reported."""
    before = _changed_code_deps(code_repo)
    assert "pipeline/geometry.py" not in before
    edited = ["pipeline/profiles.py", "pipeline/orchestration/dag.py"]
    for rel in edited:
        with open(code_repo / rel, "a") as f:
            f.write("# an edit\n")
    after = _changed_code_deps(code_repo)
    assert not set(edited) & set(after), {p: after[p] for p in set(edited) & set(after)}
    with open(code_repo / "pipeline/geometry.py", "a") as f:
        f.write("# an edit\n")
    control = _changed_code_deps(code_repo)
    assert "geometry" in control.get("pipeline/geometry.py", set()), control


def test_report_reruns_when_the_noise_floor_changes():
    """The report's verdicts read reports/noise_floor.json: in this repository's DAG it is a dep of the
    report stage (a new floor reruns the report); a standalone project, which has no floor file,
    does not list it (DVC would stop on a missing dep)."""
    import yaml

    from pipeline.catalog import dvc_path
    from pipeline.orchestration.dag import render_dvc_yaml

    floor = dvc_path("noise_floor")
    assert floor == "reports/noise_floor.json"
    project = yaml.safe_load(render_dvc_yaml())["stages"]
    assert floor in project["report"]["deps"]
    assert not any(floor in e["deps"] for n, e in project.items() if n != "report")
    standalone = yaml.safe_load(render_dvc_yaml(code_root=Path("/x"), data_deps={"prepare": ["images"]}))["stages"]
    assert floor not in standalone["report"]["deps"]
