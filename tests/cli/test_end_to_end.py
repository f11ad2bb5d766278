"""The real DAG (dvc.yaml + every stage script) on a tiny synthetic benchmark, in a temporary copy of
the repository; then the example notebook against the run it produced.

This is the test that fails when dvc.yaml and the stage command lines drift apart.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.builders.lane import TINY_DEMO

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def tiny_run(tiny_demo):
    """The demo's DAG on :data:`TINY_DEMO` sizes with one seed of each method, run by ``dvc repro`` in a copy
    of the repository (tests.builders.lane.tiny_demo_run, on the tests' second lane: tests/conftest.py):
    (repo, env, the first repro's stdout, a command runner in the repo)."""
    repo, env, first = tiny_demo
    run = lambda *a: subprocess.run(list(a), cwd=repo, env=env, capture_output=True, text=True)  # noqa: E731
    return repo, env, first, run


@pytest.mark.slow
def test_dag_runs_end_to_end_and_is_a_noop_the_second_time(tiny_run):
    repo, env, first, run = tiny_run
    import pipeline
    from pipeline.evaluation.inference import iter_runs

    art = repo / "artifacts"
    for name in ("manifest.parquet", "images.zarr", "reference.zarr", "teacher.zarr", "consensus.zarr",
                 "geometry.zarr", "gates.parquet", "thresholds.parquet", "metrics.parquet"):
        a = pipeline.open_artifact(art / name)  # validates schema
        assert len(a.meta.fingerprint) == 64
    runs = {(m, s) for m, s, _ in iter_runs(art / "checkpoints")}
    assert runs == {("plain", 42), ("geodistill", 42), ("continuation", 42)}  # the demo profile's active entries only
    metrics = pipeline.open_artifact(art / "metrics.parquet").df
    assert set(metrics.method) == {"plain", "geodistill", "continuation"}
    assert (repo / "reports" / "demo" / "report.html").exists()
    second = run(sys.executable, "-m", "dvc", "repro")
    assert second.returncode == 0 and "Running stage" not in second.stdout, second.stdout[-2000:]
    status = run(sys.executable, "-m", "dvc", "status")
    assert "up to date" in status.stdout, status.stdout


@pytest.mark.slow
def test_every_train_run_and_the_report_record_their_environment(tiny_run):
    """Each checkpoint's meta.json says what it ran on (precision actually used, torch threads = the tiny
    profile's train.num_threads, CPU); the report carries the same records in environment.json.  None of
    it is a fingerprinted param."""
    import json

    import pipeline
    from pipeline.artifacts.lineage import fingerprint
    from pipeline.evaluation.inference import iter_runs

    repo = tiny_run[0]
    records = {}
    for method, seed, path in iter_runs(repo / "artifacts" / "checkpoints"):
        meta = pipeline.open_artifact(path).meta
        rt = meta.extra["runtime"]
        assert rt["num_threads"] == TINY_DEMO["train"]["num_threads"] and rt["device"] == "cpu"
        assert meta.extra["autocast"] in ("bfloat16", "fp32") and rt["cpu_flags"] is not None
        # the fingerprint is (stage, code, params, inputs) alone: the machine record is not among them
        assert "runtime" not in json.dumps(meta.params) and meta.fingerprint == fingerprint(
            meta.stage, meta.code_version, meta.params, [i["fingerprint"] for i in meta.inputs])
        records[(method, seed)] = (meta.extra["autocast"], rt)
    env = json.loads((repo / "reports" / "demo" / "environment.json").read_text())
    assert {(r["method"], r["seed"]): (r["precision"], r["runtime"]) for r in env["training_runs"]} == records
    assert "## Environment" in (repo / "reports" / "demo" / "report.md").read_text()


@pytest.mark.slow
def test_notebook_opens_every_artifact(tiny_run):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    repo, env, _, _ = tiny_run
    nb = nbformat.read(ROOT / "reports" / "explore_artifacts.ipynb", as_version=4)
    old = dict(os.environ)
    os.environ["GEODISTILL_ARTIFACTS"] = str(repo / "artifacts")
    try:
        nbclient.NotebookClient(nb, timeout=300, kernel_name="python3",
                                resources={"metadata": {"path": str(repo)}}).execute()
    finally:
        os.environ.clear()
        os.environ.update(old)
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"]
    assert any("image/png" in o.get("data", {}) for o in outputs)  # it drew the pseudo-targets
