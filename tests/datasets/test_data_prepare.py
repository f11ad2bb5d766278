"""The `prepare` stage end to end through its click command (64 px, tiny counts)."""

from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from pipeline.artifacts.store import open_artifact
from stages.prepare import main as prepare

REPO = Path(__file__).resolve().parents[2]
PARAMS = str(REPO / "params.yaml")
TINY = ["data.resolution=64", "data.synthetic.train_spacecraft=2", "data.synthetic.train_views=3",
        "data.synthetic.val_spacecraft=1", "data.synthetic.val_views=2", "data.synthetic.test_groups=[KCP, HJM]",
        "data.synthetic.test_spacecraft_per_group=1", "data.synthetic.test_views=2", "data.contact_sheet_images=4"]


def run(out, *extra, sets=()):
    args = ["--params", PARAMS, "--out-dir", str(out)]
    for s in [*TINY, f"data.cache_dir={out.parent / 'cache'}", *sets]:
        args += ["--set", s]
    return CliRunner().invoke(prepare, [*args, *extra])


def test_prepare_synthetic_end_to_end(tmp_path):
    out = tmp_path / "artifacts"
    res = run(out)
    assert res.exit_code == 0, res.output
    man = open_artifact(out / "manifest.parquet", "manifest")
    df = man.df
    assert len(df) == 2 * 3 + 1 * 2 + 2 * 1 * 2
    assert df.groupby("split").size().to_dict() == {"train": 6, "val": 2, "test": 4}
    assert set(df[df.split == "test"]["group"]) == {"KCP", "HJM"}
    assert {"background", "hard_case", "area_fraction"} <= set(df.columns)
    assert df.groupby("spacecraft")["split"].nunique().max() == 1           # eq:spacecraft-disjoint
    for col in ("image_path", "mask_path", "part_path"):
        assert all(Path(p).is_file() for p in df[col])
    images = open_artifact(out / "images.zarr", "images")
    ref = open_artifact(out / "reference.zarr", "reference")
    assert images["image"].shape == (12, 64, 64, 3) and images["image"].dtype == np.uint8
    assert ref["mask"].shape == (12, 64, 64) and ref.numpy("has_mask").all()
    assert ref["parts"].dtype == np.uint8 and ref.numpy("parts").max() <= 5
    assert images.attrs["image_ids"] == ref.attrs["image_ids"] == df["image_id"].tolist()
    masks = ref.numpy("mask")
    np.testing.assert_array_equal(masks, ref.numpy("parts") > 0)
    np.testing.assert_allclose(masks.mean((1, 2)), df["area_fraction"], atol=1e-9)
    # the stored PNGs are what the arrays hold
    first = cv2.imread(df["image_path"][0])[..., ::-1]
    np.testing.assert_array_equal(first, images.numpy("image")[0])
    assert len(open_artifact(out / "skipped_files.parquet", "skipped_files").df) == 0
    sheet = cv2.imread(str(out / "figures" / "contact_sheet.png"))
    assert sheet is not None and sheet.shape[0] > 64
    # determinism: same params -> same content and fingerprints
    out2 = tmp_path / "again"
    assert run(out2).exit_code == 0
    df2 = open_artifact(out2 / "manifest.parquet").df
    assert df2["sha256"].tolist() == df["sha256"].tolist()
    assert open_artifact(out2 / "images.zarr").fingerprint == images.fingerprint
    # a different seed changes content and fingerprint
    out3 = tmp_path / "seed"
    assert run(out3, sets=["data.seed=5"]).exit_code == 0
    assert open_artifact(out3 / "images.zarr").fingerprint != images.fingerprint


@pytest.mark.parametrize("bad", ["data.resolution=-3", "data.source=moon", "data.synthetic.train_views=x",
                                 "data.skip_bad=maybe"])
def test_prepare_bad_param_exits_2_with_one_line(tmp_path, bad):
    res = run(tmp_path / "a", sets=[bad])
    assert res.exit_code == 2
    msg = res.output.strip().splitlines()
    assert len(msg) == 1 and "error" in msg[0] and bad.split("=")[0] in msg[0]
    assert not (tmp_path / "a" / "manifest.parquet").exists()


def _img(path, size=20):
    path.parent.mkdir(parents=True, exist_ok=True)
    a = np.zeros((size, size, 3), np.uint8)
    a[5:12, 5:12] = 200
    assert cv2.imwrite(str(path), a)


def _mask(path, size=20):
    path.parent.mkdir(parents=True, exist_ok=True)
    m = np.zeros((size, size), np.uint8)
    m[5:12, 5:12] = 255
    assert cv2.imwrite(str(path), m)


def bad_folder(root):
    for k in range(4):
        _img(root / "images" / f"good{k}.png")
    for k in (0, 1):
        _mask(root / "masks" / f"good{k}.png")
    (root / "images" / "zero.png").write_bytes(b"")
    (root / "images" / "corrupt.jpg").write_bytes(b"\xff\xd8\xffgarbage")
    (root / "images" / "notes.txt").write_text("unsupported")
    _img(root / "images" / "mism.png")
    _mask(root / "masks" / "mism.png", size=16)                         # mask size mismatch
    _img(root / "images" / "good0.bmp")                                  # duplicate id 'good0'
    # mask size mismatch must be a val/test row to be checked: all masked rows are val/test here
    return root


def test_prepare_folder_bad_input_errors_name_the_file(tmp_path):
    root = bad_folder(tmp_path / "data")
    res = run(tmp_path / "a", sets=["data.source=folder", f"data.root={root}"])
    assert res.exit_code == 2
    line = res.output.strip().splitlines()
    assert len(line) == 1 and str(root / "images") in line[0] and "--skip-bad" in line[0]


def test_prepare_folder_skip_bad_records_every_case(tmp_path):
    root = bad_folder(tmp_path / "data")
    out = tmp_path / "a"
    res = run(out, "--skip-bad", sets=["data.source=folder", f"data.root={root}"])
    assert res.exit_code == 0, res.output
    skipped = open_artifact(out / "skipped_files.parquet", "skipped_files").df
    reasons = dict(zip(skipped["path"].map(lambda p: Path(p).name), skipped["reason"]))
    assert "zero-byte" in reasons["zero.png"]
    assert "corrupt" in reasons["corrupt.jpg"]
    assert "not an image file" in reasons["notes.txt"]   # listed, not an error (the folder scan of label/segment)
    assert "differs from image" in reasons["mism.png"]
    assert "duplicate image id 'good0' (also used by" in reasons["good0.png"]   # first in sorted order (good0.bmp) kept
    df = open_artifact(out / "manifest.parquet").df
    assert sorted(df["image_id"]) == ["good0", "good1", "good2", "good3"]
    ref = open_artifact(out / "reference.zarr")
    has = dict(zip(df["image_id"], ref.numpy("has_mask")))
    assert has == {"good0": True, "good1": True, "good2": False, "good3": False}
    assert "parts" not in ref
    assert (out / "synthetic" / "README.txt").is_file()     # declared DVC out exists, holds no stale files


def test_prepare_missing_listed_image(tmp_path):
    root = tmp_path / "tango"
    for n in ("a.png", "b.png", "c.png"):
        _img(root / "images" / n)
        _mask(root / "masks" / n)
    (root / "train.txt").write_text("a.png\nb.png\n")
    (root / "test.txt").write_text("c.png\ngone.png\n")
    proto = tmp_path / "t.yaml"
    proto.write_text((REPO / "data_manifests" / "tango.yaml").read_text()
                     .replace("train_images: 500", "train_images: 1").replace("val_images: 500", "val_images: 1"))
    sets = ["data.source=tango", f"data.root={root}", f"data.protocol={proto}"]
    res = run(tmp_path / "a", sets=sets)
    assert res.exit_code == 2 and "gone.png: file not found" in res.output
    res = run(tmp_path / "b", "--skip-bad", sets=sets)
    assert res.exit_code == 0, res.output
    skipped = open_artifact(tmp_path / "b" / "skipped_files.parquet").df
    assert skipped["path"].str.endswith("gone.png").tolist() == [True]
