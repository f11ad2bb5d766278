"""``geodistill review export|import``: the disagreement statistic label records, the rankings, the Label
Studio / CVAT / CSV export read back with the formats' own decoders (label-studio-converter's brush RLE,
vendored below as the reference; pycocotools), and the corrections import with its refusals."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

from pipeline.artifacts.store import open_artifact
from pipeline.review.corrections import correction_masks
from pipeline.consensus import agreement_entropy
from pipeline.review.formats import (coco_uncompressed_rle, ls_brush_rgba, ls_rle_decode, ls_rle_encode,
                                     ls_rle_encode_values)
from pipeline.review.ranking import rank
from tests.builders.teacher import FAST, cli, make_image_folder

pytestmark = pytest.mark.filterwarnings("ignore:__array__ implementation:DeprecationWarning")


# --------------------------------------------------------------------------------------------------
# Reference: label-studio-converter's brush RLE, copied from
# https://github.com/HumanSignal/label-studio-converter/blob/master/label_studio_converter/brush.py
# (commit 0098e78193fd164decf2f2a1fd8c89c4f6a3cc52).  Copyright Heartex, Inc. (HumanSignal), licensed
# under the Apache License, Version 2.0 (http://www.apache.org/licenses/LICENSE-2.0).  Unmodified
# except for formatting and the removal of unused branches' print; the package itself is not a
# dependency of the project (not in requirements/lock.txt).
# --------------------------------------------------------------------------------------------------
class InputStream:
    def __init__(self, data):
        self.data = data
        self.i = 0

    def read(self, size):
        out = self.data[self.i: self.i + size]
        self.i += size
        return int(out, 2)


def access_bit(data, num):
    base = int(num // 8)
    shift = 7 - int(num % 8)
    return (data[base] & (1 << shift)) >> shift


def bytes2bit(data):
    return "".join([str(access_bit(data, i)) for i in range(len(data) * 8)])


def decode_rle(rle):
    input = InputStream(bytes2bit(rle))
    num = input.read(32)
    word_size = input.read(5) + 1
    rle_sizes = [input.read(4) + 1 for _ in range(4)]
    i = 0
    out = np.zeros(num, dtype=np.uint8)
    while i < num:
        x = input.read(1)
        j = i + 1 + input.read(rle_sizes[input.read(2)])
        if x:
            val = input.read(word_size)
            out[i:j] = val
            i = j
        else:
            while i < j:
                val = input.read(word_size)
                out[i] = val
                i += 1
    return out


def bits2byte(arr_str, n=8):
    rle = []
    numbers = [arr_str[i: i + n] for i in range(0, len(arr_str), n)]
    for i in numbers:
        rle.append(int(i, 2))
    return rle


def base_rle_encode(inarray):
    ia = np.asarray(inarray)
    n = len(ia)
    if n == 0:
        return None, None, None
    y = ia[1:] != ia[:-1]
    i = np.append(np.where(y), n - 1)
    z = np.diff(np.append(-1, i))
    p = np.cumsum(np.append(0, z))[:-1]
    return z, p, ia[i]


def encode_rle(arr, wordsize=8, rle_sizes=[3, 4, 8, 16]):  # noqa: B006  (as in the reference)
    num = len(arr)
    numbits = f"{num:032b}"
    wordsizebits = f"{wordsize - 1:05b}"
    rle_bits = "".join([f"{x - 1:04b}" for x in rle_sizes])
    base_str = numbits + wordsizebits + rle_bits
    out_str = ""
    for length_reeks, p, value in zip(*base_rle_encode(arr)):
        if length_reeks == 1:
            out_str += "0" + "00" + "000" + f"{value:08b}"
        elif length_reeks > 1:
            if length_reeks <= 8:
                out_str += "1" + "00" + f"{length_reeks - 1:03b}" + f"{value:08b}"
            elif 8 < length_reeks <= 16:
                out_str += "1" + "01" + f"{length_reeks - 1:04b}" + f"{value:08b}"
            elif 16 < length_reeks <= 256:
                out_str += "1" + "10" + f"{length_reeks - 1:08b}" + f"{value:08b}"
            else:
                length_temp = length_reeks
                while length_temp > 2**16:
                    out_str += "1" + "11" + f"{2 ** 16 - 1:016b}" + f"{value:08b}"
                    length_temp -= 2**16
                out_str += "1" + "11" + f"{length_temp - 1:016b}" + f"{value:08b}"
    nzfill = 8 - len(base_str + out_str) % 8
    total_str = base_str + out_str
    total_str = total_str + nzfill * "0"
    return bits2byte(total_str)


def mask2rle(mask):
    assert len(mask.shape) == 2, "mask must be 2D np.array"
    assert mask.dtype == np.uint8 or mask.dtype == int, "mask must be uint8 or int"
    array = mask.ravel()
    array = np.repeat(array, 4)
    return encode_rle(array)
# ----------------------------------------------- end of the vendored reference ------------------


def ref_decode(rle, h, w) -> np.ndarray:
    """The reference's decoding as its ``decode_from_annotation`` does it: alpha channel, > 0."""
    return np.reshape(decode_rle(rle), [h, w, 4])[:, :, 3] > 0


def masks_for_tests():
    rng = np.random.default_rng(3)
    out = [np.zeros((7, 9), bool), np.ones((5, 4), bool), np.ones((300, 300), bool)]  # > 2**16 values per run
    big = np.zeros((200, 180), bool)
    big[40:170, 20:150] = True
    out.append(big)
    for _ in range(12):
        h, w = (int(v) for v in rng.integers(1, 40, 2))
        out.append(rng.random((h, w)) < rng.random())
    return out


# --------------------------------------------------------------------------------------------------
# pure parts
# --------------------------------------------------------------------------------------------------
def test_agreement_entropy_is_the_mean_binary_entropy_over_the_union():
    a = np.zeros((4, 5), np.float32)
    a[0, :2] = 0.5          # h = 1 bit
    a[1, :3] = 1.0          # h = 0
    a[2, 0] = 1 / 6         # h(1/6)
    h16 = -(1 / 6 * np.log2(1 / 6) + 5 / 6 * np.log2(5 / 6))
    assert agreement_entropy(a) == pytest.approx((2 * 1.0 + 3 * 0.0 + h16) / 6)   # 6 pixels in the union
    assert agreement_entropy(np.zeros((3, 3))) == 0.0                             # no vote: 0 (the gate flags it)
    assert agreement_entropy(np.full((2, 2), 0.5)) == pytest.approx(1.0)
    stack = agreement_entropy(np.stack([a, np.zeros_like(a)]))
    assert stack.shape == (2,) and stack[0] == pytest.approx(agreement_entropy(a)) and stack[1] == 0.0


def test_brush_rle_matches_label_studio_converter_bit_for_bit():
    """Ours encodes exactly the bytes of label-studio-converter's mask2rle of the 0/255 mask, and each
    decoder reads the other's RLE back to the same mask."""
    for m in masks_for_tests():
        h, w = m.shape
        ours = ls_rle_encode(m)
        assert ours == mask2rle(m.astype(np.uint8) * 255)
        assert (ref_decode(ours, h, w) == m).all()
        assert (ls_rle_decode(mask2rle(m.astype(np.uint8) * 255), h, w) == m).all()
    # literal stretches (Label Studio's own encoder writes them; e.g. a soft alpha) are read too
    m = masks_for_tests()[-1]
    rgba = np.repeat(m.astype(np.uint8) * 255, 4).reshape(*m.shape, 4)
    rgba[..., 0] = np.arange(m.size).reshape(m.shape) % 7          # breaks every run into literals
    assert (ls_rle_decode(encode_rle(rgba.ravel()), *m.shape) == m).all()
    # a drawn stroke's soft alpha copied into R, G, B (Label Studio's editor): the converter's bytes
    alpha = (np.arange(m.size).reshape(m.shape) * 37 % 256).astype(np.uint8) * m
    assert ls_rle_encode_values(ls_brush_rgba(alpha)) == encode_rle(np.repeat(alpha.ravel(), 4))
    assert (ls_rle_decode(ls_rle_encode_values(ls_brush_rgba(alpha)), *m.shape) == (alpha > 0)).all()


def test_coco_rle_for_cvat_decodes_with_pycocotools():
    from pycocotools import mask as mu

    for m in masks_for_tests():
        rle = coco_uncompressed_rle(m)
        json.dumps(rle)
        assert (mu.decode(mu.frPyObjects(rle, *m.shape)) == m).all()


def test_rankings_order_by_score_then_id():
    t = pd.DataFrame({"image_id": ["a", "b", "c", "d"], "g": [0.9, 0.0, 0.0, 0.5], "h": [0.1, 0.2, 0.7, 0.0]})
    assert rank(t, "gate")["image_id"].tolist() == ["b", "c", "d", "a"]
    assert rank(t, "disagreement")["image_id"].tolist() == ["c", "b", "a", "d"]
    combined = rank(t, "combined")
    assert combined["image_id"].tolist()[:2] == ["c", "b"] and combined["rank"].tolist() == [1, 2, 3, 4]
    assert rank(t, "combined", top=2)["image_id"].tolist() == ["c", "b"]


# --------------------------------------------------------------------------------------------------
# the commands
# --------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def labelled(tmp_path_factory):
    root = tmp_path_factory.mktemp("review")
    images, masks = make_image_folder(root / "data", n=12)
    out = root / "labels"
    res = cli("label", images, "--out", out, "--backend", "simulated", "--reference-masks", masks, *FAST)
    assert res.exit_code == 0, res.output
    return out


@pytest.fixture(scope="module")
def exported(labelled, tmp_path_factory):
    out = tmp_path_factory.mktemp("export") / "review"
    res = cli("review", "export", labelled, "--out", out, "--top", 6)
    assert res.exit_code == 0, res.output
    return out


def voted(labelled, image_id):
    return cv2.imread(str(labelled / "masks" / f"{image_id}.png"), cv2.IMREAD_UNCHANGED) > 0


def test_label_records_the_disagreement(labelled):
    t = pd.read_parquet(labelled / "labels.parquet")
    assert t["h"].between(0, 1).all() and t["h"].nunique() > 1
    assert (t.loc[t["n_valid"] == 0, "h"] == 0).all()


def test_export_writes_ranked_label_studio_and_cvat_files(labelled, exported):
    from pycocotools.coco import COCO

    table = pd.read_parquet(labelled / "labels.parquet")
    ranked = pd.read_csv(exported / "ranked.csv")
    expected = rank(table, "combined", top=6)
    assert ranked["image_id"].tolist() == expected["image_id"].tolist() and ranked["rank"].tolist() == list(range(1, 7))
    assert np.allclose(ranked["score"], expected["score"], atol=1e-6)
    record = json.loads((exported / "review.json").read_text())
    assert record["written_by"] == "geodistill review export" and record["complete"]
    # Label Studio local files: the storage path is the labelled folder, the URLs start from its parent
    assert record["label_studio"] == {"storage_path": record["input"], "document_root": str(Path(record["input"]).parent)}

    tasks = json.loads((exported / "labelstudio" / "tasks.json").read_text())
    assert [t["data"]["image_id"] for t in tasks] == ranked["image_id"].tolist()
    coco = COCO(str(exported / "cvat" / "instances_default.json"))
    by_file = {im["file_name"]: im for im in coco.dataset["images"]}
    for task, row in zip(tasks, ranked.itertuples()):
        m = voted(labelled, row.image_id)
        assert task["data"]["geodistill_export"] == record["export_id"]
        assert task["data"]["image"] == f"/data/local-files/?d={Path(record['input']).name}/{row.file}"
        results = task["predictions"][0]["result"] if task["predictions"] else []
        assert len(results) == int(m.any())
        for res in results:
            assert (res["original_width"], res["original_height"]) == (m.shape[1], m.shape[0])
            assert res["type"] == "brushlabels" and res["value"]["brushlabels"] == ["spacecraft"]
            assert (ref_decode(res["value"]["rle"], *m.shape) == m).all()        # the reference decoder
        im = by_file[row.file]
        anns = coco.loadAnns(coco.getAnnIds(imgIds=im["id"]))
        assert len(anns) == int(m.any()) and all((coco.annToMask(a) > 0).sum() == m.sum() for a in anns)
        for a in anns:
            assert (coco.annToMask(a).astype(bool) == m).all() and a["iscrowd"] == 1
    assert 'name="mask" toName="image"' in (exported / "labelstudio" / "label_config.xml").read_text()


def test_export_refuses_files_it_did_not_write(labelled, tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "ranked.csv").write_text("my own notes\n")
    res = cli("review", "export", labelled, "--out", out)
    assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1 and "--overwrite" in res.output
    assert (out / "ranked.csv").read_text() == "my own notes\n"
    res = cli("review", "export", tmp_path, "--out", out)
    assert res.exit_code == 2 and "not an output folder of geodistill label" in res.output


def test_export_refuses_a_users_file_inside_the_folders_it_replaces_whole(labelled, exported, tmp_path):
    """labelstudio/ and cvat/ are swapped in whole: a file of the user's in one is refused by name before
    anything runs, --overwrite or not, on a rerun over an earlier export and in a folder without one."""
    import shutil

    again = tmp_path / "again"
    shutil.copytree(exported, again)
    notes = again / "labelstudio" / "my_notes.txt"
    notes.write_text("mine\n")
    before = {p: p.read_bytes() for p in again.rglob("*") if p.is_file()}
    for extra in ((), ("--overwrite",)):
        res = cli("review", "export", labelled, "--out", again, "--top", 6, *extra)
        assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1, res.output
        assert str(notes) in res.output and "--overwrite" in res.output, res.output
        assert {p: p.read_bytes() for p in again.rglob("*") if p.is_file()} == before   # nothing ran
    fresh = tmp_path / "fresh"
    (fresh / "cvat").mkdir(parents=True)
    (fresh / "cvat" / "mine.json").write_text("{}")
    res = cli("review", "export", labelled, "--out", fresh, "--overwrite")
    assert res.exit_code == 2 and str(fresh / "cvat" / "mine.json") in res.output, res.output
    assert sorted(p.name for p in fresh.rglob("*")) == ["cvat", "mine.json"]


def corrected(m: np.ndarray) -> np.ndarray:
    """A person's correction: the vote plus a block (never empty)."""
    c = m.copy()
    c[2:8, 2:10] = True
    return c


def test_import_reads_label_studio_cvat_and_png(labelled, exported, tmp_path, monkeypatch):
    from pycocotools import mask as mu

    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    tasks = json.loads((exported / "labelstudio" / "tasks.json").read_text())
    ids = [t["data"]["image_id"] for t in tasks]
    want = {i: corrected(voted(labelled, i)) for i in ids}
    # Label Studio: the first three tasks annotated (brush, by the reference encoder), the rest untouched
    for k, t in enumerate(tasks):
        t["id"] = 100 + k
        if k < 3:
            m = want[t["data"]["image_id"]]
            t["annotations"] = [{"was_cancelled": False, "result": [{
                "type": "brushlabels", "from_name": "mask", "to_name": "image", "original_width": m.shape[1],
                "original_height": m.shape[0], "value": {"format": "rle", "rle": mask2rle(m.astype(np.uint8) * 255),
                                                         "brushlabels": ["spacecraft"]}}]}]
    ls = tmp_path / "ls.json"
    ls.write_text(json.dumps(tasks))
    out = tmp_path / "c.parquet"
    res = cli("review", "import", ls, "--review", exported, "--out", out)
    assert res.exit_code == 0, res.output
    art = open_artifact(out, "corrections")
    got = correction_masks(art)
    assert list(got) == ids[:3] and all((got[i] == want[i]).all() for i in got)
    assert art.meta.stage == "review import" and art.meta.params["format"] == "labelstudio"
    assert (art.table["iou_to_voted"] < 1).all()
    first = out.read_bytes()
    assert cli("review", "import", ls, "--review", exported, "--out", out).exit_code == 0
    assert out.read_bytes() == first                                     # same inputs: byte-identical

    # CVAT: its own image ids, one compressed RLE and one polygon annotation
    coco = json.loads((exported / "cvat" / "instances_default.json").read_text())
    coco["annotations"] = []
    for im in coco["images"]:
        im["id"] += 40
        m = want[ids[[t["data"]["image"].endswith(im["file_name"]) for t in tasks].index(True)]]
        rle = mu.encode(np.asfortranarray(m.astype(np.uint8)))
        coco["annotations"].append({"id": len(coco["annotations"]) + 1, "image_id": im["id"], "category_id": 1,
                                    "iscrowd": 1, "segmentation": {"size": rle["size"],
                                                                   "counts": rle["counts"].decode()}})
    coco["annotations"].append({"id": 99, "image_id": coco["images"][0]["id"], "category_id": 1, "iscrowd": 0,
                                "segmentation": [[0, 0, 3, 0, 3, 3, 0, 3]]})
    cvat = tmp_path / "cvat.json"
    cvat.write_text(json.dumps(coco))
    res = cli("review", "import", cvat, "--review", exported, "--out", tmp_path / "cvat.parquet")
    assert res.exit_code == 0, res.output
    got = correction_masks(open_artifact(tmp_path / "cvat.parquet"))
    assert set(got) == set(ids)
    assert all((got[i] == want[i]).all() for i in ids[1:]) and got[ids[0]][:3, :3].all()

    # a folder of PNGs
    pngs = tmp_path / "pngs"
    pngs.mkdir()
    for i in ids[:2]:
        cv2.imwrite(str(pngs / f"{i}.png"), want[i].astype(np.uint8) * 255)
    res = cli("review", "import", pngs, "--review", exported, "--out", tmp_path / "png.parquet")
    assert res.exit_code == 0, res.output
    got = correction_masks(open_artifact(tmp_path / "png.parquet"))
    assert list(got) == ids[:2] and all((got[i] == want[i]).all() for i in got)


def test_import_refuses_bad_inputs_in_one_line(labelled, exported, tmp_path):
    tasks = json.loads((exported / "labelstudio" / "tasks.json").read_text())
    iid = tasks[0]["data"]["image_id"]
    m = voted(labelled, iid)

    def annotate(task, mask):
        h, w = mask.shape
        task["annotations"] = [{"result": [{"type": "brushlabels", "from_name": "mask", "original_width": w,
                                            "original_height": h, "value": {"rle": ls_rle_encode(mask)}}]}]
        return [task]

    cases = {
        "from another export": [dict(annotate(dict(tasks[0]), corrected(m))[0],
                                     data={**tasks[0]["data"], "geodistill_export": "0123456789abcdef"})],
        "unknown image": [dict(annotate(dict(tasks[0]), corrected(m))[0], data={**tasks[0]["data"], "image_id": "nope"})],
        "differs from image": annotate(dict(tasks[0]), np.ones((m.shape[0] + 1, m.shape[1]), bool)),
        "is empty": annotate(dict(tasks[0]), np.zeros_like(m)),
    }
    for k, (message, doc) in enumerate(cases.items()):
        src = tmp_path / f"bad{k}.json"
        src.write_text(json.dumps(doc))
        res = cli("review", "import", src, "--review", exported, "--out", tmp_path / f"bad{k}.parquet")
        assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1, (message, res.output)
        assert message in res.output, (message, res.output)
        assert not (tmp_path / f"bad{k}.parquet").exists()
    pngs = tmp_path / "pngs"
    pngs.mkdir()
    cv2.imwrite(str(pngs / "stranger.png"), np.full((8, 8), 255, np.uint8))
    res = cli("review", "import", pngs, "--review", exported, "--out", tmp_path / "p.parquet")
    assert res.exit_code == 2 and "unknown image 'stranger'" in res.output
