"""Real-dataset adapters on small fixture trees built in the documented layouts."""

import json

import cv2
import numpy as np
import pytest
import yaml

from pipeline.datasets import adapters, build
from pipeline.datasets.loading import DecodeCache, decode_rows, iter_arrays
from pipeline.datasets.manifest import BadInputPolicy, DatasetSpec, check_manifest, spacecraft_split_violations
from pipeline.datasets.params import FrameSettings
from pipeline.params import PAPER
from pipeline.runtime.errors import InputError

PAPER_FRAMES = FrameSettings.from_params(PAPER.data.model_dump())  # data.bit_depth, letterbox, max_pixels


def _img(path, h=24, w=24, value=90):
    path.parent.mkdir(parents=True, exist_ok=True)
    arr = np.full((h, w, 3), value, np.uint8)
    arr[h // 4: h // 2, w // 4: w // 2] = 220
    assert cv2.imwrite(str(path), arr)
    return path


def _seg(path, h=24, w=24, color_bgr=(0, 0, 40)):
    path.parent.mkdir(parents=True, exist_ok=True)
    arr = np.zeros((h, w, 3), np.uint8)
    arr[2:6, 3:9] = color_bgr            # a dark part colour: still foreground (any non-black)
    arr[10:12, 10:20] = (255, 0, 0)      # second part, blue in BGR = (0, 0, 255) RGB
    assert cv2.imwrite(str(path), arr)
    return path


def _grey_mask(path, h=24, w=24, value=200):
    path.parent.mkdir(parents=True, exist_ok=True)
    arr = np.zeros((h, w), np.uint8)
    arr[5:15, 5:15] = value
    arr[0, 0] = 100                      # below the SPEED+ threshold (> 128): background
    assert cv2.imwrite(str(path), arr)
    return path


def _decode(spec, tmp_path, size=16, skip=False):
    policy = BadInputPolicy(skip)
    rows = check_manifest(spec, policy)
    rows = decode_rows(rows, spec, PAPER_FRAMES, size, DecodeCache(tmp_path / "cache"), policy)
    return rows, policy


# ---------------------------------------------------------------------------------------------------
# SpaceSense-Bench
# ---------------------------------------------------------------------------------------------------
SATS = {  # folder name -> (nested same-name folder?, identity)
    "Kepler": (False, "Kepler"),
    "1712345678_Chandra": (False, "Chandra"),
    "Philae": (True, "Philae"),
    "Lunar_Reconnaissance_Orbiter": (True, "Lunar_Reconnaissance_Orbiter"),
    "20240101_Aqua_Terra": (False, "Aqua_Terra"),
    "Dawn": (False, "Dawn"),
    "Rosetta": (False, "Rosetta"),
}


def make_spacesense(root, per_traj=3):
    for folder, (nested, _) in SATS.items():
        base = root / folder / (folder if nested else "")
        for traj in ("traj_a", "traj_b"):
            for k in range(per_traj):
                name = f"{1000 + k}.png"
                _img(base / traj / "image" / name)
                _seg(base / traj / "seg" / name)
                (base / traj / "depth").mkdir(parents=True, exist_ok=True)
                (base / traj / "depth" / name).write_bytes(b"not an image")   # ignored
                (base / traj / "lidar").mkdir(exist_ok=True)
    return root


def spacesense_protocol(tmp_path, **over):
    proto = {
        "dataset": "spacesense", "mask_threshold": 0,
        "splits": {"test_images_per_spacecraft": 2,
                   "test_groups": {"KCP": ["Kepler", "Chandra", "Philae"]},
                   "val": {"spacecraft": None, "count": 1, "images_per_spacecraft": 2},
                   "train": {"spacecraft": None, "count": 3, "images_per_spacecraft": 4}},
        "part_colors": {"40,0,0": 1, "0,0,255": 2},
    }
    proto.update(over)
    p = tmp_path / "ss.yaml"
    p.write_text(yaml.safe_dump(proto))
    return p


def test_spacecraft_identity_strips_only_a_leading_timestamp():
    assert adapters.spacecraft_identity("20240101_Lunar_Reconnaissance_Orbiter") == "Lunar_Reconnaissance_Orbiter"
    assert adapters.spacecraft_identity("Lunar_Reconnaissance_Orbiter") == "Lunar_Reconnaissance_Orbiter"
    assert adapters.spacecraft_identity("Mars_2020") == "Mars_2020"
    assert adapters.spacecraft_identity("2020_Mars_2020") == "Mars_2020"


def test_spacesense_adapter_split_masks_and_parts(tmp_path):
    root = make_spacesense(tmp_path / "ssb")
    cfg = {"source": "spacesense", "root": str(root), "protocol": str(spacesense_protocol(tmp_path)), "seed": 3}
    spec = adapters.build_source(cfg)
    rows, policy = _decode(spec, tmp_path)
    assert not policy.skipped
    ids = set(rows["spacecraft"])
    assert ids == {ident for _, ident in SATS.values()}                  # 3 test + 1 val + 3 train = all 7
    assert "Lunar" not in ids and {"Kepler", "Chandra", "Philae"} <= ids
    counts = rows.groupby("split")["spacecraft"].nunique().to_dict()
    assert counts == {"test": 3, "val": 1, "train": 3}
    assert not spacecraft_split_violations(rows)
    assert (rows[rows.split == "test"].groupby("spacecraft").size() == 2).all()
    assert (rows[rows.split == "train"].groupby("spacecraft").size() == 4).all()
    assert rows[rows.split == "train"]["mask_path"].isna().all()          # annotation-free training
    assert rows[rows.split != "train"]["mask_path"].notna().all()
    assert set(rows[rows.split == "test"]["group"]) == {"KCP"}
    assert not rows["image_path"].str.contains("/depth/").any()
    assert rows["image_id"].is_unique
    assert (rows["width"] == 24).all() and (rows["height"] == 24).all() and rows["sha256"].str.len().eq(64).all()
    # decoded masks: any non-black pixel; parts through the colour table (RGB order)
    r = rows[rows.split == "test"].iloc[0]
    cache = DecodeCache(tmp_path / "cache")
    from pipeline.datasets.loading import load_labels, load_mask
    m = load_mask(r.mask_path, 24, cache, spec.mask_threshold).array
    assert m[3, 4] and m[11, 12] and not m[0, 0]
    assert m.sum() == 4 * 6 + 2 * 10
    parts = load_labels(r.part_path, 24, cache, spec.part_colors).array
    assert parts[3, 4] == 1 and parts[11, 12] == 2 and parts[0, 0] == 0


def test_spacesense_seeded_and_reproducible(tmp_path):
    root = make_spacesense(tmp_path / "ssb")
    proto = str(spacesense_protocol(tmp_path))
    a = adapters.build_source({"source": "spacesense", "root": str(root), "protocol": proto, "seed": 1}).rows
    b = adapters.build_source({"source": "spacesense", "root": str(root), "protocol": proto, "seed": 1}).rows
    assert a.equals(b)
    draws = {tuple(adapters.build_source({"source": "spacesense", "root": str(root), "protocol": proto,
                                          "seed": s}).rows["image_id"]) for s in range(6)}
    assert len(draws) > 1


def test_spacesense_missing_spacecraft_names_protocol(tmp_path):
    root = make_spacesense(tmp_path / "ssb")
    # the default protocol's CVI/HJM spacecraft are not in this tree
    with pytest.raises(InputError, match="spacesense_bench.yaml: spacecraft 'Cassini'"):
        adapters.build_source({"source": "spacesense", "root": str(root), "protocol": None, "seed": 0})
    bad = spacesense_protocol(tmp_path, splits={
        "test_groups": {"KCP": ["Kepler"], "CVI": ["Kepler"]},
        "val": {"spacecraft": ["Dawn"], "images_per_spacecraft": 1},
        "train": {"spacecraft": ["Rosetta"], "images_per_spacecraft": 1}})
    with pytest.raises(InputError, match="more than one split"):
        adapters.build_source({"source": "spacesense", "root": str(root), "protocol": str(bad), "seed": 0})


# ---------------------------------------------------------------------------------------------------
# SPEED+
# ---------------------------------------------------------------------------------------------------
def make_speedplus(root, n=12, masked=10):
    for domain in ("lightbox", "sunlamp"):
        entries = []
        for k in range(n):
            name = f"img{k:06d}.jpg"
            _img(root / domain / "images" / name)
            if k < masked:
                _grey_mask(root / domain / "masks" / name.replace(".jpg", ".png"))
            entries.append({"filename": name, "q_vbs2tango_true": [1, 0, 0, 0], "r_Vo2To_vbs_true": [0, 0, 5]})
        (root / domain / "test.json").write_text(json.dumps(entries))
    return root


def speed_protocol(tmp_path):
    p = tmp_path / "sp.yaml"
    proto = yaml.safe_load((adapters.MANIFEST_DIR / "speedplus.yaml").read_text())
    proto.update(train_images=4, val_images=3, test_images=None)
    p.write_text(yaml.safe_dump(proto))
    return p


def test_speedplus_adapter(tmp_path):
    root = make_speedplus(tmp_path / "speed")
    cfg = {"source": "speedplus", "root": str(root), "protocol": str(speed_protocol(tmp_path)),
           "domain": "sunlamp", "seed": 0}
    spec = adapters.build_source(cfg)
    assert not spec.spacecraft_disjoint
    rows, _ = _decode(spec, tmp_path)
    sizes = rows["split"].value_counts().to_dict()
    assert sizes["train"] == 4 and sizes["val"] == 3
    assert sizes["train"] + sizes["val"] + sizes["test"] <= 12
    assert set(rows["domain"]) == {"sunlamp"} and set(rows[rows.split == "test"]["group"]) == {"sunlamp"}
    assert rows["image_id"].is_unique
    assert rows[rows.split == "train"]["mask_path"].isna().all()
    assert rows[rows.split != "train"]["mask_path"].notna().all()
    assert rows["image_path"].str.contains("/sunlamp/images/").all()
    m = iter_arrays(rows[rows.split == "val"].head(1), spec, PAPER_FRAMES, 24, DecodeCache(tmp_path / "cache"))
    _, _, mask, _ = next(m)
    assert mask[10, 10] and not mask[0, 0]         # 200 > 128 foreground; 100 background
    with pytest.raises(InputError, match="data.domain"):
        adapters.build_source({**cfg, "domain": "moon"})


# ---------------------------------------------------------------------------------------------------
# TANGO
# ---------------------------------------------------------------------------------------------------
def make_tango(root, n_train=10, n_test=4):
    train = [f"tr{k}.png" for k in range(n_train)]
    test = [f"te{k}.jpg" for k in range(n_test)]
    for n in train + test:
        _img(root / "images" / n)
        _grey_mask(root / "masks" / (n.rsplit(".", 1)[0] + ".png"), value=255)
    (root / "train.txt").write_text("\n".join(train) + "\n")
    (root / "test.txt").write_text("\n".join(test) + "\n")
    return root


def test_tango_adapter(tmp_path):
    root = make_tango(tmp_path / "tango")
    proto = yaml.safe_load((adapters.MANIFEST_DIR / "tango.yaml").read_text())
    proto.update(train_images=5, val_images=3)
    p = tmp_path / "tango.yaml"
    p.write_text(yaml.safe_dump(proto))
    spec = adapters.build_source({"source": "tango", "root": str(root), "protocol": str(p), "seed": 4})
    rows, _ = _decode(spec, tmp_path)
    by = rows.groupby("split")["image_id"].apply(set).to_dict()
    assert len(by["train"]) == 5 and len(by["val"]) == 3
    assert by["test"] == {f"tango__te{k}" for k in range(4)}          # official test list unchanged
    assert not (by["train"] & by["val"])
    assert rows[rows.split == "train"]["mask_path"].isna().all()
    assert rows[rows.split == "test"]["mask_path"].notna().all()


# ---------------------------------------------------------------------------------------------------
# Any folder
# ---------------------------------------------------------------------------------------------------
def test_folder_adapter_matches_masks_by_stem(tmp_path):
    root = tmp_path / "mydata"
    for k, ext in enumerate([".png", ".jpg", ".tif", ".bmp", ".png", ".png"]):
        _img(root / "images" / f"s{k}{ext}")
    for k in (0, 1, 2, 3):
        _grey_mask(root / "masks" / f"s{k}.png", value=255)
    spec = adapters.build_source({"source": "folder", "root": str(root), "protocol": None, "seed": 0})
    rows, _ = _decode(spec, tmp_path)
    assert len(rows) == 6 and set(rows["spacecraft"]) == {"mydata"}
    assert set(rows[rows.split == "train"]["image_id"]) == {"s4", "s5"}
    assert (rows["split"] == "val").sum() == 2 and (rows["split"] == "test").sum() == 2
    assert rows[rows.split != "train"]["mask_path"].str.endswith(".png").all()


def test_spacecraft_in_two_splits_is_an_error_or_skipped(tmp_path):
    a = _img(tmp_path / "a.png")
    rows = build.pd.DataFrame([
        {"image_id": "x1", "dataset": "d", "domain": "d", "split": "train", "group": "train", "spacecraft": "Kepler",
         "image_path": str(a), "mask_path": None, "part_path": None},
        {"image_id": "x2", "dataset": "d", "domain": "d", "split": "test", "group": "KCP", "spacecraft": "Kepler",
         "image_path": str(a), "mask_path": None, "part_path": None},
        {"image_id": "x3", "dataset": "d", "domain": "d", "split": "val", "group": "val", "spacecraft": "Dawn",
         "image_path": str(a), "mask_path": None, "part_path": None}])
    spec = DatasetSpec(rows=rows, spacecraft_disjoint=True)
    with pytest.raises(InputError, match="Kepler.*eq:spacecraft-disjoint"):
        check_manifest(spec, BadInputPolicy(False))
    policy = BadInputPolicy(True)
    kept = check_manifest(spec, policy)
    assert kept["image_id"].tolist() == ["x2", "x3"]                  # the training copy is left out
    assert policy.table()["image_id"].tolist() == ["x1"]
    assert "eq:spacecraft-disjoint" in policy.table()["reason"].iloc[0]
