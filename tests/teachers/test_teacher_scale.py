"""The teacher past one machine: the fsspec cache (local and ``memory://``), existence by listing,
corrupt entries recomputed at assembly, retried jobs, and the Ray Data path against the serial loop."""

from __future__ import annotations

import re
import uuid

import numpy as np
import pytest
from fsspec.core import url_to_fs

from pipeline.artifacts.store import open_artifact
from pipeline.teachers.base import TeacherInput
from pipeline.teachers.cache import TeacherCache
from pipeline.teachers.distributed import JOBS_PER_BLOCK, TeacherWorker, decode_jobs, job_blocks
from pipeline.teachers import runner as runner_module
from pipeline.teachers.jobs import TeacherBuildArgs, in_view
from pipeline.teachers.runner import TeacherRunner
from pipeline.teachers.simulated import PERSONAS, SimulatedFoundationTeacher
from tests.builders.teacher import FAST, build_artifacts, cli, make_image_folder, run_stage, teacher_items

PROMPTS = list(PERSONAS)
RES = (32, 32)


@pytest.fixture(params=["local", "memory"])
def cache_root(request, tmp_path):
    root = str(tmp_path / "cache") if request.param == "local" else f"memory://geodistill-test-{uuid.uuid4().hex}"
    yield root
    fs, path = url_to_fs(root)
    if request.param == "memory" and fs.exists(path):
        fs.rm(path, recursive=True)


class Loader:
    """(row, view) -> TeacherInput over test items (picklable, like the stage's loader)."""

    def __init__(self, items):
        self.items = items

    def __call__(self, row, view):
        it = self.items[row]
        return TeacherInput(it.image_id, it.image_sha256, in_view(it.image, view), view,
                            {k: in_view(v, view) for k, v in it.reference.items()}, it.extras)


def _runner(root, items, batch_size=3):
    spec = TeacherBuildArgs({"backend": "simulated", "seed": 0, "cache_dir": str(root)}, RES, "cpu")
    teacher = SimulatedFoundationTeacher(seed=0, resolution=RES)
    cache = TeacherCache(root, "fp-test")
    return TeacherRunner(teacher, cache, PROMPTS, image_sha=lambda r: items[r].image_sha256, load=Loader(items),
                         vflip_prompt=PROMPTS[0], batch_size=batch_size, spec=spec)


def _all_answers(runner, rows):
    return [runner.answers(r) for r in rows]


def test_cache_round_trip_listing_and_corruption(cache_root):
    cache = TeacherCache(cache_root, "fp")
    keys = [cache.key(f"sha{i}", "spacecraft") for i in range(3)]
    assert cache.listed() == set() and cache.get(keys[0]) is None
    for i, k in enumerate(keys):
        cache.put(k, np.eye(5, dtype=bool) ^ bool(i), 0.25 * (i + 1))
    assert cache.listed() == set(keys)
    mask, score = cache.get(keys[1])
    np.testing.assert_array_equal(mask, ~np.eye(5, dtype=bool))
    assert score == pytest.approx(0.5)
    cache.fs.pipe_file(str(cache.path(keys[2])), b"garbage")           # damaged in place
    assert keys[2] in cache.listed()                                    # listing does not read it
    assert cache.get(keys[2]) is None and cache.stats.corrupt == 1      # reading does, and removes it
    assert cache.listed() == set(keys[:2])
    names = cache.fs.find(cache_root)
    assert len(names) == 2 and not [n for n in names if n.endswith(".tmp")]  # no temp file left


def test_existence_is_decided_by_listing_and_corruption_is_fixed_at_assembly(cache_root, monkeypatch):
    items, rows = teacher_items(5), range(5)
    first = _runner(cache_root, items)
    assert first.fill(rows).answers_computed == 5 * 7
    want = _all_answers(first, rows)

    again = _runner(cache_root, items)
    reads = []
    real = type(again.cache.fs).cat_file
    monkeypatch.setattr(type(again.cache.fs), "cat_file", lambda fs, p, *a, **k: reads.append(p) or real(fs, p, *a, **k))
    victim = again.cache.path(again.cache.key(items[2].image_sha256, PROMPTS[3]))
    again.cache.fs.pipe_file(str(victim), b"GDTCE02\n" + b"\0" * 80)   # corrupt, but present
    stats = again.fill(rows)
    assert (stats.answers_computed, stats.cache_hits, reads) == (0, 5 * 7, [])  # planning read nothing
    got = _all_answers(again, rows)                                      # assembly reads, finds, recomputes
    assert again.stats.cache_corrupt == 1 and again.stats.answers_computed == 1
    assert len(reads) == 5 * 7 + 1                                       # every entry once, the fixed one twice
    for (m1, s1, v1, vs1), (m2, s2, v2, vs2) in zip(want, got):
        np.testing.assert_array_equal(m1, m2)
        np.testing.assert_array_equal(s1, s2)
        np.testing.assert_array_equal(v1, v2)
        assert vs1 == vs2


def test_a_retried_job_rewrites_the_same_entries(tmp_path):
    items = teacher_items(4)
    runner = _runner(str(tmp_path / "cache"), items, batch_size=2)
    jobs = runner.jobs(runner.missing(range(4)))
    assert [len(j.rows) for j in jobs] == [2, 2, 2, 2]                  # identity x 2, vflip x 2
    worker = TeacherWorker(runner.spec, runner.cache.root, runner.cache.teacher_fingerprint, jobs)
    batch = decode_jobs({"job": np.array([1])}, jobs, runner.load)
    assert worker(batch)["written"].tolist() == [2 * len(PROMPTS)]
    files = sorted(p for p in (tmp_path / "cache").rglob("*") if p.is_file())
    before = {p: p.read_bytes() for p in files}
    assert worker(batch)["written"].tolist() == [2 * len(PROMPTS)]       # Ray retries the task
    after = sorted(p for p in (tmp_path / "cache").rglob("*") if p.is_file())
    assert after == files and {p: p.read_bytes() for p in after} == before  # no duplicate, same bytes
    # the serial loop computes only what the retried job did not
    assert runner.fill(range(4)).answers_computed == 4 * 7 - 2 * len(PROMPTS)


def test_jobs_go_to_the_pool_in_blocks_of_a_few_as_many_per_teacher():
    assert job_blocks(240, 1) == job_blocks(240, 2) == 240 // JOBS_PER_BLOCK
    assert job_blocks(0, 2) == 1 and job_blocks(1, 8) == 1 and job_blocks(3, 2) == 2
    for n in range(1, 120):
        for workers in range(1, 9):
            blocks = job_blocks(n, workers)
            assert 1 <= blocks <= n
            assert -(-n // blocks) <= JOBS_PER_BLOCK              # no block holds more than that many jobs
            assert blocks % workers == 0 or blocks == n         # each teacher gets as many blocks
            if n >= workers:
                assert blocks >= workers                        # no teacher idles for want of a block


@pytest.fixture(scope="module")
def ray_local():
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, num_gpus=2, include_dashboard=False, log_to_driver=False, logging_level="WARNING")
    yield ray
    ray.shutdown()


def _no_serial_loop(*args, **kwargs):
    raise AssertionError("the driver ran a job: the Ray actors should have")


def test_ray_data_teacher_gives_the_serial_artifact(tmp_path, monkeypatch, ray_local):
    monkeypatch.setenv("GEODISTILL_QUIET", "1")
    paths = build_artifacts(tmp_path / "a", n=6)
    assert run_stage(paths, tmp_path / "serial").exit_code == 0
    serial = {k: open_artifact(paths["out"]).numpy(k) for k in ("masks", "scores", "vflip_masks", "vflip_scores")}
    table = open_artifact(paths["scores"]).df
    with monkeypatch.context() as m:
        m.setattr(runner_module, "answer_job", _no_serial_loop)  # this process only: the actors run theirs
        res = run_stage(paths, tmp_path / "ray", "--workers", "2")
    assert res.exit_code == 0, res.output
    out = open_artifact(paths["out"])
    for k, v in serial.items():
        got = out.numpy(k)
        assert got.dtype == v.dtype and got.tobytes() == v.tobytes(), k
    assert open_artifact(paths["scores"]).df.equals(table)
    rel = lambda root: {p.relative_to(root): p.read_bytes() for p in root.rglob("*.tce")}  # noqa: E731
    assert rel(tmp_path / "ray") == rel(tmp_path / "serial")           # the same cache, entry for entry


def test_label_with_ray_workers_writes_the_serial_labels(tmp_path, monkeypatch, ray_local):
    monkeypatch.setenv("GEODISTILL_QUIET", "1")
    img_dir, mask_dir = make_image_folder(tmp_path / "data", n=8)
    outs = {}
    for name, extra in (("serial", ()), ("ray", ("--workers", "2"))):
        outs[name] = tmp_path / name
        r = cli("label", img_dir, "--out", outs[name], "--backend", "simulated", "--reference-masks", mask_dir,
                *FAST, *extra)
        assert r.exit_code == 0, r.output
        # label's cost: the projection after the first batch, under the Ray workers as serially
        how = "under 2 Ray workers" if extra else "serially"
        assert re.search(rf"first batch: [\d.]+ image\(s\) in .* 8 image\(s\) to label: about .* {how}", r.output), r.output
    files = lambda root: {p.relative_to(root): p.read_bytes() for p in root.rglob("*")  # noqa: E731
                          if p.is_file() and not p.is_symlink() and p.name not in ("label.json", "data.yaml")}
    serial, ray = files(outs["serial"]), files(outs["ray"])
    assert serial.keys() == ray.keys() and len(serial) > 8 + 3
    assert [k for k in serial if serial[k] != ray[k]] == []            # PNG, COCO, YOLO, tables, sheet, cache


def test_more_workers_than_the_cluster_holds_is_one_line(tmp_path, monkeypatch, ray_local):
    monkeypatch.setenv("GEODISTILL_QUIET", "1")
    paths = build_artifacts(tmp_path / "a", n=2)
    res = run_stage(paths, tmp_path / "cache", "--workers", "3")
    assert res.exit_code == 2 and "--workers 3: the Ray cluster has 2 CPUs" in res.output
