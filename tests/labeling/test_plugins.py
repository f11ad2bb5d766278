"""A plug-in is one module and one entry-point line in its own package: here a package written onto a path
(the module and its ``.dist-info`` with ``entry_points.txt``, no network, no install) gives a teacher and a
label format that ``geodistill label`` uses through the CLI and ``python -m stages.teacher`` uses in a fresh
process, its settings through ``teacher.options``; a plug-in reusing a built-in name, or failing to import,
is one line."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from click.testing import CliRunner

from pipeline.artifacts.store import open_artifact
from pipeline.cli.label import main as label_main
from pipeline.labeling.formats import LABEL_FORMATS, mask_bbox, unregister_format
from pipeline.orchestration.dag import project_dvc_yaml, render_params_yaml
from pipeline.params import load_yaml
from pipeline.teacher_table import TEACHER_TABLE, unregister_teacher
from tests.builders.teacher import FAST, REPO, build_artifacts, make_image_folder

TEACHER, FORMAT, MODULE, DIST = "bright_plug", "boxes_plug", "geodistill_plug_test", "geodistill-plug-test"

PLUGIN = f'''
"""A test plug-in: a teacher whose answer is the pixels brighter than ``teacher.options.min_grey``, and a
format writing each voted mask's box."""
import numpy as np
from pydantic import BaseModel, ConfigDict

from pipeline.labeling.formats import LabelFormat, mask_bbox
from pipeline.teacher_table import TeacherSpec
from pipeline.teachers.base import RegisteredTeacher


class Options(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)
    min_grey: int = 100


class Bright(RegisteredTeacher):
    backend = "{TEACHER}"

    def __init__(self, min_grey):
        self.min_grey = min_grey

    @classmethod
    def from_params(cls, cfg, resolution, device="auto"):
        return cls(cfg["options"]["min_grey"])

    def fingerprint(self):
        return {{"backend": self.backend, "min_grey": self.min_grey}}

    def predict(self, batch, prompts):
        if any(item.reference is not None or item.extras for item in batch):
            raise AssertionError("a teacher not marked simulator was given the reference")
        bright = np.stack([item.image.mean(axis=2) > self.min_grey for item in batch])
        return np.repeat(bright[:, None], len(prompts), axis=1), np.full((len(batch), len(prompts)), 0.9, np.float32)


def _box(job, row, mask):
    (job.out / "{FORMAT}").mkdir(exist_ok=True)
    (job.out / "{FORMAT}" / f"{{job.ids[row]}}.txt").write_text(" ".join(f"{{v:g}}" for v in mask_bbox(mask)))


TEACHER = TeacherSpec("{MODULE}:Bright", "a test plug-in teacher", options="{MODULE}:Options")
FORMAT = LabelFormat("{FORMAT}", lambda ids, rels: [f"{FORMAT}/{{i}}.txt" for i in ids], _box,
                     image_folders=("{FORMAT}/",), default=False)
'''


def write_package(root, name: str, entry_points: str, module: str | None = None):
    """``root`` holding distribution ``name`` 1.2.3 (its ``.dist-info``) and, if given, :data:`MODULE`."""
    info = root / f"{name.replace('-', '_')}-1.2.3.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 1.2.3\n")
    (info / "entry_points.txt").write_text(textwrap.dedent(entry_points))
    if module is not None:
        (root / f"{MODULE}.py").write_text(module)
    return root


@pytest.fixture
def plugin_path(tmp_path, monkeypatch):
    """The test package on ``sys.path``; what it registered is removed after."""
    root = write_package(tmp_path / "site", DIST, f"""\
        [geodistill.teachers]
        {TEACHER} = {MODULE}:TEACHER
        [geodistill.label_formats]
        {FORMAT} = {MODULE}:FORMAT
        """, PLUGIN)
    monkeypatch.syspath_prepend(str(root))
    try:
        yield root
    finally:
        unregister_teacher(TEACHER)
        unregister_format(FORMAT)
        sys.modules.pop(MODULE, None)
    assert TEACHER not in TEACHER_TABLE and FORMAT not in LABEL_FORMATS


@pytest.mark.filterwarnings("ignore:__array__ implementation:DeprecationWarning")  # pycocotools' own
def test_label_uses_a_plugin_teacher_and_format_through_the_cli(tmp_path, plugin_path):
    assert TEACHER not in TEACHER_TABLE and FORMAT not in LABEL_FORMATS  # nothing loaded before it is named
    images, _ = make_image_folder(tmp_path / "data", n=3, masks=False)
    out = tmp_path / "labels"
    res = CliRunner().invoke(label_main, [str(images), "--out", str(out), "--backend", TEACHER, "--format",
                                          f"{FORMAT},png", *FAST])  # teacher.options: the plug-in's defaults
    assert res.exit_code == 0, res.output
    assert TEACHER_TABLE[TEACHER].distribution == f"{DIST} 1.2.3" and FORMAT in LABEL_FORMATS
    for png in sorted((out / "masks").glob("*.png")):  # the plug-in format's boxes are those of label's masks
        import cv2

        mask = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE) > 0
        assert mask.any() and (out / FORMAT / f"{png.stem}.txt").read_text().split() == \
            [f"{v:g}" for v in mask_bbox(mask)]
    assert len(list((out / FORMAT).glob("*.txt"))) == 3 and "SIMULATOR" not in res.output
    for sets, error in ((["teacher.backend=" + TEACHER, "teacher.options.speed=2"], "speed: unknown key"),
                        (["teacher.options.min_grey=90"], "teacher.options: backend simulated takes none")):
        bad = CliRunner().invoke(label_main, [str(images), "--out", str(tmp_path / "x"), *FAST,
                                              *(a for s in sets for a in ("--set", s))])
        assert bad.exit_code == 2 and bad.output.strip().count("\n") == 0 and error in bad.output, bad.output


def test_the_teacher_stage_runs_a_plugin_in_a_fresh_process(tmp_path, plugin_path):
    paths = build_artifacts(tmp_path, n=4)
    params = tmp_path / "params.yaml"
    params.write_text(render_params_yaml("demo", {"teacher": {"backend": TEACHER, "options": {"min_grey": 120},
                                                              "cache_dir": str(tmp_path / "cache")}}))
    assert "options: {min_grey: 120}" in params.read_text()
    assert "teacher.options" in project_dvc_yaml(load_yaml(params.read_text()))  # DVC tracks the set options
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), str(plugin_path)])}
    args = [f"--{k}={paths[k]}" for k in ("manifest", "images", "reference", "out", "scores")]
    run = subprocess.run([sys.executable, "-m", "stages.teacher", "--params", str(params), "--device", "cpu", *args],
                         cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    teacher, images = open_artifact(paths["out"], "teacher"), open_artifact(paths["images"], "images")
    assert teacher.attrs["backend"] == TEACHER and teacher.attrs["simulator"] is False
    assert teacher.attrs["teacher"] == {"backend": TEACHER, "min_grey": 120, "distribution": f"{DIST} 1.2.3"}
    bright = images.numpy("image").mean(axis=3) > 120
    masks = teacher.numpy("masks")  # every row ran (teacher.splits: all)
    assert bright.any() and masks.shape[0] == 4
    np.testing.assert_array_equal(masks, np.repeat(bright[:, None], masks.shape[1], axis=1))


@pytest.mark.parametrize("entry, line", [
    ("sam3 = nowhere:TEACHER", "plug-in 'sam3' of geodistill-clash 1.2.3 (geodistill.teachers) reuses a built-in "
                               "name: refused"),
    ("broken = geodistill_missing_module:TEACHER", "plug-in 'broken' of geodistill-clash 1.2.3 "
                                                   "(geodistill.teachers): geodistill_missing_module:TEACHER failed "
                                                   "to import: ModuleNotFoundError"),
])
def test_a_plugin_reusing_a_built_in_name_or_failing_to_import_is_one_line(tmp_path, monkeypatch, entry, line):
    monkeypatch.syspath_prepend(str(write_package(tmp_path / "site", "geodistill-clash", f"""\
        [geodistill.teachers]
        {entry}
        """)))
    images, _ = make_image_folder(tmp_path / "data", n=1, masks=False)
    res = CliRunner().invoke(label_main, [str(images), "--out", str(tmp_path / "labels"), "--backend", "broken",
                                          *FAST])
    assert res.exit_code == 2 and line in res.output and res.output.strip().count("\n") == 0, res.output
    assert "sam3" in TEACHER_TABLE and TEACHER_TABLE["sam3"].distribution is None  # the built-in stays


def test_a_built_in_teachers_fingerprint_is_what_it_was():
    """Caches made before plug-ins stay valid: the SIMULATOR's fingerprint at 32x32 as main 3056231 computed it."""
    from pipeline.params import validate_section
    from pipeline.teachers import make_teacher, teacher_fingerprint

    teacher = make_teacher(validate_section("teacher", {}), (32, 32), "cpu")
    assert teacher_fingerprint(teacher) == "5c098ff804e6f8d522b03e5722221eb08ed8d2ef5cdf8c03707a232d35258348"
