"""A quiet console for ``geodistill label``: progress bars that stay and count images, silenced by
``--quiet``; no third-party bar (transformers' "Loading weights"); one summary line, not also a log
line; the step log only with GEODISTILL_LOG; widgets in notebooks (ipywidgets in the notebook extra)."""

from __future__ import annotations

import logging
import re
import tomllib

import pytest

from pipeline.runtime.progress import library_bars_off, progress, quiet_bars
from tests.builders.teacher import FAST, REPO, cli, make_image_folder

N = 4


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    return make_image_folder(tmp_path_factory.mktemp("console"), n=N, masks=False)[0]


@pytest.fixture
def console(monkeypatch):
    """The user's defaults: no GEODISTILL_QUIET, no GEODISTILL_LOG."""
    monkeypatch.delenv("GEODISTILL_QUIET", raising=False)
    monkeypatch.delenv("GEODISTILL_LOG", raising=False)


def _label(images, out, tiny_sam3, *extra):
    res = cli("label", images, "--out", out, "--checkpoint", tiny_sam3, "--format", "png", *FAST, *extra)
    assert res.exit_code == 0, res.output
    return res


def test_label_bars_stay_count_images_and_one_summary_line(tmp_path, images, tiny_sam3, console, caplog):
    caplog.set_level(logging.INFO)
    err = _label(images, tmp_path / "out", tiny_sam3).stderr
    for desc in ("label: reading", r"teacher\[sam3\]", "label: vote \\+ export"):
        # the bar's final state stays on screen, counting the images (not batches of them)
        assert re.search(desc + rf": 100%\|[^\r\n]*\| {N}/{N} \[[^\]]*(img/s|s/img)\]\n", err), (desc, err)
    assert "Loading weights" not in err                      # transformers' own bar
    assert err.count(f"label: {N} images ->") == 1
    summary = [line for line in err.splitlines() if line.startswith(f"label: {N} images ->")][0]
    assert f"teacher answers {N * 6} computed, 0 cached" in summary
    # no timestamped step log by default (only warnings): the summary says what the steps did
    assert not [r for r in caplog.records if r.name.startswith("pipeline") and r.levelno < logging.WARNING]


def test_label_summary_is_not_also_a_log_line_and_the_step_log_is_there_on_request(tmp_path, images, tiny_sam3,
                                                                                    console, caplog, monkeypatch):
    monkeypatch.setenv("GEODISTILL_LOG", "INFO")
    caplog.set_level(logging.INFO)
    _label(images, tmp_path / "out", tiny_sam3)
    infos = [r.getMessage() for r in caplog.records if r.name.startswith("pipeline") and r.levelno == logging.INFO]
    assert any(m.startswith("teacher[sam3]:") for m in infos), infos       # the step log, asked for
    assert not [m for m in infos if "images ->" in m], infos                # not the summary a second time


def test_label_quiet_has_no_bars_and_keeps_the_summary(tmp_path, images, tiny_sam3, console):
    err = _label(images, tmp_path / "out", tiny_sam3, "--quiet").stderr
    assert "%|" not in err and not re.search(r"it/s|img/s|s/img", err), err
    assert err.count(f"label: {N} images ->") == 1


def test_progress_leaves_its_bar_and_quiet_bars_restores(capsys, console):
    for _ in progress(range(3), desc="x", unit="img"):
        pass
    assert re.search(r"x: 100%\|[^\r\n]*\| 3/3 ", capsys.readouterr().err)
    with quiet_bars():
        list(progress(range(3), desc="y"))
    list(progress(range(2), desc="z"))
    err = capsys.readouterr().err
    assert "y:" not in err and "z: 100%" in err


def test_library_bars_off_silences_transformers_and_restores(capsys):
    hf_logging = pytest.importorskip("transformers.utils.logging")
    hf_logging.enable_progress_bar()
    with library_bars_off():
        list(hf_logging.tqdm(range(3), desc="Loading weights"))
        assert not hf_logging.is_progress_bar_enabled()
    assert "Loading weights" not in capsys.readouterr().err
    assert hf_logging.is_progress_bar_enabled()
    list(hf_logging.tqdm(range(3), desc="Loading weights"))
    assert "Loading weights" in capsys.readouterr().err   # the check above can fail: bars do show otherwise


def test_the_notebook_extra_installs_ipywidgets_pinned_by_the_lock():
    extras = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert any(d.startswith("ipywidgets") for d in extras["notebook"])  # tqdm.auto's widgets in Jupyter
    lock = (REPO / "requirements" / "lock.txt").read_text()
    for pkg in ("ipywidgets", "widgetsnbextension", "jupyterlab-widgets"):
        assert re.search(rf"^{pkg}==\S+$", lock, re.M), pkg


def test_segment_and_distill_take_quiet_too(tmp_path, console, monkeypatch):
    """--quiet is one shared option: segment draws no bar with it; distill hands it to the stages DVC runs
    (GEODISTILL_QUIET in their environment), and not without it."""
    import cv2
    import numpy as np
    from click.testing import CliRunner

    from pipeline.runtime.progress import QUIET_ENV
    from pipeline.orchestration.standalone import _env
    from pipeline.cli.main import main
    from tests.builders.deploy import make_checkpoint

    ckpt = make_checkpoint(tmp_path / "ckpt")
    (tmp_path / "in").mkdir()
    cv2.imwrite(str(tmp_path / "in" / "a.png"), np.full((20, 24, 3), 90, np.uint8))

    def segment(out, *extra):
        return CliRunner().invoke(main, ["segment", "--device", "cpu", "--checkpoint", str(ckpt), "--input",
                                         str(tmp_path / "in"), "--output", str(tmp_path / out), "--resolution", "32",
                                         "--tau", "0.5", *extra])

    loud, quiet = segment("o1"), segment("o2", "--quiet")
    assert loud.exit_code == quiet.exit_code == 0, loud.output + quiet.output
    assert "%|" in loud.stderr and "segment: wrote 1 mask(s)" in loud.stderr, loud.stderr
    assert "%|" not in quiet.stderr and "segment: wrote 1 mask(s)" in quiet.stderr, quiet.stderr
    # -q: the summary (and warnings, errors) only -- not the engine and timing lines the default prints
    assert "segment: engine torch" in loud.stderr and "segment: timing:" in loud.stderr, loud.stderr
    assert [ln for ln in quiet.stderr.splitlines() if ln.strip()] == [
        ln.replace("o1", "o2") for ln in loud.stderr.splitlines() if ln.startswith("segment: wrote")], quiet.stderr
    monkeypatch.delenv(QUIET_ENV, raising=False)
    assert QUIET_ENV not in _env("cpu")
    with quiet_bars():
        assert _env("cpu")[QUIET_ENV] == "1"
    for command in ("label", "distill", "segment"):
        assert "--quiet" in CliRunner().invoke(main, [command, "--help"]).output
