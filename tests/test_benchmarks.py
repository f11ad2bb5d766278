"""The benchmark scripts still run (tiny sizes) and print a ratio against their baseline.

No timing is asserted here: performance targets live in the scripts' output, not in tests.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

CASES = {
    "bench_memory": ["--n", "2", "--factor", "2", "--size", "32", "--label-size", "32", "--read-size", "32",
                     "--reps", "1"],
    "bench_geometry": ["--n", "4", "--size", "64", "--repeats", "1", "--workers", "1"],
    "bench_synthetic": ["--size", "48", "--views", "2", "--baseline-views", "1"],
    "bench_train": ["--images", "4", "--size", "32", "--epochs", "1", "--reps", "1", "--val-images", "2"],
    "bench_teacher": ["--images", "2", "--resolution", "32"],
    "bench_evaluate": ["--runs", "3", "--images", "6", "--size", "48", "--resamples", "50", "--repeats", "1",
                       "--student-images", "1"],
}


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(CASES))
def test_benchmark_script_runs_and_reports_a_ratio(name):
    r = subprocess.run([sys.executable, "-m", f"pipeline.benchmarks.{name}", *CASES[name]], cwd=ROOT,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert re.search(r"\d+(\.\d+)?\s*x", r.stdout), r.stdout[-2000:]  # "<ratio> x" against the baseline


@pytest.mark.slow
def test_teacher_benchmark_on_ray_prints_each_pools_start_up_and_ratio():
    pytest.importorskip("ray")
    r = subprocess.run([sys.executable, "-m", "pipeline.benchmarks.bench_teacher", "--ray-workers", "1,2",
                        "--images", "8", "--resolution", "32", "--repeats", "1"], cwd=ROOT,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    for pool in ("serial", "ray x1", "ray x2"):
        assert re.search(rf"{pool}\s+wall median .* images/s", r.stdout), r.stdout[-2000:]
        assert re.search(rf"{pool}\s+start-up median\s+\d+\.\d+ s", r.stdout), r.stdout[-2000:]
    assert re.search(r"ray x2\s+steady median .*\d\.\d\dx the 1-worker pool", r.stdout), r.stdout[-2000:]
    assert re.search(r"\n\s+8 images: ray x2 \d\.\d\dx the 1-worker pool", r.stdout), r.stdout[-2000:]
