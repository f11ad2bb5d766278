"""The tests' shared fixtures: tiny artifacts, a one-epoch Stage-I state, the tiny random SAM 3 and tiny
student checkpoints, each built once per module (or once per session) for every module that asks.

The rule of this folder: **no test module imports another test module** (``test_*.py``; a test module
imported by another would be collected twice and share its fixtures by import, which pyflakes reports as
redefinitions).  What several modules share lives here (fixtures) or in a builder module under ``tests/builders/``
(plain functions and constants), imported as ``tests.builders.name``:

- ``tests/builders/training.py``  -- the training tests' tiny artifacts and helpers (``build_tiny_artifacts``,
  ``tiny_cfg``, ``load_arrays``, the train-stage subprocess);
- ``tests/builders/evaluation.py``   -- the result stages' tiny artifacts with random checkpoints, their params
  and command runner;
- ``tests/builders/deploy.py`` -- a tiny random student, its checkpoint, thresholds, artifacts, export;
- ``tests/builders/teacher.py`` -- the teacher stage's tiny artifacts and runner, a folder of images and the
  ``geodistill`` command runner.

- ``tests/builders/lane.py``  -- the second lane: the long subprocess-only runs (the tiny demo DAG, the two
  ``distill`` runs, the benchmark scripts) started in the background when the session starts.

Helper modules import no test module either; tests/house/test_test_layout.py checks both.  The fixtures
import their helpers when first used, so that a run of a light test module does not load them.

**The lane** (wall time on CI's two cores): a test that checks a long run asks for a fixture that
*waits* for it (:data:`LANE_FIXTURES`: ``tiny_demo``, ``distill_without_masks``, ``distill_with_masks``,
``bench_script``, ``bench_teacher_ray``).  When the session starts, ``_lane_prefetch`` queues every run
the selected tests will wait for, in the order they will wait, on one background thread that starts
the same commands as subprocesses; meanwhile the other tests run.  The modules holding such a test
run last (``pytest_collection_modifyitems``), so their runs are usually done when they are reached.  A
run of one such module alone takes as long as before: its test waits at once.  Last, the lane runs whole
modules (``LANE_MODULES``) in a pytest process of its own when their collector
(tests/house/test_lane_modules.py) is selected too, which then asserts that they all passed.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
from pathlib import Path

import pytest

# One CPU thread per process: the suite runs as two lanes on CI's two cores (below), and torch's OpenMP
# threads spin-wait when two processes of two threads share them (docs/performance.md).  Set before torch
# is imported here; the lane's subprocesses inherit it (``Lane.env``); a test that needs another count sets
# its own.
os.environ["OMP_NUM_THREADS"] = "1"

#: the fixtures that wait for a run on the lane (tests/builders/lane.py), and the run's key
LANE_FIXTURES = {"tiny_demo": "tiny_demo", "distill_without_masks": "distill_nomasks",
                 "distill_with_masks": "distill_masks", "bench_teacher_ray": "bench:bench_teacher_ray",
                 "lane_modules": "modules"}
#: whole test modules the lane runs in a pytest process of its own, last, when the session also selects
#: their collector (tests/house/test_lane_modules.py): subprocess-heavy training tests, about 80 s that the
#: main process would otherwise run while the lane sits idle (docs/performance.md).  Set in that process.
LANE_MODULES = ("tests/training/test_training.py", "tests/training/test_train_grouped.py")
LANE_COLLECTOR = "tests/house/test_lane_modules.py"
ON_LANE = "GEODISTILL_TESTS_ON_LANE"
_MODULES_ON_LANE = pytest.StashKey[list]()
_LANE_MODULES_RUN = pytest.StashKey[object]()


def _lane_keys(item) -> list[str]:
    """The lane runs the test ``item`` waits for."""
    names = getattr(item, "fixturenames", ())
    keys = [key for name, key in LANE_FIXTURES.items() if name in names]
    if "bench_script" in names and hasattr(item, "callspec"):
        keys.append(f"bench:{item.callspec.params['bench_script']}")
    return keys


@pytest.hookimpl(trylast=True)  # after -k / -m deselection: the lane runs exactly what is selected
def pytest_collection_modifyitems(config, items):
    """The :data:`LANE_MODULES` leave this process for the lane when their collector is selected too (not
    inside the lane's own pytest); the modules with a test that waits for a lane run go last, in their
    order (their runs have the rest of the session to finish in the background), the collector at the end."""
    module = lambda item: item.nodeid.split("::")[0]  # noqa: E731 -- relative to the repository (rootdir)
    moved = [i for i in items if module(i) in LANE_MODULES]
    if moved and not os.environ.get(ON_LANE) and any(module(i) == LANE_COLLECTOR for i in items):
        config.stash[_MODULES_ON_LANE] = [i.nodeid for i in moved]
        config.hook.pytest_deselected(items=moved)
        items[:] = [i for i in items if i not in moved]
    last = {item.path for item in items if _lane_keys(item)}
    items.sort(key=lambda i: 2 if "lane_modules" in getattr(i, "fixturenames", ()) else int(i.path in last))


@pytest.fixture(scope="session")
def lane():
    """The second lane (tests/builders/lane.py); its runs are killed when the session ends."""
    from tests.builders.lane import Lane

    lane = Lane()
    yield lane
    lane.close()


def _submit(request, lane, key: str) -> None:
    """Queue the lane run ``key`` (once), with what it needs from this session (folders, the tiny SAM 3)."""
    from tests.builders import lane as tl

    if key in lane.jobs:
        return
    factory = request.getfixturevalue("tmp_path_factory")
    if key == "tiny_demo":
        if shutil.which("git") is None:
            pytest.skip("git not available")
        lane.submit(key, tl.tiny_demo_run, factory.mktemp("repo"))
    elif key in ("distill_nomasks", "distill_masks"):
        sam3 = request.getfixturevalue("tiny_sam3")
        images, val = request.getfixturevalue("distill_folder")
        if key == "distill_nomasks":
            lane.submit(key, tl.distill_run, images, factory.mktemp("distill") / "nomasks", sam3)
        else:
            lane.submit(key, tl.distill_run, images, factory.mktemp("distill") / "masks", sam3, "--val-masks", val)
    elif key == "modules":
        nodeids = request.config.stash.get(_MODULES_ON_LANE, [])
        if not nodeids:
            pytest.skip("the lane runs no modules in this session (their collector runs them only with the rest)")
        lane.submit(key, tl.pytest_run, nodeids, ON_LANE)
    elif key.startswith("bench:"):
        if key.endswith("_ray") and importlib.util.find_spec("ray") is None:
            pytest.skip("ray not installed")
        lane.submit(key, tl.bench_run, key.removeprefix("bench:"))
    else:
        raise KeyError(key)


def _lane_result(request, key: str):
    lane = request.getfixturevalue("lane")
    _submit(request, lane, key)
    return lane.wait(key)


@pytest.fixture(scope="session", autouse=True)
def _lane_prefetch(request):
    """Queue on the lane every run a selected test will wait for, in the order the tests will wait."""
    keys = list(dict.fromkeys(k for item in request.session.items for k in _lane_keys(item)))
    if keys:
        lane = request.getfixturevalue("lane")
        for key in keys:
            try:
                _submit(request, lane, key)
            except pytest.skip.Exception:  # the test that waits for it skips by itself
                pass


@pytest.fixture(scope="session")
def tiny_demo(request) -> tuple[Path, dict, str]:
    """(repo, env, stdout of the first ``dvc repro``) of the tiny demo DAG run in a copy of the repository
    (tests.builders.lane.tiny_demo_run), on the lane."""
    return _lane_result(request, "tiny_demo")


@pytest.fixture(scope="session")
def distill_folder(tmp_path_factory) -> tuple[Path, Path]:
    """The distill tests' folder of 20 images and a folder of 8 of their masks (4 validation, 4 test)."""
    from tests.builders.teacher import make_image_folder

    images, masks = make_image_folder(tmp_path_factory.mktemp("data"))
    val = masks.parent / "val_masks"
    val.mkdir()
    for m in sorted(masks.iterdir())[:8]:
        (val / m.name).write_bytes(m.read_bytes())
    return images, val


@pytest.fixture(scope="session")
def distill_without_masks(request):
    """(out, finished process) of ``geodistill distill`` on :func:`distill_folder`'s images, no masks, on the lane."""
    return _lane_result(request, "distill_nomasks")


@pytest.fixture(scope="session")
def distill_with_masks(request):
    """(out, finished process) of ``geodistill distill`` with ``--val-masks``, on the lane."""
    return _lane_result(request, "distill_masks")


@pytest.fixture
def bench_script(request):
    """(name, finished process) of the benchmark script case ``request.param`` (indirect
    parametrization; tests.builders.lane.BENCH_CASES), on the lane."""
    return request.param, _lane_result(request, f"bench:{request.param}")


@pytest.fixture(scope="session")
def bench_teacher_ray(request):
    """The teacher benchmark's run with Ray pools of 1 and 2 workers (finished process), on the lane."""
    return _lane_result(request, "bench:bench_teacher_ray")


@pytest.fixture(scope="session")
def lane_modules(request):
    """(node ids, finished process) of the pytest process the lane ran :data:`LANE_MODULES` in."""
    proc = _lane_result(request, "modules")
    request.config.stash[_LANE_MODULES_RUN] = proc
    return request.config.stash[_MODULES_ON_LANE], proc


def pytest_terminal_summary(terminalreporter, config):
    """The summary line of the lane's pytest process, below this one's."""
    proc = config.stash.get(_LANE_MODULES_RUN, None)
    if proc is not None:
        last = (proc.stdout.strip().splitlines() or ["no output"])[-1]
        terminalreporter.write_line(f"the lane's pytest process ({', '.join(LANE_MODULES)}): {last}")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    """The training tests' tiny artifacts (tests/builders/training.py), built once per module."""
    from tests.builders.training import build_tiny_artifacts

    return build_tiny_artifacts(tmp_path_factory.mktemp("tiny") / "artifacts")


@pytest.fixture(scope="module")
def stage1_state(tiny) -> dict:
    """The mask-path state of a one-epoch Stage-I ``plain`` run on ``tiny`` (seed 42): the warm start
    of the Stage-II methods."""
    from pipeline.training import loop as training
    from pipeline.training.checkpointing import NoCheckpointer
    from pipeline.methods import get_method
    from tests.builders.training import load_arrays, tiny_cfg

    cfg = tiny_cfg(epochs_stage1=1)
    data, val = load_arrays(tiny, "plain", cfg)
    return training.train(get_method("plain"), cfg, data, val, 42, checkpointer=NoCheckpointer(),
                          show_progress=False).model.mask_path_state_dict()


@pytest.fixture(scope="session")
def tiny_sam3(tmp_path_factory) -> Path:
    """The tiny random SAM 3 (pipeline/teachers/tiny_sam3.py) whose vocabulary holds the words of the
    paper's prompts, saved once per session (skipped without transformers)."""
    pytest.importorskip("transformers")
    from pipeline.params import PAPER_PROMPTS
    from pipeline.teachers.tiny_sam3 import build_tiny_sam3

    words = tuple(dict.fromkeys(w for p in PAPER_PROMPTS for w in p.split()))
    return build_tiny_sam3(tmp_path_factory.mktemp("sam3") / "tiny-sam3", words=words)


@pytest.fixture(scope="session")
def fitted_tiny_sam3(tmp_path_factory) -> Path:
    """A tiny SAM 3 fitted to bright-box scenes under the paper's prompts (``fit_tiny_sam3``: a trained
    model's logit margins, for numerics tests), saved once per session (skipped without transformers)."""
    pytest.importorskip("transformers")
    from pipeline.params import PAPER_PROMPTS
    from pipeline.teachers.tiny_sam3 import fit_tiny_sam3

    return fit_tiny_sam3(tmp_path_factory.mktemp("sam3") / "fitted-tiny-sam3", tuple(PAPER_PROMPTS))


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory) -> dict[str, Path]:
    """A tiny checkpoint recording its training resolution (as the train stage writes it) and the same
    weights without it (an older checkpoint)."""
    import pandas as pd

    from pipeline.artifacts.lineage import make_meta
    from pipeline.evaluation.inference import save_checkpoint
    from tests.builders.deploy import RES, tiny_model

    root = tmp_path_factory.mktemp("ckpts")
    log = pd.DataFrame({"epoch": [1], "stage": [1], "loss": [0.1], "val_iou": [0.5], "val_bf1": [0.5],
                        "lr": [1e-4]})
    meta = make_meta("checkpoint", "train", "test", {"seed": 42, "method": "geodistill"})
    common = dict(method="geodistill", seed=42, stage=1, selected_epoch=1, tau=0.5)
    return {"with": save_checkpoint(root / "with", tiny_model(3), meta, log, resolution=RES, **common),
            "without": save_checkpoint(root / "without", tiny_model(3), meta, log, **common)}


@pytest.fixture
def cpu_host(monkeypatch):
    """Pose as a CPU host for the precision and engine rules: ``cpu_host(flags, vendor, isa)`` sets
    ``pipeline.runtime.device``'s flags and vendor, and ``ONEDNN_MAX_CPU_ISA`` (None: unset)."""
    from pipeline.runtime import device

    def pose(flags, vendor: str = "GenuineIntel", isa: str | None = None) -> None:
        monkeypatch.setattr(device, "cpu_flags", lambda: frozenset(flags))
        monkeypatch.setattr(device, "cpu_vendor", lambda: vendor)
        if isa is None:
            monkeypatch.delenv("ONEDNN_MAX_CPU_ISA", raising=False)
        else:
            monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", isa)

    return pose
