"""The SPARK 2024 (stream 1) reader, and colour-coded masks read through a class table with a stated
tolerance: SPARK's JPEG masks (never exact colours) and SpaceSense-Bench's PNG seg files (a colour
outside the table refuses the file)."""

import csv
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from pipeline.artifacts.store import open_artifact
from pipeline.datasets import adapters
from pipeline.datasets.loading import (BadFileError, ColorTable, DecodeCache, decode_rows, load_labels, load_mask,
                                       parts_from_colors)
from pipeline.datasets.manifest import BadInputPolicy, check_manifest, spacecraft_split_violations
from pipeline.datasets.params import FrameSettings
from pipeline.params import PAPER
from pipeline.runtime.errors import InputError
from tests.builders.teacher import REPO, cli

PAPER_FRAMES = FrameSettings.from_params(PAPER.data.model_dump())  # data.bit_depth, letterbox, max_pixels

S = 24                                           # image side (px)
CLASSES = ("Cheops", "Proba2", "Smart1", "Soho", "VenusExpress", "XMM Newton")   # a space in a class name
OFFICIAL = {"train": 3, "val": 2}                # images per class in train.csv / val.csv
TOL = yaml.safe_load((adapters.MANIFEST_DIR / "spark.yaml").read_text())["color_tolerance"]   # as shipped
BODY = (slice(6, 18), slice(3, 12))              # red block (rows, cols), panel block right beside it
PANEL = (slice(6, 18), slice(12, 21))


def inner(block):
    """``block`` without its one-pixel rim (where JPEG blends it with its neighbours)."""
    return tuple(slice(b.start + 1, b.stop - 1) for b in block)


def _jpeg(path, rgb, quality=85):
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, quality])


def spark_mask(seed: int) -> np.ndarray:
    """Red body beside blue panels on black, each channel pushed up to 40 from its pure value (JPEG
    colour noise before compression adds its own): never an exact colour."""
    rng = np.random.default_rng(seed)
    m = np.zeros((S, S, 3), np.int16)
    m[BODY] = (255, 0, 0)
    m[PANEL] = (0, 0, 255)
    noise = rng.integers(0, 41, m.shape)
    return np.clip(np.where(m > 127, m - noise, m + noise), 0, 255).astype(np.uint8)


def make_spark(root):
    """``images/<Class>/<split>/*_img.jpg``, ``mask/<Class>/<split>/*_layer.jpg`` and the two lists."""
    root.mkdir(parents=True, exist_ok=True)
    k = 0
    for split, n in OFFICIAL.items():
        with open(root / f"{split}.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["Class", "Image name", "Mask name", "Bbox"])      # an extra column is ignored
            for cls in CLASSES:
                for i in range(n):
                    stem = f"img{k:06d}"
                    k += 1
                    img = np.full((S, S, 3), 30 + 10 * i, np.uint8)
                    img[BODY] = 200
                    _jpeg(root / "images" / cls / split / f"{stem}_img.jpg", img)
                    _jpeg(root / "mask" / cls / split / f"{stem}_layer.jpg", spark_mask(k))
                    w.writerow([cls, f"{stem}_img.jpg", f"{stem}_layer.jpg", "[1, 2, 3, 4]"])
    return root


def spark_protocol(tmp_path, test_groups=None):
    proto = yaml.safe_load((adapters.MANIFEST_DIR / "spark.yaml").read_text())
    proto["splits"] = {"test_images_per_spacecraft": 3, "test_groups": test_groups or {"unseen": 2},
                       "val": {"spacecraft": None, "count": 1, "images_per_spacecraft": 2},
                       "train": {"spacecraft": None, "count": 3, "images_per_spacecraft": 4}}
    p = tmp_path / "spark.yaml"
    p.write_text(yaml.safe_dump(proto))
    return p


def test_spark_reader_pools_both_lists_and_splits_by_class(tmp_path):
    root = make_spark(tmp_path / "spark")
    cfg = {"source": "spark", "root": str(root), "protocol": str(spark_protocol(tmp_path)), "seed": 5}
    spec = adapters.build_source(cfg)
    assert spec.spacecraft_disjoint and spec.mask_threshold == 127
    assert spec.part_colors == ColorTable({(255, 0, 0): 1, (0, 0, 255): 2}, TOL, True)
    policy = BadInputPolicy(False)
    rows = decode_rows(check_manifest(spec, policy), spec, PAPER_FRAMES, S, DecodeCache(tmp_path / "c"), policy)
    assert not policy.skipped and set(rows["spacecraft"]) == set(CLASSES)
    assert rows.groupby("split")["spacecraft"].nunique().to_dict() == {"test": 2, "val": 1, "train": 3}
    assert not spacecraft_split_violations(rows)
    assert (rows.groupby("spacecraft").size() == rows.groupby("spacecraft")["split"].first().map(
        {"test": 3, "val": 2, "train": 4})).all()
    assert set(rows["spark_split"]) == {"train", "val"}                # both official lists pooled
    assert rows["image_id"].is_unique and rows["image_id"].str.match(r"^[^_].*__(train|val)__img\d{6}_img$").all()
    assert set(rows[rows.split == "test"]["group"]) == {"unseen"}
    assert rows[rows.split == "train"]["mask_path"].isna().all()      # annotation-free training
    labeled = rows[rows.split != "train"]
    assert labeled["mask_path"].str.endswith("_layer.jpg").all() and (labeled["part_path"] == labeled["mask_path"]).all()
    assert (labeled["image_path"].str.replace("/images/", "/mask/").str.replace("_img.jpg", "_layer.jpg")
            == labeled["mask_path"]).all()
    cache = DecodeCache(tmp_path / "c")
    for path in labeled["mask_path"]:                                   # foreground = body or panels
        parts = load_labels(path, S, cache, spec.part_colors).array
        mask = load_mask(path, S, cache, spec.mask_threshold).array
        assert (parts[inner(BODY)] == 1).all() and (parts[inner(PANEL)] == 2).all()
        assert (parts[:5] == 0).all() and not mask[:5].any() and mask[inner(BODY)].all() and mask[inner(PANEL)].all()
        assert (mask != (parts > 0)).sum() <= 2          # a three-colour corner blend may differ
    # the same seed draws the same classes and images; another seed may not
    assert adapters.build_source(cfg).rows.equals(spec.rows)
    draws = {tuple(adapters.build_source({**cfg, "seed": s}).rows["image_id"]) for s in range(4)}
    assert len(draws) > 1
    # named classes (as SpaceSense-Bench's protocol) are taken as given; an unknown one is named
    named = adapters.build_source({**cfg, "protocol": str(spark_protocol(tmp_path, {"A": ["XMM Newton", "Soho"]}))})
    assert set(named.rows[named.rows.split == "test"]["spacecraft"]) == {"XMM Newton", "Soho"}
    for seed in range(4):                  # a drawn group never takes a class another group names, in any order
        mixed = adapters.build_source({**cfg, "seed": seed, "protocol": str(spark_protocol(tmp_path, {"A": 1, "B": ["Soho"]}))})
        assert mixed.rows.groupby("group")["spacecraft"].unique().map(sorted).to_dict()["B"] == ["Soho"]
        assert "Soho" not in set(mixed.rows[mixed.rows.group != "B"]["spacecraft"])
    with pytest.raises(InputError, match=r"spacecraft 'Rosetta' \(test/A\) not found"):
        adapters.build_source({**cfg, "protocol": str(spark_protocol(tmp_path, {"A": ["Rosetta"]}))})


def test_spark_lists_are_checked(tmp_path):
    root = tmp_path / "spark"
    root.mkdir()
    cfg = {"source": "spark", "root": str(root), "protocol": None, "seed": 0}
    with pytest.raises(InputError, match=r"none of the SPARK lists \['train.csv', 'val.csv'\] found"):
        adapters.build_source(cfg)
    (root / "train.csv").write_text("Class,Image\nSoho,a_img.jpg\n")
    with pytest.raises(InputError, match=r"train.csv: SPARK list lacks column\(s\) \['Image name', 'Mask name'\]"):
        adapters.build_source(cfg)


def test_color_table_tolerance_is_stated_never_exact():
    table = ColorTable({(255, 0, 0): 1, (0, 0, 255): 2}, TOL, True)
    at_tolerance = np.array([[[255 - TOL, TOL, TOL], [TOL, TOL, TOL], [TOL, 0, 255 - TOL], [0, 0, 0]]], np.uint8)
    assert parts_from_colors(at_tolerance, table).tolist() == [[1, 0, 2, 0]]
    # JPEG blends: red-black goes to the nearer end; a red/blue boundary pixel (4:2:0 chroma) is foreground
    blends = np.array([[[127, 0, 0], [128, 0, 0], [0, 10, 140], [150, 24, 150]]], np.uint8)
    got = parts_from_colors(blends, table)
    assert got[0, :3].tolist() == [0, 1, 2] and got[0, 3] in (1, 2)
    with pytest.raises(BadFileError, match=r"m.jpg: seg colour \(150, 24, 150\) is outside the class table"):
        parts_from_colors(blends[:, 3:], ColorTable(table.colors, TOL, False), "m.jpg")    # no blends: refused
    # one step past the tolerance, on no blend: refused, naming the file, the colour and the tolerance
    for px in ((0, TOL + 1, 0), (255, 255, 255), (0, TOL + 1, 255)):
        bad = np.zeros((2, 2, 3), np.uint8)
        bad[1, 1] = px
        with pytest.raises(BadFileError, match=rf"m.jpg: seg colour \({px[0]}, {px[1]}, {px[2]}\) .*within {TOL}"):
            parts_from_colors(bad, table, "m.jpg")


def test_protocol_colour_options_are_checked(tmp_path):
    where = tmp_path / "p.yaml"
    with pytest.raises(InputError, match=r"color_tolerance=128 must be a whole number in \[0, 127\]"):
        adapters._parse_colors({"part_colors": {"255,0,0": 1}, "color_tolerance": 128}, where)
    with pytest.raises(InputError, match=r"\(255, 0, 0\) and \(200, 0, 0\) are within 2 x color_tolerance=30"):
        adapters._parse_colors({"part_colors": {"255,0,0": 1, "200,0,0": 2}, "color_tolerance": 30}, where)
    with pytest.raises(InputError, match=r"\(0, 0, 0\) and \(20, 0, 0\)"):   # black is in every table
        adapters._parse_colors({"part_colors": {"20,0,0": 1}, "color_tolerance": 10}, where)
    assert adapters._parse_colors({"part_colors": {}}, where) is None


def _prepare(tmp_path, name, *sets, skip=False):
    out = tmp_path / name / "artifacts"
    args = ["prepare", "--params", REPO / "params.yaml", "--out-dir", out, "--set", f"data.resolution={S}",
            "--set", f"data.cache_dir={tmp_path / 'cache'}", "--set", "data.contact_sheet_images=2"]
    for s in sets:
        args += ["--set", s]
    return cli(*args, *(["--skip-bad"] if skip else [])), out


def _refused_then_skipped(tmp_path, bad, *sets) -> tuple[Path, tuple[int, int, int]]:
    """prepare refuses ``bad`` in one line naming it and its colour; with --skip-bad it is listed."""
    res, _ = _prepare(tmp_path, "refused", *sets)
    lines = [ln for ln in res.stderr.strip().splitlines() if "error" in ln.lower()]
    assert res.exit_code == 2 and len(lines) == 1, res.output
    m = re.search(rf"{re.escape(str(bad))}: seg colour \((\d+), (\d+), (\d+)\) is outside the class table", lines[0])
    assert m and "--skip-bad" in lines[0], lines[0]
    res, out = _prepare(tmp_path, "skipped", *sets, skip=True)
    assert res.exit_code == 0, res.output
    skipped = open_artifact(out / "skipped_files.parquet").df
    assert skipped[skipped.path == str(bad)]["reason"].str.startswith(f"seg colour ({m[1]}, {m[2]}, {m[3]})").tolist() == [True]
    return out, tuple(int(v) for v in m.groups())


def test_spark_through_prepare_refuses_a_mask_of_foreign_colours(tmp_path):
    root = make_spark(tmp_path / "spark")
    proto = spark_protocol(tmp_path, {"A": ["Soho", "XMM Newton"]})
    rows = adapters.build_source({"source": "spark", "root": str(root), "protocol": str(proto), "seed": 2026}).rows
    bad = Path(rows[rows.spacecraft == "Soho"]["mask_path"].iloc[-1])    # a green blob: not a SPARK mask
    m = spark_mask(0)
    m[1:5, 1:5] = (0, 255, 0)
    _jpeg(bad, m, quality=100)
    out, colour = _refused_then_skipped(tmp_path, bad, "data.source=spark", f"data.root={root}", f"data.protocol={proto}")
    assert colour[1] > TOL                                             # green: neither a table colour nor a blend
    df = open_artifact(out / "manifest.parquet").df
    assert set(df["dataset"]) == {"spark"} and str(bad) not in set(df["mask_path"].dropna())
    assert set(df[df.split == "test"]["spacecraft"]) == {"Soho", "XMM Newton"}
    ref = open_artifact(out / "reference.zarr")
    parts, has = ref.numpy("parts"), ref.numpy("has_mask")
    assert set(np.unique(parts[has])) == {0, 1, 2}
    np.testing.assert_array_equal(ref.numpy("mask")[has][:, BODY[0], BODY[1]][:, 1:-1, 1:-1], True)


def test_spacesense_refuses_a_seg_colour_outside_the_table(tmp_path):
    root = tmp_path / "ssb"
    for sat in ("Kepler", "Dawn", "Rosetta"):
        for k in range(2):
            img = np.full((S, S, 3), 60, np.uint8)
            seg = np.zeros((S, S, 3), np.uint8)
            seg[4:10, 4:10] = (40, 0, 0)        # RGB, in the table
            seg[12:16, 4:20] = (0, 0, 255)
            if sat == "Kepler" and k == 1:
                seg[18:20, 2:4] = (0, 255, 0)   # not in the table: once silently background
            for sub, arr in (("image", img), ("seg", seg)):
                (root / sat / "traj_a" / sub).mkdir(parents=True, exist_ok=True)
                assert cv2.imwrite(str(root / sat / "traj_a" / sub / f"{1000 + k}.png"), arr[..., ::-1])
    proto = tmp_path / "ss.yaml"
    proto.write_text(yaml.safe_dump({
        "dataset": "spacesense", "mask_threshold": 0, "part_colors": {"40,0,0": 1, "0,0,255": 2},
        "splits": {"test_images_per_spacecraft": 2, "test_groups": {"KCP": ["Kepler"]},
                   "val": {"spacecraft": ["Dawn"], "images_per_spacecraft": 2},
                   "train": {"spacecraft": ["Rosetta"], "images_per_spacecraft": 2}}}))
    bad = root / "Kepler" / "traj_a" / "seg" / "1001.png"
    out, colour = _refused_then_skipped(tmp_path, bad, "data.source=spacesense", f"data.root={root}",
                                        f"data.protocol={proto}")
    assert colour == (0, 255, 0)                                       # exact: a PNG keeps it
    df = open_artifact(out / "manifest.parquet").df
    assert df[df.spacecraft == "Kepler"]["image_id"].tolist() == ["Kepler__traj_a__1000"]
