"""``geodistill label``: teacher (cached), vote and gate on a folder of images, exported as PNG, COCO RLE
(read back with pycocotools) and YOLO segmentation labels, with the simulated backend (a SIMULATOR
reading the folder's masks) and the tests' tiny random SAM 3."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from pipeline.labeling.formats import rle_encode, yolo_lines, yolo_polygons
from tests.builders.teacher import FAST, cli, make_image_folder

# pycocotools' own NumPy-2 deprecation notice (its __array__), not ours
pytestmark = pytest.mark.filterwarnings("ignore:__array__ implementation:DeprecationWarning")


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return make_image_folder(tmp_path_factory.mktemp("data"))


def parse_yolo(path: Path, w: int, h: int) -> np.ndarray:
    """Rasterise a YOLO segmentation label file (Ultralytics' polygon2mask: fillPoly of the points)."""
    mask = np.zeros((h, w), np.uint8)
    for line in path.read_text().splitlines():
        parts = line.split()
        assert parts[0] == "0" and len(parts) % 2 == 1 and len(parts) >= 7, line
        xy = np.array(parts[1:], float).reshape(-1, 2)
        assert ((xy >= 0) & (xy <= 1)).all()
        cv2.fillPoly(mask, [np.round(xy * [w, h]).astype(np.int32)], 1)
    return mask.astype(bool)


def iou(a, b) -> float:
    union = np.logical_or(a, b).sum()
    return 1.0 if union == 0 else float(np.logical_and(a, b).sum() / union)


# --------------------------------------------------------------------------------------------------
# formats (pure)
# --------------------------------------------------------------------------------------------------
def test_rle_decodes_to_the_mask():
    """rle_encode (pycocotools' encoder on the Fortran-order mask) gives JSON-ready RLE that pycocotools
    decodes back to the same mask, with the right size and area -- empty and full masks included."""
    import pycocotools.mask as mu

    rng = np.random.default_rng(1)
    for t in range(200):
        h, w = (int(v) for v in rng.integers(1, 50, 2))
        m = rng.random((h, w)) < rng.random()
        m[:] = False if t % 7 == 0 else m
        m[:] = True if t % 11 == 0 else m
        rle = rle_encode(m)
        assert isinstance(rle["counts"], str) and rle["size"] == [h, w]
        json.dumps(rle)
        back = {"size": rle["size"], "counts": rle["counts"]}
        assert (mu.decode(back) == m).all() and mu.area(back) == m.sum()


def test_yolo_polygons_give_the_regions_back():
    m = np.zeros((40, 60), bool)
    cv2.circle(m.view(np.uint8), (15, 20), 9, 1, -1)
    m[5:12, 35:55] = True          # a second object: a second line
    m[30, 50] = True               # a 1-px speck: no polygon (fewer than 3 points)
    lines = yolo_lines(m)
    assert len(lines) == 2 and len(yolo_polygons(np.zeros((5, 5), bool))) == 0
    for line in lines:
        assert re.fullmatch(r"0( \d\.\d{6})+", line) and len(line.split()) % 2 == 1
    back = np.zeros_like(m, np.uint8)
    for poly in yolo_polygons(m):
        cv2.fillPoly(back, [np.round(poly * [60, 40]).astype(np.int32)], 1)
    speckless = m.copy()
    speckless[30, 50] = False
    assert (back.astype(bool) == speckless).all()  # exact for simply connected regions


# --------------------------------------------------------------------------------------------------
# the command
# --------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def simulated_run(folder, tmp_path_factory):
    images, masks = folder
    out = tmp_path_factory.mktemp("label") / "sim"
    res = cli("label", images, "--out", out, "--backend", "simulated", "--reference-masks", masks, *FAST)
    assert res.exit_code == 0, res.output
    return out


def test_label_writes_png_coco_yolo_table_and_sheet(folder, simulated_run):
    from pycocotools.coco import COCO

    images, masks = folder
    out = simulated_run
    files = sorted(images.glob("*.png"))
    table = pd.read_parquet(out / "labels.parquet")
    assert len(table) == 20 and table["image_id"].tolist() == [f.stem for f in files]
    for col in ("c", "v", "a", "g_conf", "g_valid", "g_area", "g"):
        assert table[col].between(0, 1).all(), col
    assert (table["g"] > 0).any() and table["simulator"].all()
    assert pd.read_csv(out / "labels.csv")["g"].round(4).tolist() == table["g"].round(4).tolist()

    coco = COCO(str(out / "coco.json"))
    assert coco.dataset["info"]["simulator"] is True and "SIMULATOR" in coco.dataset["info"]["description"]
    by_name = {im["file_name"]: im for im in coco.dataset["images"]}
    agree = []
    for f in files:
        png = cv2.imread(str(out / "masks" / f"{f.stem}.png"), cv2.IMREAD_UNCHANGED)
        h, w = cv2.imread(str(f), cv2.IMREAD_UNCHANGED).shape[:2]
        assert png.shape == (h, w) and set(np.unique(png)) <= {0, 255}  # the ORIGINAL size
        mask = png > 0
        im = by_name[f.name]
        assert (im["width"], im["height"]) == (w, h)
        anns = coco.loadAnns(coco.getAnnIds(imgIds=im["id"]))
        assert len(anns) == int(mask.any())
        for ann in anns:
            assert ann["area"] == int(mask.sum()) and (coco.annToMask(ann).astype(bool) == mask).all()
            x, y, bw, bh = ann["bbox"]
            ys, xs = np.nonzero(mask)
            assert (x, y, bw, bh) == (xs.min(), ys.min(), xs.max() - xs.min() + 1, ys.max() - ys.min() + 1)
        assert table.set_index("image_id").at[f.stem, "mask_pixels"] == mask.sum()
        label = out / "yolo" / "labels" / f"{f.stem}.txt"
        assert (out / "yolo" / "images" / f.name).resolve() == f.resolve()
        if mask.sum() > 40:
            agree.append(iou(parse_yolo(label, w, h), mask))
    assert agree and min(agree) > 0.8, agree
    assert "names:" in (out / "yolo" / "data.yaml").read_text()
    sheet = cv2.imread(str(out / "contact_sheet.png"))
    assert sheet is not None and sheet.shape[0] > 100
    record = json.loads((out / "label.json").read_text())
    assert record["simulator"] is True and record["images"] == 20 and record["teacher_backend"] == "simulated"


def test_label_masks_follow_the_vote_and_gate(simulated_run):
    """The table's numbers are eq:foreground-agreement .. eq:reliability-gate of the voted masks."""
    from pipeline.geometry import gate_factors
    from pipeline.params import PAPER

    t = pd.read_parquet(simulated_run / "labels.parquet")
    geo = PAPER.geometry
    a0 = float(np.median(t.loc[t["a"] > 0, "a"]))
    assert np.allclose(t["a0"], a0) and np.allclose(t["v"], t["n_valid"] / 6)
    gf = gate_factors(t["c"], t["v"], t["a"], a0, conf_offset=geo.conf_offset, valid_offset=geo.valid_offset,
                      area_temperature=geo.area_temperature, area_floor=geo.area_floor, eps=geo.eps)
    assert np.allclose(gf.g, t["g"])
    assert ((t["mask_pixels"] == 0) == (t["a"] == 0)).all()


def test_label_with_tiny_sam3_resumes_from_the_cache(folder, tiny_sam3, tmp_path):
    images, _ = folder
    out = tmp_path / "sam3"
    args = ("label", images, "--out", out, "--checkpoint", tiny_sam3, "--format", "coco,png",
            "--set", "teacher.score_threshold=0", *FAST)
    first = cli(*args)
    assert first.exit_code == 0, first.output
    rec1 = json.loads((out / "label.json").read_text())
    assert rec1["teacher_backend"] == "sam3" and not rec1["simulator"] and rec1["teacher_answers_computed"] == 120
    assert not list((out / "yolo").glob("labels/*"))  # yolo not requested
    coco1 = (out / "coco.json").read_bytes()
    second = cli(*args)
    assert second.exit_code == 0, second.output
    rec2 = json.loads((out / "label.json").read_text())
    assert rec2["teacher_answers_computed"] == 0 and rec2["teacher_cache_hits"] == 120
    assert (out / "coco.json").read_bytes() == coco1
    t = pd.read_parquet(out / "labels.parquet")
    assert len(t) == 20 and not t["simulator"].any() and (t["n_valid"] > 0).any()


@pytest.mark.parametrize("case, message", [
    ("missing", "input folder not found"),
    ("empty", "no images"),
    ("format", "--format"),
    ("no_teacher", "--checkpoint SAM3_DIR is required"),
    ("no_reference", "SIMULATOR that reads reference masks"),
    ("collision", "same label name"),
])
def test_label_errors_are_one_line_exit_2(tmp_path, folder, case, message):
    images, masks = folder
    empty = tmp_path / "empty"
    empty.mkdir()
    clash = tmp_path / "clash"
    clash.mkdir()
    cv2.imwrite(str(clash / "a.png"), np.zeros((8, 8), np.uint8))
    cv2.imwrite(str(clash / "a.bmp"), np.zeros((8, 8), np.uint8))
    sim = ["--backend", "simulated", "--reference-masks", masks]
    args = {"missing": [tmp_path / "nope", "--out", tmp_path / "o", *sim],
            "empty": [empty, "--out", tmp_path / "o", *sim],
            "format": [images, "--out", tmp_path / "o", "--format", "png,voc", *sim],
            "no_teacher": [images, "--out", tmp_path / "o"],
            "no_reference": [images, "--out", tmp_path / "o", "--backend", "simulated"],
            "collision": [clash, "--out", tmp_path / "o", "--backend", "simulated", "--reference-masks", clash]}[case]
    res = CliRunner().invoke(__import__("pipeline.cli.main", fromlist=["main"]).main, ["label", *map(str, args)])
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("geodistill label: error:") and message in lines[0], res.output
    assert not (tmp_path / "o").exists()
