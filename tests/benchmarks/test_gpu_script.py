"""The prepared GPU script (reports/gpu/run.sh, issue 57 item 6) on the CPU, with a tiny fake project: it returns
only small files (no *.zarr, no weights) with meta.json, under 5 MB, and a run past its deadline stops (its
processes gone) and still says what finished.  The DAG runner is the real one beside the checkout
(../shared/tools/gpu/dagrun.py) where it is there; the guard is also tested with a fake runner that ignores its
deadline, injected through DAGRUN."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import subprocess
import sys
import tarfile
import textwrap
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
RUN_SH = REPO / "reports" / "gpu" / "run.sh"
SHARED_DAGRUN = REPO.parent / "shared" / "tools" / "gpu" / "dagrun.py"
META_FIELDS = ("date_utc", "end_utc", "card", "torch", "cuda", "code_commit", "deadline_s", "sections_asked",
               "sections", "finished", "status", "elapsed_s", "archive_files", "returned")


def collect_module():
    spec = importlib.util.spec_from_file_location("gpu_collect", REPO / "reports" / "gpu" / "collect.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def run_script(tmp_path: Path, deadline: float, **env) -> tuple[dict, float]:
    out = tmp_path / "out"
    full = {**os.environ, "OUT": str(out), "WORK": str(tmp_path / "work"), "PYTHON": sys.executable,
            "GPU_DIR": str(tmp_path / "no-gpu-dir"), "DEVICE": "cpu", "SECTIONS": "dag", "DEADLINE": str(deadline),
            "COLLECT_S": "1", "MIN_SECTION_S": "1", **env}
    t0 = time.perf_counter()
    r = subprocess.run(["bash", str(RUN_SH)], env=full, capture_output=True, text=True, timeout=60)
    wall = time.perf_counter() - t0
    assert r.returncode == 0, r.stdout + r.stderr
    meta = json.loads((out / "meta.json").read_text())
    returned = [p for p in out.iterdir()]
    assert all(p.is_file() and re.fullmatch(r"[A-Za-z0-9._-]+", p.name) for p in returned)  # the device returns these
    assert len(returned) <= 8 and sum(p.stat().st_size for p in returned) < 5_000_000
    return meta, wall


def fake_project(root: Path) -> Path:
    """Three stages: ``fast`` writes a metric, a 2 MB *.zarr chunk, weights and a 6 MB log; ``slow`` sleeps past
    any deadline (its pid in slow.pid); ``after`` waits for ``slow``."""
    proj = root / "proj"
    proj.mkdir()
    fast = ("import os, json; os.makedirs('reports/metrics', exist_ok=True); "
            "json.dump(dict(iou=0.5), open('reports/metrics/fast.json', 'w')); "
            "os.makedirs('artifacts/images.zarr', exist_ok=True); "
            "open('artifacts/images.zarr/c0', 'wb').write(os.urandom(2000000)); "
            "open('artifacts/w.safetensors', 'wb').write(os.urandom(1000000)); print('x' * 6000000)")
    slow = "import os, time; open('slow.pid', 'w').write(str(os.getpid())); time.sleep(60)"
    (proj / "dvc.yaml").write_text(textwrap.dedent(f"""\
        stages:
          fast:
            cmd: python -c "{fast}"
            outs: [reports/metrics/fast.json, artifacts/images.zarr]
          slow:
            cmd: python -c "{slow}"
            deps: [reports/metrics/fast.json]
            outs: [reports/slow.json]
          after:
            cmd: python -c "print(1)"
            deps: [reports/slow.json]
            outs: [reports/after.json]
        """))
    (proj / "params.yaml").write_text("seed: 1\n")
    return proj


def gone(pid: int, wait: float = 3.0) -> bool:
    """Whether process ``pid`` has ended within ``wait`` seconds (a killed process is reaped a moment later)."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < wait:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.05)
    return False


@pytest.mark.skipif(not SHARED_DAGRUN.is_file(), reason="../shared/tools/gpu/dagrun.py is not beside the checkout")
def test_a_dag_past_its_deadline_stops_and_returns_only_its_metrics_and_logs(tmp_path):
    proj = fake_project(tmp_path)
    # deadlines of a few seconds: room for the script's own start on a loaded CI host
    meta, wall = run_script(tmp_path, 8, PROJ=str(proj), DAGRUN=str(SHARED_DAGRUN))
    assert wall < 8 + 3
    assert all(k in meta for k in META_FIELDS) and meta["deadline_s"] == 8 and meta["card"] is None
    assert meta["status"] == "deadline"
    dag = meta["finished"]["dag"]
    assert dag["finished"] == ["fast"] and dag["running_at_deadline"] == ["slow"]
    assert dag["pending_at_deadline"] == ["after"]
    assert gone(int((proj / "slow.pid").read_text()))  # stopped, not left running on the card
    with tarfile.open(tmp_path / "out" / meta["archive"]) as tar:
        names = tar.getnames()
        assert json.load(tar.extractfile("dag/reports/metrics/fast.json")) == {"iou": 0.5}
        log = tar.extractfile("dag/logs/fast.log").read()
    assert not any(".zarr" in n or n.endswith(".safetensors") for n in names)
    assert "dag/logs/timings.json" in names and "dag/logs/fast.log" in meta["logs_cut_to_tail"]
    assert len(log) < 25_000 and log.rstrip().endswith(b"x" * 100)  # the log's tail, not its head


def test_a_section_that_ignores_its_deadline_is_killed_and_meta_json_still_says_so(tmp_path):
    runner = tmp_path / "stubborn.py"  # a runner that ignores SIGTERM and its deadline argument
    runner.write_text("import os, signal, sys, time\nsignal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
                      "open(sys.argv[1] + '.pid', 'w').write(str(os.getpid()))\nprint('started', flush=True)\n"
                      "time.sleep(60)\n")
    meta, wall = run_script(tmp_path, 6, PROJ=str(tmp_path / "p"), DAGRUN=str(runner))
    assert wall < 6 + 2
    (section,) = meta["sections"]
    assert section["section"] == "dag" and section["timed_out"] and section["seconds"] <= section["budget_s"] + 0.5
    assert meta["status"] == "deadline" and all(k in meta for k in META_FIELDS)
    assert gone(int((tmp_path / "p.pid").read_text()))
    with tarfile.open(tmp_path / "out" / meta["archive"]) as tar:
        assert b"started" in tar.extractfile("logs/dag.log").read()


def test_the_collected_set_is_cut_under_its_limit_logs_first():
    c = collect_module()
    files = {"a.log": b"a" * 3000, "b.log": b"b" * 500, "m.json": b"{}" * 100, "t.json": b"1" * 2000,
             "huge.csv": b"h" * (c.MAX_FILE_BYTES + 1)}
    kept, cut, dropped = c.fit(files, limit=3000, tail=100)
    assert dropped == ["huge.csv"] and cut == ["a.log"] and kept["a.log"].endswith(b"a" * 100)
    assert kept["b.log"] == files["b.log"]  # under the limit once the largest log is cut: the next one stays whole
    assert sum(map(len, kept.values())) <= 3000 and kept["t.json"] == files["t.json"]
    kept, cut, dropped = c.fit(files, limit=1000, tail=100)  # logs cut are not enough: the largest file goes
    assert "t.json" in dropped and "m.json" in kept and sum(map(len, kept.values())) <= 1000
    assert c.section_budget(100, end=1000, reserve=20, now=950) == 30
    assert c.section_budget(None, end=1000, reserve=20, now=990) == 0
