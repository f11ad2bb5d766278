"""``geodistill label``'s YOLO dataset (a seeded validation split, relative links or copies that survive
the folder being moved) and the README's own-images quick start, run as written with the tests' tiny
random SAM 3 standing in for SAM 3."""

from __future__ import annotations

import os
import re
import shlex
import shutil
from pathlib import Path

import numpy as np
import yaml

from pipeline.labeling.formats import yolo_split
from tests.builders.teacher import FAST, REPO, cli, make_image_folder

SIM = ("--backend", "simulated")


def ultralytics_images(data_yaml: Path, key: str) -> list[Path]:
    """The image files Ultralytics reads for ``key`` (train / val) of ``data_yaml``: no ``path:`` key ->
    the yaml's folder is the root; a list file's ``./`` lines are relative to the list's own folder
    (ultralytics.data.utils.check_det_dataset, ultralytics.data.base.BaseDataset.get_img_files)."""
    doc = yaml.safe_load(data_yaml.read_text())
    root = Path(doc.get("path") or data_yaml.parent)
    listing = root / doc[key]
    return [listing.parent / line[2:] if line.startswith("./") else Path(line)
            for line in listing.read_text().splitlines() if line.strip()]


def test_yolo_split_is_disjoint_seeded_and_stable():
    ids = [f"img{i:02d}" for i in range(20)]
    train, val = yolo_split(ids, seed=7)
    assert len(val) == 4 and not set(train) & set(val) and sorted(train + val) == list(range(20))
    assert yolo_split(ids, seed=7) == (train, val)              # deterministic
    assert yolo_split(ids, seed=8)[1] != val                    # the seed picks the share
    more = ids + ["img20"]                                      # an image keeps its side when one is added
    val_more = {more[i] for i in yolo_split(more, seed=7)[1]}
    assert len(val_more) == 4 and val_more - {"img20"} <= {ids[i] for i in val}
    assert yolo_split(ids[:1], seed=7) == ([0], [])             # one image: nothing to hold out
    assert yolo_split(ids[:2], seed=7)[1] and yolo_split(ids[:2], seed=7)[0]  # two: one each


def test_yolo_dataset_has_a_real_val_split_and_survives_being_moved(tmp_path):
    proj = tmp_path / "proj"
    images, masks = make_image_folder(proj, n=10)
    out = proj / "labels"
    res = cli("label", images, "--out", out, "--reference-masks", masks, "--format", "yolo", *SIM, *FAST)
    assert res.exit_code == 0, res.output
    yolo = out / "yolo"
    doc = yaml.safe_load((yolo / "data.yaml").read_text())
    assert "path" not in doc and doc["train"] != doc["val"]
    train, val = ultralytics_images(yolo / "data.yaml", "train"), ultralytics_images(yolo / "data.yaml", "val")
    assert len(val) == 2 and len(train) == 8 and not {p.name for p in train} & {p.name for p in val}
    assert sorted(p.name for p in train + val) == sorted(p.name for p in images.iterdir())
    links = sorted((yolo / "images").iterdir())
    assert links and all(p.is_symlink() and not os.path.isabs(os.readlink(p)) for p in links)
    assert "val.txt holds out 2 of the 10 images" in (yolo / "README.txt").read_text()

    moved = tmp_path / "elsewhere" / "proj"   # the input and label folders moved together
    moved.parent.mkdir()
    shutil.move(proj, moved)
    for p in ultralytics_images(moved / "labels" / "yolo" / "data.yaml", "train"):
        assert p.read_bytes() == (moved / "images" / p.name).read_bytes()
        assert (moved / "labels" / "yolo" / "labels" / f"{p.stem}.txt").is_file()  # images/ -> labels/

    # --copy-images: the same folder again, now copies that go anywhere (the label folder moved alone)
    res = cli("label", moved / "images", "--out", moved / "labels", "--reference-masks", moved / "masks",
              "--format", "yolo", "--copy-images", *SIM, *FAST)
    assert res.exit_code == 0, res.output
    alone = tmp_path / "labels-alone"
    shutil.move(moved / "labels", alone)
    shutil.rmtree(moved)
    copies = ultralytics_images(alone / "yolo" / "data.yaml", "val")
    assert copies and all(p.is_file() and not p.is_symlink() and p.stat().st_size > 0 for p in copies)
    assert "copies" in (alone / "yolo" / "README.txt").read_text()


def test_one_image_gives_no_val_split_and_says_why(tmp_path):
    images, masks = make_image_folder(tmp_path, n=1)
    out = tmp_path / "labels"
    res = cli("label", images, "--out", out, "--reference-masks", masks, "--format", "yolo", *SIM, *FAST)
    assert res.exit_code == 0, res.output
    doc = yaml.safe_load((out / "yolo" / "data.yaml").read_text())
    assert "val" not in doc and not (out / "yolo" / "val.txt").exists()
    assert "No validation split" in (out / "yolo" / "README.txt").read_text()
    assert "yolo: no val split" in res.stderr


def _quick_start() -> list[str]:
    """The shell lines of the README's "Your own images" quick start (its first bash block)."""
    text = (REPO / "README.md").read_text()
    section = text.split("## Your own images", 1)[1].split("\n## ", 1)[0]
    block = re.search(r"```bash\n(.*?)```", section, re.S).group(1)
    return [line for line in block.splitlines() if line.strip()]


def test_readme_quick_start_runs_as_written_with_the_tiny_sam3(tmp_path, tiny_sam3, monkeypatch):
    """The quick start copy-pasted: `make install` is a Makefile target, `hf download` writes the folder
    `--checkpoint` reads (the tiny SAM 3 stands in for it), `geodistill label` runs exactly as written,
    and `geodistill distill`'s command line parses (its run trains a student: tests/cli/test_distill.py)."""
    from pipeline.cli.main import main

    lines = _quick_start()
    assert lines[0].startswith("make install") and "make demo" not in "\n".join(lines)
    assert re.search(r"^install:", (REPO / "Makefile").read_text(), re.M)
    assert any(line.startswith("hf download facebook/sam3 --local-dir sam3/") for line in lines)
    monkeypatch.chdir(tmp_path)
    make_image_folder(tmp_path, n=4, masks=False)
    (tmp_path / "sam3").symlink_to(tiny_sam3, target_is_directory=True)
    monkeypatch.setenv("GEODISTILL_QUIET", "1")
    ran = []
    for line in lines:
        argv = shlex.split(line, comments=True)
        if argv[:1] != ["geodistill"]:
            continue
        if argv[1] == "label":
            res = cli(*argv[1:])
            assert res.exit_code == 0, res.output
            assert sorted(p.name for p in (tmp_path / "labels" / "masks").iterdir()) == [
                f"img{i:02d}.png" for i in range(4)]
        else:
            cmd = main.get_command(main.make_context("geodistill", argv[1:2]), argv[1])
            cmd.make_context(argv[1], argv[2:])  # every flag it names exists and the line parses
        ran.append(argv[1])
    assert ran == ["label", "distill"]


def test_a_contact_sheet_caption_is_wrapped_or_shrunk_never_cut():
    import cv2

    from pipeline.datasets.contact_sheet import caption_lines, tile

    label = "deep/sub/folder/a_very_long_image_name_from_a_camera_0001 g=0.93"
    for size in (32, 192, 384):
        lines, scale = caption_lines(label, size - 6, max(size / 400.0, 0.3))
        assert "".join(lines).replace(" ", "") == label.replace(" ", "")   # every character is there
        assert all(cv2.getTextSize(ln, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][0] <= size - 6 for ln in lines)
        assert tile(np.zeros((size, size, 3), np.uint8), None, label, size).shape == (size, size, 3)
    assert caption_lines("img01 g=0.50", 186, 0.48) == (["img01 g=0.50"], 0.48)  # a short one: as it was
