"""The API as documented: required arguments are required in the signature, ``LabelResult`` is a typed
dataclass with mask paths and a one-line repr, ``Segmenter.predict`` takes one image or a list, command
names are spelled alike (old spellings kept as aliases, DVC stage names unchanged), and required options
say so in --help."""

from __future__ import annotations

import dataclasses
import inspect
import typing
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner


def cli(*args):
    from pipeline.cli.main import main

    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.mark.parametrize("name", ["label", "distill"])
def test_out_is_a_required_keyword(name):
    import pipeline

    fn = getattr(pipeline, name)
    sig = inspect.signature(fn)
    params = list(sig.parameters.values())
    assert params[0].name == "input" and params[0].kind is inspect.Parameter.POSITIONAL_OR_KEYWORD
    assert all(p.kind is inspect.Parameter.KEYWORD_ONLY for p in params[1:])
    assert sig.parameters["out"].default is inspect.Parameter.empty
    with pytest.raises(TypeError, match="out"):
        fn("images/")
    with pytest.raises(TypeError):
        fn("images/", "sam3/", "labels/")  # the checkpoint and out are keywords now


def test_label_returns_a_typed_label_result():
    import pipeline
    from pipeline.labeling import LabelResult

    assert typing.get_type_hints(pipeline.label)["return"] is LabelResult
    hints = typing.get_type_hints(LabelResult)
    assert hints["out"] is Path and hints["table"] is pd.DataFrame
    assert dataclasses.is_dataclass(LabelResult)


def test_label_result_masks_and_short_repr(tmp_path):
    from pipeline.labeling import LabelResult

    table = pd.DataFrame({"image_id": ["a", "sub/b"], "c": [0.9, 0.1], "v": [1.0, 0.5], "a": [0.1, 0.2],
                          "g": [0.8, 0.0]})
    res = LabelResult(tmp_path, table, [("x.png", "corrupt")], ("png", "coco"), "sam3")
    assert res.masks == {"a": tmp_path / "masks" / "a.png", "sub/b": tmp_path / "masks" / "sub" / "b.png"}
    text = repr(res)
    assert "\n" not in text and len(text) < 200 and "images=2" in text and "skipped=1" in text
    assert "DataFrame" not in text and "0.9" not in text
    assert LabelResult(tmp_path, table, [], ("coco",), "sam3").masks == {}  # no PNG asked for


def test_label_result_masks_point_at_the_written_pngs(tmp_path):
    """A real (simulated-teacher) label run: every mask path of the result exists."""
    import pipeline
    from tests.builders.teacher import make_image_folder

    images, masks = make_image_folder(tmp_path / "data", n=3)
    res = pipeline.label(images, out=tmp_path / "labels", formats="png", backend="simulated",
                         reference_masks=masks, overrides=["data.resolution=32"], device="cpu")
    assert len(res.masks) == 3 and all(p.is_file() for p in res.masks.values())
    assert repr(res).startswith("LabelResult(out=") and "images=3" in repr(res)


def test_segmenter_predict_takes_one_image_or_a_list(tmp_path):
    import cv2

    from pipeline.deploy.segmenter import Segmenter
    from tests.builders.deploy import make_checkpoint

    ckpt = make_checkpoint(tmp_path / "ckpt")
    seg = Segmenter.from_bundle(ckpt, tau=0.5, resolution=32)
    rng = np.random.default_rng(0)
    paths = []
    for i, (h, w) in enumerate([(40, 50), (30, 30)]):
        paths.append(tmp_path / f"im{i}.png")
        cv2.imwrite(str(paths[-1]), rng.integers(0, 255, (h, w, 3), dtype=np.uint8))
    one = seg.predict(paths[0])
    assert isinstance(one, np.ndarray) and one.shape == (40, 50) and one.dtype == bool
    many = seg.predict([str(p) for p in paths])  # the "unsupported pixel type <U13" of before
    assert isinstance(many, list) and [m.shape for m in many] == [(40, 50), (30, 30)]
    assert np.array_equal(many[0], one)
    arrays = seg.predict((cv2.imread(str(paths[1]))[..., ::-1],))
    assert isinstance(arrays, list) and np.array_equal(arrays[0], many[1])


def test_command_names_use_hyphens_and_old_spellings_still_work():
    from pipeline.orchestration.dag import stage_modules
    from pipeline.cli.main import ALIASES, COMMANDS

    listed = cli("--help").output
    assert "analyze-teacher" in listed and "analyze_teacher" not in listed and "reproduce-check" in listed
    assert all("_" not in name for name in COMMANDS)
    # every DVC stage spelled with "_" keeps that spelling as a hidden alias of its hyphenated command
    assert ALIASES == {s: s.replace("_", "-") for s in stage_modules() if "_" in s}
    assert ALIASES["analyze_teacher"] == "analyze-teacher"
    old, new = cli("analyze_teacher", "--help"), cli("analyze-teacher", "--help")
    assert old.exit_code == new.exit_code == 0 and "--artifacts" in old.output
    assert old.output.replace("analyze_teacher", "analyze-teacher") == new.output
    # the DVC stage keeps its name: dvc.yaml and dvc.lock do not change
    assert "analyze_teacher" in stage_modules()
    assert "\n  analyze_teacher:\n" in Path("dvc.yaml").read_text()


def test_required_options_marked_in_help():
    seg = cli("segment", "--help").output
    for opt in ("--checkpoint", "--input", "--output"):
        line = next(ln for ln in seg.splitlines() if ln.strip().startswith(opt))
        assert "[required]" in line, line
    missing = cli("segment", "--input", "x", "--output", "y")
    assert missing.exit_code == 2 and "Missing option '--checkpoint'" in missing.output


def test_profile_help_lists_every_profile():
    from pipeline.profiles import PROFILES

    text = cli("profile", "--help").output
    assert "distill" in PROFILES and all(name in text for name in PROFILES)
    bad = cli("profile", "nope", "--out", "x.yaml")
    assert bad.exit_code == 2 and "nope" in bad.output and not Path("x.yaml").exists()
