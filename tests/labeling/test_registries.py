"""An extension is one module: this file alone registers a label format and a teacher backend, and
``pipeline.label`` plans, writes, records and summarises with both; the registrations are removed after."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pandas as pd
import pytest

import pipeline
from pipeline.catalog import OUTPUT_FILES, OutputFile
from pipeline.labeling.formats import LABEL_FORMATS, LabelFormat, mask_bbox, register_format, unregister_format
from pipeline.labeling.run import parse_formats
from pipeline.params import validate_section
from pipeline.runtime.errors import InputError
from pipeline.teacher_table import TEACHER_TABLE, TeacherSpec, register_teacher, unregister_teacher
from pipeline.teachers.base import RegisteredTeacher
from tests.builders.teacher import make_image_folder

TEACHER, FORMAT, BOXES = "bright_test", "boxes_test", "boxes_test"


class BrightTeacher(RegisteredTeacher):
    """Every prompt's answer: the pixels brighter than 100 (grey mean), score 0.9; the last prompt misses."""

    backend = TEACHER

    @classmethod
    def from_params(cls, cfg, resolution, device="auto"):
        return cls()

    def fingerprint(self) -> dict:
        return {"backend": TEACHER, "version": 1}

    def predict(self, batch, prompts):
        bright = np.stack([item.image.mean(axis=2) > 100 for item in batch])
        masks = np.repeat(bright[:, None], len(prompts), axis=1)
        scores = np.full((len(batch), len(prompts)), 0.9, np.float32)
        scores[:, -1] = 0.0
        return masks, scores


def _box(job, row, mask):
    (job.out / BOXES).mkdir(exist_ok=True)
    (job.out / BOXES / f"{job.ids[row]}.txt").write_text(" ".join(f"{v:g}" for v in mask_bbox(mask)))
    return int(mask.sum())


def _index(job, per_image, table):
    pd.DataFrame({"image_id": table["image_id"], "pixels": per_image, "g": table["g"]}).to_csv(
        job.out / BOXES / "index.csv", index=False)


BOXES_FORMAT = LabelFormat(
    FORMAT, lambda ids, rels: [f"{BOXES}/{i}.txt" for i in ids] + [f"{BOXES}/index.csv"], _box, _index,
    image_folders=(f"{BOXES}/",), outputs=(OutputFile(BOXES, BOXES, __name__, "a test format's boxes"),),
    summary=lambda out, n: f"{FORMAT}: {n} boxes", default=False)


@pytest.fixture
def registered():
    register_teacher(TEACHER, TeacherSpec(BrightTeacher, "a test teacher"))
    register_format(BOXES_FORMAT)
    try:
        yield
    finally:
        unregister_format(FORMAT)
        unregister_teacher(TEACHER)
    assert FORMAT not in LABEL_FORMATS and BOXES not in OUTPUT_FILES["label"] and TEACHER not in TEACHER_TABLE


@pytest.mark.filterwarnings("ignore:__array__ implementation:DeprecationWarning")  # pycocotools' own
def test_label_uses_a_format_and_a_teacher_registered_here(tmp_path, registered):
    from pipeline.cli.label import summary_line

    assert FORMAT in LABEL_FORMATS and OUTPUT_FILES["label"][BOXES].written_by == __name__
    assert FORMAT not in parse_formats() and parse_formats(f"{FORMAT},png") == ("png", FORMAT)
    with pytest.raises(ValueError, match="registered already"):
        register_format(BOXES_FORMAT)
    images, _ = make_image_folder(tmp_path / "data", n=3, masks=False)
    res = pipeline.label(images, out=tmp_path / "labels", backend=TEACHER, formats=[FORMAT, "png"],
                         overrides={"data.resolution": 32}, device="cpu")
    assert res.backend == TEACHER and not res.simulator and res.formats == ("png", FORMAT) and len(res.masks) == 3
    out = tmp_path / "labels"
    index = pd.read_csv(out / BOXES / "index.csv", dtype={"image_id": str})
    for _, row in res.table.iterrows():  # the format's files agree with the built-in PNG masks of the same votes
        png = cv2.imread(str(res.masks[row["image_id"]]), cv2.IMREAD_GRAYSCALE) > 0
        box = [float(v) for v in (out / BOXES / f"{row['image_id']}.txt").read_text().split()]
        assert png.any() and box == mask_bbox(png)
        assert index.set_index("image_id").loc[row["image_id"], "pixels"] == png.sum() == row["mask_pixels"]
    assert np.allclose(index["g"], res.table["g"]) and (res.table["teacher_backend"] == TEACHER).all()
    assert (res.table["n_valid"] == 5).all()  # the teacher's last prompt missed: it is the one that answered
    record = json.loads((out / "label.json").read_text())
    assert {f"{BOXES}/index.csv", f"{BOXES}/{res.table['image_id'][0]}.txt"} <= set(record["checksums"])
    assert record["teacher_backend"] == TEACHER and record["simulator"] is False
    assert summary_line(res).count(f"{FORMAT}: 3 boxes") == 1 and "SIMULATOR" not in summary_line(res)


def test_the_params_accept_a_backend_by_its_row_and_its_required_settings():
    with pytest.raises(InputError, match="expected one of simulated, sam3, imported"):
        validate_section("teacher", {"backend": TEACHER})  # not registered outside the fixture
    with pytest.raises(InputError, match="teacher.imported_dir is required for backend imported"):
        validate_section("teacher", {"backend": "imported"})
