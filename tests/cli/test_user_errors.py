"""Errors and warnings in the user's terms: no internal file, equation label or command-line flag in what
a Python caller reads; the params override named as ``--set key=value`` on the command line and
``overrides=["key=value"]`` in the Python API (pipeline.runtime.errors.Option), including for a stage's line
read back from a subprocess (``InputError.from_line``, what distill's ``dvc repro`` does)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from pipeline.runtime.errors import API, CLI, SET, InputError, caller, calling
from pipeline.geometry import NO_FOREGROUND, NoForeground, median_area
from pipeline.labeling.run import folder_gates
from pipeline.params import PAPER

WORDS = NO_FOREGROUND


def test_no_foreground_names_the_fix_in_each_callers_terms():
    with pytest.raises(NoForeground) as err:
        median_area(np.zeros(3), np.array([True, True, False]))
    e = err.value
    assert isinstance(e, InputError)
    assert e.render(CLI) == WORDS.format("--set teacher.score_threshold=…")
    assert str(e) == e.render(API) == WORDS.format("overrides=['teacher.score_threshold=…']")
    for internal in ("--", "median_area", "a0", "eq:", ".parquet", "pseudo-mask"):
        assert internal not in str(e), internal


def test_a_many_option_spells_one_flag_per_item_and_a_list_keyword():
    e = InputError("try {}", SET(["a.b=1", "c=x y"]))
    assert e.render(CLI) == "try --set a.b=1 --set c=x y"
    assert str(e) == "try overrides=['a.b=1', 'c=x y']"
    assert InputError("{} items", SET).render(CLI) == "--set items" and str(InputError("{} items", SET)) == "overrides= items"


def test_a_stage_line_read_back_names_the_override_by_keyword():
    line = NoForeground().render(CLI)
    back = InputError.from_line(line)
    assert back.render(CLI) == line
    assert str(back) == str(NoForeground())
    # other flags in the same line keep today's reading; a --set without key=value is unbound
    mixed = InputError.from_line("--skip-bad or --set teacher.seed=3, not --set alone; --out run/")
    assert str(mixed) == "skip_bad=True or overrides=['teacher.seed=3'], not overrides= alone; out= run/"
    assert mixed.render(CLI) == "--skip-bad or --set teacher.seed=3, not --set alone; --out run/"


def test_label_warns_with_the_same_words_for_its_caller(caplog):
    zeros, geo = np.zeros(3), PAPER.geometry.model_dump()
    assert caller() == API
    with caplog.at_level(logging.WARNING, logger="pipeline.labeling.run"):
        gates = folder_gates(zeros, np.zeros(3, np.int64), zeros, geo)
        with calling(CLI):
            assert caller() == CLI
            folder_gates(zeros, np.zeros(3, np.int64), zeros, geo)
    assert caller() == API and gates.missing and gates.a0 == 0.0 and not gates.factors.g.any()
    api, cli = (r.getMessage() for r in caplog.records)
    assert api == "label: " + WORDS.format("overrides=['teacher.score_threshold=…']") + " (every gate g is 0)"
    assert cli == "label: " + WORDS.format("--set teacher.score_threshold=…") + " (every gate g is 0)"


def test_api_errors_of_distill_from_labels_name_keywords(tmp_path):
    import pipeline

    images = tmp_path / "images"
    images.mkdir()
    with pytest.raises(InputError) as err:
        pipeline.distill(images, out=tmp_path / "run", labels=tmp_path / "nope", run=False)
    assert str(err.value) == f"labels={str(tmp_path / 'nope')!r}: folder not found (no label.json of label there)"
    assert err.value.render(CLI).startswith(f"--labels {tmp_path / 'nope'}: folder not found")
    assert not (tmp_path / "run").exists()


def test_a_bad_checkpoint_is_named_as_the_user_gave_it(tmp_path):
    """--checkpoint on the command line (not the params key teacher.checkpoint=), checkpoint= in Python."""
    import pipeline
    from click.testing import CliRunner
    from pipeline.cli.main import main
    from pipeline.deploy.image_files import segment_images
    from tests.builders.teacher import make_image_folder

    images, _ = make_image_folder(tmp_path / "data", n=2, masks=False)
    nope, empty = tmp_path / "nope", tmp_path / "empty"
    empty.mkdir()
    for ck, why in ((nope, "directory not found"), (empty, "not a SAM 3 checkpoint (no config.json)")):
        for cmd in ("label", "distill"):
            res = CliRunner().invoke(main, [cmd, str(images), "--out", str(tmp_path / cmd), "--checkpoint", str(ck)])
            lines = [ln for ln in res.output.splitlines() if ln.strip()]
            assert res.exit_code == 2 and lines == [f"geodistill {cmd}: error: --checkpoint {ck}: {why}"
                                                    + (" (a local SAM 3 checkpoint saved with save_pretrained; "
                                                       "nothing is downloaded)" if ck == nope else "")], res.output
        for call in (pipeline.label, pipeline.distill):
            with pytest.raises(InputError) as err:
                call(images, out=tmp_path / "api", checkpoint=ck)
            assert str(err.value).startswith(f"checkpoint={str(ck)!r}: {why}") and "--" not in str(err.value)
    res = CliRunner().invoke(main, ["segment", "--checkpoint", str(nope), "--input", str(images), "--output",
                                    str(tmp_path / "m")])
    assert res.exit_code == 2 and f"error: --checkpoint {nope}: not found" in res.output, res.output
    with pytest.raises(InputError) as err:
        segment_images(nope, images, tmp_path / "m")
    assert str(err.value) == f"checkpoint={str(nope)!r}: not found"
    assert not (tmp_path / "label").exists() and not (tmp_path / "distill").exists() and not (tmp_path / "api").exists()
