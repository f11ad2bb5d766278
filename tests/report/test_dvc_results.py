"""DVC-native results (issue 18 item 4): metrics files, plot tables, the DVCLive run log, the offline
plots page.

Unit tests of pipeline.report.dvc_results (write_live_log among them) and pipeline.report.offline_plots; then a
tiny git + DVC project whose dvc.yaml holds the generated evaluate / analyze_teacher / benchmark
stages and plots, and whose metrics and plot tables come from the real calibrate, evaluate and
analyze_teacher commands on tests.test_evaluate's tiny artifacts: ``dvc metrics show`` fits 120
columns, ``dvc metrics diff HEAD`` works after a param change, ``dvc plots show`` with the offline
page renders one line per method in headless Chromium without network.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from pipeline.report import dvc_results as R
from pipeline.report import offline_plots as P
ROOT = Path(__file__).resolve().parents[2]
CHROMIUM = shutil.which("chromium") or ("/usr/bin/chromium" if Path("/usr/bin/chromium").exists() else None)
WIDTH = 120


def _summary(groups=("KCP", "CVI"), methods=("plain", "geodistill"), dataset="synthetic") -> pd.DataFrame:
    rows = []
    for gi, g in enumerate(groups):
        for mi, m in enumerate(methods):
            for mode, off in (("calibrated", 0.0), ("fixed", -0.1)):
                rows.append({"dataset": dataset, "group": g, "method": m, "threshold_mode": mode,
                             "iou_mean": 0.512345678 + 0.1 * mi + 0.01 * gi + off, "bf1_mean": 0.4 + off,
                             "iou_std": 0.01, "gain_iou": 0.02, "gain_iou_lo": -0.01, "gain_iou_hi": 0.05})
    return pd.DataFrame(rows)


# --------------------------------------------------------------------------------------------------
# metrics
# --------------------------------------------------------------------------------------------------
def test_student_metric_files_are_short_numeric_at_the_calibrated_tau():
    s = _summary()
    s.loc[(s.group == "CVI") & (s.method == "plain") & (s.threshold_mode == "calibrated"), "bf1_mean"] = np.nan
    files = R.student_metric_files(s)
    assert set(files) == {"KCP/plain.json", "KCP/geodistill.json", "CVI/plain.json", "CVI/geodistill.json"}
    assert files["KCP/geodistill.json"] == {"iou": 0.6123, "bf1": 0.4}  # calibrated rows, 4 decimals
    assert files["CVI/plain.json"] == {"iou": 0.5223}                    # NaN left out, never null or text
    assert all(set(d) <= {"iou", "bf1"} and all(isinstance(v, float) for v in d.values()) for d in files.values())


def test_student_metric_files_safe_names_and_several_datasets():
    s = pd.concat([_summary(groups=("lab/sun lamp",), methods=("plain",), dataset="speedplus"),
                   _summary(groups=("KCP",), methods=("plain",), dataset="synthetic")])
    assert set(R.student_metric_files(s)) == {"speedplus.lab_sun_lamp/plain.json", "synthetic.KCP/plain.json"}
    assert R.path_component("../x") == "_x" and R.path_component("") == "_"


def test_teacher_metric_files_vote_quality_and_gate_share():
    tm = pd.DataFrame({
        "image_id": ["a", "b", "c", "d", "a", "v"], "dataset": "synthetic",
        "split": ["test", "test", "test", "test", "test", "val"], "group": ["KCP", "KCP", "KCP", "CVI", "KCP", "val"],
        "source": ["vote", "vote", "vote", "vote", "prompt_0", "vote"],
        "iou": [0.5, 0.7, 0.9, 0.2, 0.0, 1.0], "bf1": [0.1, 0.2, 0.3, np.nan, 0.0, 1.0]})
    gates = pd.DataFrame({"image_id": ["a", "b", "c", "d", "v"], "g": [0.0, 0.3, 0.8, 0.0, 1.0]})
    files = R.teacher_metric_files(tm, gates)
    assert files == {"KCP.json": {"iou": 0.7, "bf1": 0.2, "gate_share": 0.6667},
                     "CVI.json": {"iou": 0.2, "gate_share": 0.0}}


def test_deploy_metrics_fast_path_else_baseline():
    rows = [{"variant": "fp32_eager_nchw", "latency_ms": 212.84567}, {"variant": "int8", "latency_ms": 45.1}]
    assert R.deploy_metrics({"variant": "int8", "latency_ms": 45.1}, rows, "fp32_eager_nchw") == {"latency_ms": 45.1}
    assert R.deploy_metrics(None, rows, "fp32_eager_nchw") == {"latency_ms": 212.8457}
    assert R.deploy_metrics(None, rows[1:], "fp32_eager_nchw") == {}


def test_write_metrics_dir_replaces_stale_files(tmp_path):
    d = tmp_path / "metrics" / "students"
    R.write_metrics_dir(d, {"KCP/plain.json": {"iou": 0.5}, "KCP/gone.json": {"iou": 0.1}})
    R.write_metrics_dir(d, {"KCP/plain.json": {"iou": 0.6, "bf1": 0.2}})
    assert sorted(p.relative_to(d).as_posix() for p in d.rglob("*") if p.is_file()) == ["KCP/plain.json"]
    assert json.loads((d / "KCP" / "plain.json").read_text()) == {"bf1": 0.2, "iou": 0.6}


# --------------------------------------------------------------------------------------------------
# plot tables
# --------------------------------------------------------------------------------------------------
def test_plot_tables_are_long_with_a_method_column():
    log = pd.DataFrame({"epoch": [2, 1], "stage": 1, "loss": [0.5, 0.9], "val_iou": [0.61234567, 0.5],
                        "val_bf1": [0.3, 0.2], "lr": 1e-3})
    tc = R.training_curves([("plain", 42, log), ("geodistill", 42, log.iloc[:1])])
    assert list(tc.columns) == ["method", "seed", "epoch", "val_iou", "val_bf1", "loss"]
    assert tc[["method", "epoch"]].values.tolist() == [["geodistill", 2], ["plain", 1], ["plain", 2]]
    assert tc["val_iou"].iloc[0] == 0.612346
    thr = pd.DataFrame({"method": ["plain", "plain"], "seed": [2, 1], "tau": [0.5, 0.4],
                        "grid": [[0.3, 0.5], [0.3, 0.5]], "curve": [[0.1, 0.2], [0.3, 0.4]]})
    th = R.threshold_curves(thr)
    assert th.values.tolist() == [["plain", 1, 0.3, 0.3], ["plain", 1, 0.5, 0.4],
                                  ["plain", 2, 0.3, 0.1], ["plain", 2, 0.5, 0.2]]


# --------------------------------------------------------------------------------------------------
# DVCLive
# --------------------------------------------------------------------------------------------------
def test_train_log_written_with_dvclive_byte_identical(tmp_path):
    from pipeline.report.dvc_results import write_live_log

    log = pd.DataFrame({"epoch": [1, 2, 3], "stage": 2, "loss": [0.9, 0.5, 0.4], "sdf": np.nan,
                        "val_iou": [0.5, 0.6, 0.7], "lr": 1e-3})
    a, b = tmp_path / "a" / "geodistill" / "42", tmp_path / "b"
    write_live_log(log, a, selected_epoch=2)
    write_live_log(log, b, selected_epoch=2)
    files = sorted(p.relative_to(a).as_posix() for p in a.rglob("*") if p.is_file())
    assert files == ["metrics.json", "plots/metrics/loss.tsv", "plots/metrics/lr.tsv", "plots/metrics/val_iou.tsv"]
    assert all((a / f).read_bytes() == (b / f).read_bytes() for f in files)  # no timestamps
    assert (a / "plots/metrics/val_iou.tsv").read_text().splitlines() == ["step\tval_iou", "1\t0.5", "2\t0.6", "3\t0.7"]
    summary = json.loads((a / "metrics.json").read_text())
    assert summary == {"loss": 0.4, "val_iou": 0.7, "lr": 0.001, "selected_epoch": 2, "step": 3}


def test_dvclive_log_works_in_a_git_repo_without_commits_and_touches_no_repo(tmp_path, monkeypatch):
    """A fresh `git init` (no commit) made DVCLive's repository probing raise; and in a git checkout
    without DVC it would `dvc init` the user's repository.  The stage's log needs neither."""
    if shutil.which("git") is None:
        pytest.skip("git not available")
    from pipeline.report.dvc_results import write_live_log

    _git(tmp_path, "init", "-q")
    monkeypatch.chdir(tmp_path)
    write_live_log(pd.DataFrame({"epoch": [1], "stage": 1, "loss": [0.5], "val_iou": [0.4], "lr": 1e-3}), "live")
    assert (tmp_path / "live" / "metrics.json").is_file()
    assert not (tmp_path / ".dvc").exists() and not (tmp_path / "dvc.yaml").exists()


# --------------------------------------------------------------------------------------------------
# dvc.yaml, template, offline page
# --------------------------------------------------------------------------------------------------
def test_dvc_yaml_results_are_git_tracked_metrics_and_method_plots():
    from pipeline.catalog import PLOT_TEMPLATE
    from pipeline.orchestration.dag import dvc_stages

    stages = dvc_stages()
    declared = {}
    for name in ("evaluate", "analyze_teacher", "benchmark"):
        for m in stages[name]["metrics"]:
            (path, opts), = m.items()
            declared[path] = opts
    assert declared == {p: {"cache": False} for p in ("reports/metrics/students", "reports/metrics/teacher", "reports/metrics/deploy.json")}
    train = stages["train_geodistill"]
    assert {"reports/dvclive/geodistill/${item.seed}": {"cache": False}} in train["outs"]
    assert "--live-dir reports/dvclive/geodistill/${item.seed}" in train["cmd"]
    # outside artifacts/ and not git-ignored: `dvc metrics diff <commit>` reads them from git
    if shutil.which("git") and (ROOT / ".git").exists():
        ignored = subprocess.run(["git", "check-ignore", "reports/metrics/students/KCP/plain.json", "reports/plots/x.csv",
                                  "reports/dvclive/plain/42/metrics.json"], cwd=ROOT, capture_output=True, text=True)
        assert ignored.returncode == 1 and ignored.stdout == "", ignored.stdout
    doc = yaml.safe_load((ROOT / "dvc.yaml").read_text())
    plots = {k: v for p in doc["plots"] for k, v in p.items()}
    assert set(plots) == {"training_curves", "threshold_curves"}
    assert {v["template"] for v in plots.values()} == {PLOT_TEMPLATE}
    assert plots["threshold_curves"]["x"] == "tau" and plots["threshold_curves"]["y"] == {
        "reports/plots/threshold_curves.csv": "val_iou"}
    # the committed template is the generated one
    assert P.template_path(ROOT).read_text() == P.template_text()


def test_offline_page_inlines_the_chart_library_and_no_cdn():
    scripts = P.vega_scripts()
    assert [n for n, _ in scripts] == list(P.VEGA_FILES) and all(len(js) > 10_000 for _, js in scripts)
    page = P.offline_page([("a.js", "var s = '</script>';"), *scripts])
    assert "{plot_divs}" in page and "{scripts}" not in page
    assert "<\\/script>'" in page and page.count("<script>") == 4
    assert "cdn.jsdelivr" not in page and "https://cdn" not in page
    assert P.dvc_plots_command("p.html", "out") == ["plots", "show", "--html-template", "p.html", "-o", "out"]
    assert P.dvc_plots_command("p.html", "o", ["HEAD"], ["training_curves"], True) == [
        "plots", "diff", "HEAD", "--targets", "training_curves", "--html-template", "p.html", "-o", "o", "--open"]


# --------------------------------------------------------------------------------------------------
# a tiny DVC project
# --------------------------------------------------------------------------------------------------
def _dvc(cwd, *args, env=None):
    return subprocess.run([sys.executable, "-m", "dvc", *args], cwd=cwd, capture_output=True, text=True,
                          env={**os.environ, "COLUMNS": str(WIDTH), **(env or {})}, timeout=300)


def _git(cwd, *args):
    subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True)


def _stage_results(repo: Path, art: Path, params: Path, deploy_ms: float) -> None:
    """Run the real evaluate and analyze_teacher commands with their DVC outputs in ``repo`` (the
    paths of the generated dvc.yaml), and the benchmark's metrics function."""
    from pipeline.artifacts.atomic import write_json
    from pipeline.catalog import path as apath
    from stages.analyze_teacher import main as analyze
    from stages.evaluate import main as evaluate
    from tests.builders.evaluation import invoke

    common = ["--params", str(params), "--artifacts", str(art)]
    res = invoke(evaluate, common + [
        "--checkpoints", str(art / "checkpoints"), "--thresholds", str(art / "thresholds.parquet"),
        "--out", str(art / "metrics.parquet"), "--summary", str(art / "summary.parquet"),
        "--metrics-dir", str(apath("metrics_students", repo / "artifacts")),
        "--training-curves", str(apath("plot_training_curves", repo / "artifacts")),
        "--threshold-curves", str(apath("plot_threshold_curves", repo / "artifacts"))])
    assert res.exit_code == 0, res.output
    res = invoke(analyze, common + ["--out", str(art / "teacher_metrics.parquet"),
                                    "--metrics-dir", str(apath("metrics_teacher", repo / "artifacts"))])
    assert res.exit_code == 0, res.output
    write_json(apath("metrics_deploy", repo / "artifacts"),
               R.deploy_metrics({"latency_ms": deploy_ms}, [], "fp32_eager_nchw"))


@pytest.fixture(scope="module")
def dvc_project(tmp_path_factory):
    if shutil.which("git") is None:
        pytest.skip("git not available")
    from pipeline.orchestration.dag import dvc_plots, dvc_stages
    from tests.builders.evaluation import calibrated_artifacts, write_params

    root = tmp_path_factory.mktemp("dvc_results")
    art, params = calibrated_artifacts(root)

    repo = root / "repo"
    repo.mkdir()
    _git(repo, "init", "-q")
    _git(repo, "config", "user.email", "t@example.com")
    _git(repo, "config", "user.name", "t")
    assert _dvc(repo, "init", "-q").returncode == 0
    _dvc(repo, "config", "core.analytics", "false")
    stages = dvc_stages()
    doc = {"stages": {n: stages[n] for n in ("evaluate", "analyze_teacher", "benchmark")}, "plots": dvc_plots()}
    (repo / "dvc.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    P.template_path(repo).parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(P.template_path(ROOT), P.template_path(repo))
    _stage_results(repo, art, params, deploy_ms=12.5)
    _git(repo, "add", "-A")
    _git(repo, "commit", "-qm", "results")
    # a second run: another Boundary F1 tolerance and a faster deployment
    _stage_results(repo, art, write_params(root / "params2.yaml", evaluate={"bf1_tolerance": 1}), deploy_ms=10.0)
    return repo


@pytest.mark.slow
def test_dvc_metrics_show_fits_120_columns_and_diff_against_a_commit(dvc_project):
    repo = dvc_project
    r = _dvc(repo, "metrics", "show")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert max(map(len, lines)) <= WIDTH, r.stdout
    assert lines[0].split() == ["Path", "bf1", "gate_share", "iou", "latency_ms"]
    paths = {ln.split()[0] for ln in lines[1:]}
    assert paths == {"reports/metrics/deploy.json", "reports/metrics/teacher/CVI.json", "reports/metrics/teacher/KCP.json",
                     *(f"reports/metrics/students/{g}/{m}.json" for g in ("KCP", "CVI") for m in ("plain", "geodistill"))}

    r = _dvc(repo, "metrics", "diff", "HEAD", "--json")
    assert r.returncode == 0, r.stderr
    diff = json.loads(r.stdout)
    assert diff["reports/metrics/deploy.json"]["latency_ms"] == {"old": 12.5, "new": 10.0, "diff": -2.5}
    assert any("bf1" in d for p, d in diff.items() if p.startswith("reports/metrics/students/"))
    r = _dvc(repo, "metrics", "diff", "HEAD")
    assert r.returncode == 0 and max(map(len, r.stdout.splitlines())) <= WIDTH, r.stdout
    # experiments: `dvc exp diff` is the same narrow table; `dvc exp show` needs the README's --keep
    # recipe (its metric columns are named <file>:<key>); measured at its natural width (no squeezing)
    r = _dvc(repo, "exp", "diff")
    assert r.returncode == 0 and "latency_ms" in r.stdout and max(map(len, r.stdout.splitlines())) <= WIDTH
    r = _dvc(repo, "exp", "show", "--no-pager", "--drop", ".*", "--keep",
             r"Experiment|latency_ms|.*/KCP/geodistill\.json:iou", env={"COLUMNS": "1000"})
    assert r.returncode == 0, r.stderr
    assert "reports/metrics/students/KCP/geodistill.json:iou" in r.stdout and "…" not in r.stdout
    assert max(map(len, r.stdout.splitlines())) <= WIDTH, r.stdout

    # every method of the catalogue in three groups still fits: one row per file, five columns
    from pipeline.methods import METHODS

    R.write_metrics_dir(repo / "reports" / "metrics" / "students", R.student_metric_files(
        _summary(groups=("KCP", "CVI", "HJM"), methods=tuple(METHODS))))
    r = _dvc(repo, "metrics", "show")
    assert r.returncode == 0 and max(map(len, r.stdout.splitlines())) <= WIDTH, r.stdout
    assert len(r.stdout.splitlines()) == 1 + 3 * len(METHODS) + 3


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="Chromium not installed (apt-get install chromium) -- "
                                             "the headless render of the plots page is skipped")
def test_dvc_plots_show_offline_one_line_per_method(dvc_project, tmp_path):
    repo = dvc_project
    page = tmp_path / "page.html"
    page.write_text(P.offline_page(P.vega_scripts()))
    r = _dvc(repo, *P.dvc_plots_command(page, tmp_path / "out"))
    assert r.returncode == 0, r.stderr
    html = (tmp_path / "out" / "index.html").read_text()
    assert "<script src" not in html and "cdn.jsdelivr" not in html  # DVC's CDN tags stayed out
    flags = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-quic",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             "--disable-dev-shm-usage", f"--user-data-dir={tmp_path / 'u'}", "--virtual-time-budget=10000",
             # no network: every host resolves nowhere, so a CDN script could not load
             "--host-resolver-rules=MAP * ~NOTFOUND"]
    dom = subprocess.run(flags + ["--dump-dom", (tmp_path / "out" / "index.html").resolve().as_uri()],
                         capture_output=True, text=True, timeout=120)
    assert dom.returncode == 0, dom.stderr[-2000:]
    parts = re.split(r'<div id="(training_curves|threshold_curves)"', dom.stdout)
    drawn = {parts[i]: parts[i + 1] for i in range(1, len(parts) - 1, 2)}
    assert set(drawn) == {"training_curves", "threshold_curves"}
    for name, svg in drawn.items():
        groups = re.findall(r'<g class="mark-line role-mark[^"]*"[^>]*>(.*?)</g>', svg)
        methods = sorted(re.search(r"method: ([^;\"]+)", g).group(1) for g in groups)
        assert methods == ["geodistill", "plain"], (name, methods)  # one line per method (seeds averaged)
        assert all(g.count("<path") == 1 for g in groups)
