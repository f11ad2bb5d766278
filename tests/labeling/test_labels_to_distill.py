"""``geodistill distill IMAGES --labels LABEL_DIR`` / ``pipeline.distill(..., labels=...)``: a ``label``
output folder, checked against the checksums label.json records, feeds distill without running the
teacher again -- the project takes label's teacher, resolution, vote and gate and reads label's teacher
cache.  With the tests' tiny random SAM 3 at 32 px on 4 images; the project's stages run in-process."""

from __future__ import annotations

import json
import logging
import shlex
import shutil
from pathlib import Path

import pytest
import yaml
from click.testing import CliRunner

from pipeline.runtime.errors import InputError
from pipeline.geometry import NO_FOREGROUND
from pipeline.teachers.sam3 import Sam3Teacher
from tests.builders.teacher import cache_files, make_image_folder

#: label's settings: 32 px, and a score threshold no query passes -- so the teacher finds no spacecraft,
#: label warns and distill's geometry stage stops with the same words (the errors in the user's terms)
LABEL_SETS = ("data.resolution=32", "data.contact_sheet_images=2", "teacher.score_threshold=1.0")
WORDS = NO_FOREGROUND  # the words label's summary and distill's error share, with the two likely causes
CLI_SET, API_SET = "--set teacher.score_threshold=…", "overrides=['teacher.score_threshold=…']"


def cli(*args):
    from pipeline.cli.main import main

    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture()
def predict_calls(monkeypatch):
    """The number of images the SAM 3 teacher was asked about (``Sam3Teacher.predict`` wrapped)."""
    calls = []
    original = Sam3Teacher.predict

    def counting(self, batch, prompts):
        calls.append(len(batch))
        return original(self, batch, prompts)

    monkeypatch.setattr(Sam3Teacher, "predict", counting)
    return calls


@pytest.fixture(scope="module")
def labelled(tmp_path_factory, tiny_sam3):
    """(images, label folder, label's warnings) of one ``geodistill label`` run."""
    root = tmp_path_factory.mktemp("l2d")
    images, _ = make_image_folder(root / "data", n=4, masks=False)
    warned = Warnings(level=logging.WARNING)
    logging.getLogger("pipeline.labeling.run").addHandler(warned)
    try:
        res = cli("label", images, "--checkpoint", tiny_sam3, "--out", root / "labels", "--format", "png",
                  "--device", "cpu", *[a for kv in LABEL_SETS for a in ("--set", kv)])
    finally:
        logging.getLogger("pipeline.labeling.run").removeHandler(warned)
    assert res.exit_code == 0, res.output[-3000:]  # every mask empty is a result, not an error: exit 0
    assert f"label: all 4 masks are empty. {WORDS.format(CLI_SET)}" in res.output.splitlines(), res.output
    return images, root / "labels", warned.lines


class Warnings(logging.Handler):
    """The messages logged to it."""

    def __init__(self, level):
        super().__init__(level)
        self.lines: list[str] = []

    def emit(self, record):
        self.lines.append(record.getMessage())


def run_stage(project: Path, name: str, monkeypatch):
    """Stage ``name`` of the distill project as its dvc.yaml command says, in this process."""
    from pipeline.cli.main import main

    cmd = yaml.safe_load((project / "dvc.yaml").read_text())["stages"][name]["cmd"]
    argv = shlex.split(cmd)
    assert argv[:3] == ["python", "-m", f"stages.{name}"], cmd
    monkeypatch.chdir(project)
    monkeypatch.setenv("GEODISTILL_QUIET", "1")  # no progress bars: the output is the stage's lines alone
    return CliRunner().invoke(main, [name, *argv[3:], "--device", "cpu"])


def test_distill_from_labels_runs_the_teacher_zero_times(labelled, tiny_sam3, tmp_path, monkeypatch, predict_calls):
    images, labels, label_warnings = labelled
    record = json.loads((labels / "label.json").read_text())
    cache = Path(record["teacher"]["cache_dir"])
    assert cache.is_absolute() and cache.is_relative_to(labels.resolve())
    entries = {p: p.stat().st_mtime_ns for p in cache_files(cache)}
    assert len(entries) == 4 * 6 and record["teacher_answers_computed"] == 4 * 6

    # no --checkpoint: the teacher is label's; nothing else set, so label's values are taken
    project = tmp_path / "run"
    res = cli("distill", images, "--labels", labels, "--out", project, "--no-run")
    assert res.exit_code == 0, res.output
    params = yaml.safe_load((project / "params.yaml").read_text())
    assert params["teacher"]["cache_dir"] == str(cache)
    assert params["teacher"]["checkpoint"] == str(Path(tiny_sam3).resolve()) and params["teacher"]["backend"] == "sam3"
    assert params["teacher"]["score_threshold"] == 1.0 and params["data"]["resolution"] == 32
    assert params["teacher"]["vflip_base_prompt"] is False  # distill's own run keys stay distill's
    assert json.loads((project / "distill.json").read_text())["labels"] == str(labels.resolve())

    for stage in ("prepare", "teacher"):
        res = run_stage(project, stage, monkeypatch)
        assert res.exit_code == 0, res.output[-3000:]
    assert predict_calls == []  # the teacher ran zero times: every answer came from label's cache
    assert {p: p.stat().st_mtime_ns for p in cache_files(cache)} == entries
    assert not (project / ".cache" / "teacher").exists()

    # the teacher found nothing: label warned, and distill's geometry stage stops, with the same words,
    # in the command line's terms here and in the Python API's through distill (run_project: from_line)
    assert label_warnings == [f"label: {WORDS.format(CLI_SET)} (every gate g is 0)"]
    assert run_stage(project, "consensus", monkeypatch).exit_code == 0
    res = run_stage(project, "geometry", monkeypatch)
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert res.exit_code == 2 and len(lines) == 1, res.output
    assert lines[0] == "geodistill geometry: error: " + WORDS.format(CLI_SET)
    api = str(InputError.from_line(lines[0].split(": error: ", 1)[1]))
    assert api == WORDS.format(API_SET)
    assert "--" not in api and ".parquet" not in api and "eq:" not in api


def test_api_distill_from_labels_writes_the_same_project(labelled, tmp_path):
    import pipeline

    images, labels, _ = labelled
    out = pipeline.distill(images, out=tmp_path / "run", labels=labels, run=False)
    params = yaml.safe_load((tmp_path / "run" / "params.yaml").read_text())
    assert out["deploy"].parent.parent == tmp_path / "run"
    assert params["teacher"]["cache_dir"].startswith(str(labels.resolve()))
    assert params["data"]["resolution"] == 32 and params["teacher"]["backend"] == "sam3"
    # an option label's folder contradicts is refused, by its keyword here
    with pytest.raises(InputError) as err:
        pipeline.distill(images, out=tmp_path / "o", labels=labels, run=False, overrides=["data.resolution=64"])
    assert str(err.value).startswith(f"labels={str(labels)!r}: label made these pseudo-labels with "
                                     "data.resolution=32, not 64")


def _copy(labels: Path, dst: Path) -> Path:
    shutil.copytree(labels, dst, symlinks=True, ignore=shutil.ignore_patterns(".cache"))
    return dst


@pytest.mark.parametrize("case, needle", [
    ("edited", "masks/img01.png changed after label wrote it; distill trains only on an unmodified label folder "
               "-- corrected masks enter only through `geodistill review import`"),
    ("missing", "masks/img02.png is missing, the folder is incomplete"),
    ("unfinished", "that label run did not finish"),
    ("other_images", "these are the labels of"),
    ("added_image", "image 'new' was added to INPUT"),
    ("conflict", "label made these pseudo-labels with data.resolution=32, not 64"),
    ("not_label", "not an output folder of label"),
])
def test_a_label_folder_not_as_label_wrote_it_is_one_line_exit_2(labelled, tmp_path, case, needle):
    images, labels, _ = labelled
    lab = _copy(labels, tmp_path / "lab")
    args = [images, "--labels", lab, "--out", tmp_path / "run", "--no-run"]
    if case == "edited":
        (lab / "masks" / "img01.png").write_bytes((lab / "masks" / "img03.png").read_bytes() + b"\0")
    elif case == "missing":
        (lab / "masks" / "img02.png").unlink()
    elif case == "unfinished":
        rec = json.loads((lab / "label.json").read_text())
        (lab / "label.json").write_text(json.dumps({**rec, "complete": False}))
    elif case == "other_images":
        other = _copy(images, tmp_path / "other")
        args[0] = other
    elif case == "added_image":
        other = _copy(images, tmp_path / "imgs")
        rec = json.loads((lab / "label.json").read_text())
        (lab / "label.json").write_text(json.dumps({**rec, "input": str(other.resolve())}))
        (other / "new.png").write_bytes((other / "img00.png").read_bytes())
        args[0] = other
    elif case == "conflict":
        args += ["--set", "data.resolution=64"]
    elif case == "not_label":
        (lab / "label.json").unlink()
    res = cli("distill", *args)
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert res.exit_code == 2 and len(lines) == 1, res.output
    assert lines[0].startswith(f"geodistill distill: error: --labels {lab}") and needle in lines[0], lines[0]
    assert not (tmp_path / "run").exists()
