"""Distillation efficiency where users look for it: the report stage's DVC metrics
(``reports/metrics/efficiency/<group>/<method>.json``, the same ratio as the reference-points table),
``dvc metrics show`` still under 120 characters with them, and ``geodistill distill --val-masks``'s
summary line "the student's test Image IoU is X × the teacher vote's Image IoU"."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
from click.testing import CliRunner

from pipeline import catalog
from pipeline.report import dvc_results as R
from pipeline.artifacts.atomic import write_json
from pipeline.methods import BASELINE, METHODS, PROPOSED, method_label
from tests.builders.evaluation import build_tiny_artifacts, invoke, run_result_stages, write_params


@pytest.fixture(scope="module")
def reported(tmp_path_factory):
    """Tiny artifacts, calibrate/evaluate/analyze_teacher and the report stage, its efficiency metrics
    in ``root/eff`` (--metrics-dir)."""
    from stages.report import main as report

    root = tmp_path_factory.mktemp("eff")
    art = build_tiny_artifacts(root / "artifacts")
    params = write_params(root / "params.yaml")
    run_result_stages(root, art, params)
    res = invoke(report, ["--params", str(params), "--artifacts", str(art), "--out", str(root / "rep"),
                          "--metrics-dir", str(root / "eff")])
    assert res.exit_code == 0, res.output
    return root, art, params


def test_report_stage_writes_the_reference_points_ratio_as_dvc_metrics(reported):
    root, art, _ = reported
    summary = pd.read_parquet(art / "summary.parquet")
    tm = pd.read_parquet(art / "teacher_metrics.parquet")
    vote = tm[(tm["source"] == "vote") & (tm["split"] == "test")].groupby("group")["iou"].mean()
    cal = summary[summary["threshold_mode"] == "calibrated"]
    expected = {f"{r['group']}/{r['method']}.json": {"efficiency": round(r["iou_mean"] / vote[r["group"]], 4)}
                for _, r in cal.iterrows()}
    written = {p.relative_to(root / "eff").as_posix(): json.loads(p.read_text())
               for p in (root / "eff").rglob("*.json")}
    assert written == expected and len(written) == len(cal) >= 4
    # the report's reference-points table prints the same ratio for Plain Student
    md = (root / "rep" / "report.md").read_text()
    table = next(b for b in md.split("\n\n") if "| IoU ÷ vote |" in b).splitlines()
    col = [c.strip() for c in table[0].split("|")].index("IoU ÷ vote")
    for g in vote.index:
        e = written[f"{g}/{BASELINE}.json"]["efficiency"]
        row = next(ln for ln in table if ln.startswith(f"| {g} | {method_label(BASELINE)} |"))
        assert row.split("|")[col].strip().startswith(f"{e:.2f}"), row


def test_without_test_masks_the_efficiency_folder_is_empty_and_stale_files_go(reported, tmp_path):
    """Only the data artifacts (a distill project without masks): the folder exists (a DVC out) and is
    empty; a file of an earlier run in it does not survive."""
    from stages.report import main as report

    _, art, params = reported
    part = tmp_path / "artifacts"
    part.mkdir()
    for name in ("manifest", "images", "reference"):
        src = catalog.path(name, art)
        (shutil.copytree if src.is_dir() else shutil.copy)(src, catalog.path(name, part))
    eff = catalog.path("metrics_efficiency", part)  # the default: beside --artifacts
    write_json(eff / "KCP" / "plain.json", {"efficiency": 0.5})
    res = invoke(report, ["--params", str(params), "--artifacts", str(part), "--out", str(tmp_path / "rep")])
    assert res.exit_code == 0, res.output
    assert eff.is_dir() and not any(eff.rglob("*"))


def test_the_report_stage_declares_the_folder_as_git_tracked_dvc_metrics():
    from pipeline.orchestration.dag import dvc_stages

    spec = catalog.ARTIFACTS["metrics_efficiency"]
    assert spec.stage == "report" and spec.path.startswith("../") and spec.schema is None
    stage = dvc_stages()["report"]
    assert stage["metrics"] == [{"reports/metrics/efficiency": {"cache": False}}]
    assert "--metrics-dir reports/metrics/efficiency" in stage["cmd"]


def _dvc(cwd, *args):
    env = {**os.environ, "COLUMNS": "120", "DVC_NO_ANALYTICS": "1"}
    return subprocess.run([sys.executable, "-m", "dvc", *args], cwd=cwd, capture_output=True, text=True, env=env,
                          timeout=120)


def _summary(groups, methods) -> pd.DataFrame:
    return pd.DataFrame([{"dataset": "synthetic", "group": g, "method": m, "threshold_mode": "calibrated",
                          "iou_mean": 0.5123, "iou_std": 0.0123, "bf1_mean": 0.6123, "n_seeds": 5}
                         for g in groups for m in methods])


def test_dvc_metrics_show_stays_under_120_characters_with_every_method(tmp_path):
    """Every method of the catalogue in three groups, students and efficiency: one row per file, six
    columns (the efficiency files hold the ratio only, not its interval)."""
    from pipeline.orchestration.dag import dvc_stages

    groups = ("KCP", "CVI", "HJM")
    summary = _summary(groups, tuple(METHODS))
    assert _dvc(tmp_path, "init", "--no-scm", "-q").returncode == 0
    stages = dvc_stages()
    metrics = [m for n in ("evaluate", "analyze_teacher", "benchmark", "report") for m in stages[n]["metrics"]]
    (tmp_path / "dvc.yaml").write_text(json.dumps({"stages": {"results": {"cmd": "true", "metrics": metrics}}}))
    art = tmp_path / "artifacts"
    R.write_metrics_dir(catalog.path("metrics_students", art), R.student_metric_files(summary))
    R.write_metrics_dir(catalog.path("metrics_efficiency", art),
                        R.efficiency_metric_files(summary, {g: 0.6123 for g in groups}))
    R.write_metrics_dir(catalog.path("metrics_teacher", art),
                        {f"{g}.json": {"iou": 0.6123, "bf1": 0.7123, "gate_share": 0.75} for g in groups})
    write_json(catalog.path("metrics_deploy", art), {"latency_ms": 12.5})
    r = _dvc(tmp_path, "metrics", "show")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert lines[0].split() == ["Path", "bf1", "efficiency", "gate_share", "iou", "latency_ms"]
    assert len(lines) == 1 + 2 * 3 * len(METHODS) + 3 + 1
    assert max(map(len, lines)) <= 120, r.stdout


# --------------------------------------------------------------------------------------------------
# distill's summary line
# --------------------------------------------------------------------------------------------------
def _project(out: Path, groups=("test",), export=PROPOSED, efficiency=0.8712) -> Path:
    """A finished distill project's params.yaml and DVC metrics files (as the stages write them)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "params.yaml").write_text(f"profile: distill\ndeploy:\n  export_method: {export}\n")
    art = out / catalog.ARTIFACTS_DIR
    summary = _summary(groups, (BASELINE, PROPOSED))
    R.write_metrics_dir(catalog.path("metrics_students", art), R.student_metric_files(summary))
    vote = {g: round(0.5123 / efficiency, 4) for g in groups}
    R.write_metrics_dir(catalog.path("metrics_teacher", art), {f"{g}.json": {"iou": v} for g, v in vote.items()})
    R.write_metrics_dir(catalog.path("metrics_efficiency", art), R.efficiency_metric_files(summary, vote))
    return out


def test_efficiency_line_names_the_deployed_students_ratio_and_both_ious(tmp_path):
    from pipeline.orchestration.standalone import efficiency_line

    line = efficiency_line(_project(tmp_path / "p"))
    assert line == (f"the student's test Image IoU is 0.87 × the teacher vote's Image IoU ({method_label(PROPOSED)}: "
                    f"0.512; the vote: {0.5123 / 0.8712:.3f}, on the same held-out images with masks)")
    # several groups: a ratio per group
    line = efficiency_line(_project(tmp_path / "g", groups=("KCP", "HJM"), export=BASELINE))
    assert line.startswith("the student's test Image IoU is 0.87 × (HJM), 0.87 × (KCP) the teacher vote's Image IoU "
                           "(Plain Student,")


def test_no_efficiency_ratio_over_a_vote_that_found_almost_nothing_and_the_line_says_why(tmp_path):
    from pipeline.orchestration.standalone import MIN_VOTE_IOU, efficiency_line

    # the case: a student IoU of 0.19 over a vote of 0.004 (47.5 ×) is no ratio to print
    line = efficiency_line(_project(tmp_path / "p", efficiency=47.5))
    assert "×" not in line and "47.5" not in line and f"below {MIN_VOTE_IOU:g}" in line, line
    assert line.startswith("no distillation efficiency: the teacher vote's test Image IoU is 0.011"), line


def test_no_efficiency_line_without_masks(tmp_path):
    """No efficiency file (a project without --val-masks writes an empty folder), or none for the
    deployed method: no line."""
    from pipeline.orchestration.standalone import efficiency_line

    out = _project(tmp_path / "p")
    R.write_metrics_dir(catalog.path("metrics_efficiency", out / catalog.ARTIFACTS_DIR), {})
    assert efficiency_line(out) is None
    assert efficiency_line(_project(tmp_path / "q", export="continuation")) is None


def test_distill_prints_the_line_after_its_summary(tmp_path, monkeypatch):
    """The command's last lines, with the project's run replaced by the finished files."""
    import pipeline.cli.distill as distill

    project = _project(tmp_path / "out")
    monkeypatch.setattr(distill, "write_project", lambda *a, **k: project)
    monkeypatch.setattr(distill, "run_project", lambda *a, **k: None)
    (tmp_path / "in").mkdir()
    res = CliRunner().invoke(distill.main, [str(tmp_path / "in"), "--out", str(project), "--backend", "imported",
                                            "--imported-dir", str(tmp_path / "in")], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    lines = res.output.strip().splitlines()
    assert lines[-2].startswith("distill: report ") and lines[-1].startswith("distill: the student's test Image IoU is 0.87 × the teacher vote's")


def test_distill_quiet_runs_dvc_quiet_and_the_stages_at_warning(tmp_path, monkeypatch):
    """-q: only warnings, errors and the summary -- `dvc repro -q` (no stage lines) and the stages' INFO
    step log off; without -q both stay."""
    import io
    import subprocess

    import pipeline.orchestration.standalone as S

    seen = []

    class FakeDvc:
        def __init__(self, args, env=None, **kw):
            seen.append((args, env))
            self.stdout, self.stderr = io.StringIO(""), io.StringIO("")

        def wait(self):
            return 0

    monkeypatch.setattr(subprocess, "Popen", FakeDvc)
    monkeypatch.delenv("GEODISTILL_LOG", raising=False)
    S.run_project(tmp_path, quiet=True)
    S.run_project(tmp_path)
    (quiet_args, quiet_env), (args, env) = seen
    assert quiet_args[-2:] == ["repro", "-q"] and quiet_env["GEODISTILL_LOG"] == "WARNING"
    assert args[-1] == "repro" and "GEODISTILL_LOG" not in env
