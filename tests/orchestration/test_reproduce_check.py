"""CI's reproduction check: pipeline.reproducibility.compare_metrics and ``geodistill reproduce-check``
against metrics committed in a throw-away git repository."""

from __future__ import annotations

import json
import shutil
import subprocess

import pytest
from click.testing import CliRunner

from pipeline.reproducibility import TOLERANCE, compare_metrics, difference_table, reproduced
from pipeline.cli.reproduce_check import main as reproduce_check

COMMITTED = {"KCP/plain.json": {"iou": 0.4361, "bf1": 0.5208}, "KCP/geodistill.json": {"iou": 0.4537, "bf1": 0.563}}


def _shifted(key: str, by: float) -> dict:
    """COMMITTED with KCP/plain.json's ``key`` moved by ``by``."""
    out = {f: dict(m) for f, m in COMMITTED.items()}
    out["KCP/plain.json"][key] = round(out["KCP/plain.json"][key] + by, 4)
    return out


@pytest.mark.parametrize("key", sorted(TOLERANCE))
def test_just_over_tolerance_fails_and_just_under_or_at_passes(key):
    tol = TOLERANCE[key]
    for by in (tol + 1e-4, -(tol + 1e-4)):
        rows = compare_metrics(COMMITTED, _shifted(key, by))
        assert not reproduced(rows)
        assert [(r.file, r.key, r.status) for r in rows if r.status != "ok"] == [("KCP/plain.json", key, "over")]
    for by in (tol - 1e-4, -(tol - 1e-4), tol):  # exactly at the tolerance reproduces (4-decimal values)
        assert reproduced(compare_metrics(COMMITTED, _shifted(key, by))), by


def test_missing_and_extra_files_and_keys_are_failures_named_in_the_table():
    fresh = {"KCP/plain.json": {"iou": 0.4361}, "CVI/plain.json": {"iou": 0.4, "bf1": 0.5}}
    rows = compare_metrics(COMMITTED, fresh)
    status = {(r.file, r.key): r.status for r in rows}
    assert status == {("CVI/plain.json", "iou"): "extra", ("CVI/plain.json", "bf1"): "extra",
                      ("KCP/geodistill.json", "iou"): "missing", ("KCP/geodistill.json", "bf1"): "missing",
                      ("KCP/plain.json", "iou"): "ok", ("KCP/plain.json", "bf1"): "missing"}
    assert not reproduced(rows)
    table = difference_table(rows)
    assert "| KCP/geodistill.json | iou | 0.4537 | -- | -- | 0.0100 | MISSING in the fresh run |" in table
    assert "| CVI/plain.json | bf1 | -- | 0.5000 | -- | 0.0200 | NOT COMMITTED (only in the fresh run) |" in table
    assert not reproduced(compare_metrics({}, {}))  # nothing compared is not a pass


@pytest.fixture
def repo(tmp_path, monkeypatch):
    """A git repository with COMMITTED under reports/metrics/students; cwd = its root."""
    if shutil.which("git") is None:
        pytest.skip("git not available")
    metrics = tmp_path / "reports" / "metrics" / "students"
    for rel, m in COMMITTED.items():
        (metrics / rel).parent.mkdir(parents=True, exist_ok=True)
        (metrics / rel).write_text(json.dumps(m))
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t", "-c", "commit.gpgsign=false"]
    for cmd in (["init", "-q"], ["add", "-A"], ["commit", "-q", "-m", "metrics"]):
        subprocess.run(git + cmd, cwd=tmp_path, check=True, capture_output=True)
    monkeypatch.chdir(tmp_path)
    return metrics


def test_cli_passes_prints_the_table_and_fails_beyond_tolerance(repo):
    res = CliRunner().invoke(reproduce_check, [])
    assert res.exit_code == 0, res.output
    assert "| KCP/plain.json | bf1 | 0.5208 | 0.5208 | +0.0000 | 0.0200 | ok |" in res.output
    assert "all 4 metrics within tolerance" in res.output

    (repo / "KCP" / "plain.json").write_text(json.dumps({"iou": 0.4361, "bf1": 0.5208 + TOLERANCE["bf1"] + 0.001}))
    res = CliRunner().invoke(reproduce_check, [])
    assert res.exit_code == 1
    assert "| KCP/plain.json | bf1 | 0.5208 | 0.5418 | +0.0210 | 0.0200 | DIFFERS |" in res.output
    assert "FAILED: 1 of 4 metrics not reproduced" in res.output

    (repo / "KCP" / "geodistill.json").unlink()
    res = CliRunner().invoke(reproduce_check, [])
    assert res.exit_code == 1 and "MISSING in the fresh run" in res.output


def test_cli_bad_input_is_one_line_and_exit_2(repo, tmp_path_factory, monkeypatch):
    res = CliRunner().invoke(reproduce_check, ["--ref", "no-such-ref"])
    assert res.exit_code == 2 and "error: git ls-tree" in res.output
    (repo / "KCP" / "plain.json").write_text('{"iou": "high"}')
    res = CliRunner().invoke(reproduce_check, [])
    assert res.exit_code == 2 and "plain.json: expected a JSON object of numbers" in res.output
    monkeypatch.chdir(tmp_path_factory.mktemp("not_a_repo"))
    res = CliRunner().invoke(reproduce_check, [])
    assert res.exit_code == 2 and "error: git rev-parse" in res.output
