"""Errors and warnings in the user's terms: no internal file, equation label or command-line flag in what
a Python caller reads; the params override named as ``--set key=value`` on the command line and
``overrides=["key=value"]`` in the Python API (pipeline.errors.Option), including for a stage's line
read back from a subprocess (``InputError.from_line``, what distill's ``dvc repro`` does)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from pipeline.errors import API, CLI, SET, InputError, caller, calling
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
        _, a0, gf = folder_gates(zeros, np.zeros(3, np.int64), zeros, geo)
        with calling(CLI):
            assert caller() == CLI
            folder_gates(zeros, np.zeros(3, np.int64), zeros, geo)
    assert caller() == API and a0 == 0.0 and not gf.g.any()
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
