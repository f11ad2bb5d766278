"""Untrusted inputs are never used silently: folder-source files, label masks, imported teacher rows,
teacher / decode cache entries.  Every case goes through the stage CLI where it is a CLI path: a bad
input is exit 2 with one line naming the file (and row), or with --skip-bad a row of
skipped_files.parquet with its reason.  32-pixel images, a few files each: seconds in all."""

from __future__ import annotations

import logging
import os
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from pipeline.artifacts.store import open_artifact
from pipeline.datasets import loading as L
from pipeline.teachers.cache import TeacherCache, decode_entry, entry_key
from stages.prepare import main as prepare_main
from tests.builders.teacher import build_artifacts, cache_files, run_stage

REPO = Path(__file__).resolve().parents[2]
PARAMS = str(REPO / "params.yaml")
S = 32


@pytest.fixture(autouse=True)
def _quiet(monkeypatch):
    monkeypatch.setenv("GEODISTILL_QUIET", "1")


def _img(path: Path, value: int = 200) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    a = np.zeros((S, S, 3), np.uint8)
    a[8:20, 8:20] = value
    assert cv2.imwrite(str(path), a)
    return path


def _mask(path: Path, values=(255,)) -> Path:
    """A mask whose foreground is split into vertical bands of ``values`` (one value: binary)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    m = np.zeros((S, S), np.uint8)
    for k, v in enumerate(values):
        m[8:20, 8 + 4 * k:8 + 4 * (k + 1)] = v
    assert cv2.imwrite(str(path), m)
    return path


def folder(root: Path, n_images: int = 4, n_masks: int = 2) -> Path:
    for k in range(n_images):
        _img(root / "images" / f"good{k}.png")
    for k in range(n_masks):
        _mask(root / "masks" / f"good{k}.png")
    return root


def prepare(root: Path, out: Path, *extra: str):
    args = ["--params", PARAMS, "--out-dir", str(out)]
    for s in ("data.source=folder", f"data.root={root}", f"data.resolution={S}", "data.contact_sheet_images=2",
              f"data.cache_dir={out.parent / 'decode-cache'}"):
        args += ["--set", s]
    return CliRunner().invoke(prepare_main, [*args, *extra])


def one_error_line(res, *needles: str) -> str:
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    for n in needles:
        assert n in lines[0], lines[0]
    return lines[0]


def skipped(out: Path) -> dict[str, str]:
    df = open_artifact(out / "skipped_files.parquet", "skipped_files").df
    return dict(zip(df["path"], df["reason"]))


# ---------------------------------------------------------------------------------------------------
# 1. files of a folder source
# ---------------------------------------------------------------------------------------------------
def test_broken_symlink_image_is_an_error_or_listed(tmp_path):
    root = folder(tmp_path / "data")
    link = root / "images" / "lost.png"
    link.symlink_to(tmp_path / "nowhere.png")
    one_error_line(prepare(root, tmp_path / "a"), str(link), "broken symbolic link", "--skip-bad")
    res = prepare(root, tmp_path / "b", "--skip-bad")
    assert res.exit_code == 0, res.output
    assert "broken symbolic link" in skipped(tmp_path / "b")[str(link)]
    assert "lost" not in open_artifact(tmp_path / "b" / "manifest.parquet").df["image_id"].tolist()


def test_broken_symlink_image_through_the_real_cli(tmp_path):
    """The same through ``python -m stages.prepare``: exit 2, the error is one stderr line naming the file."""
    root = folder(tmp_path / "data", n_masks=0)
    link = root / "images" / "lost.png"
    link.symlink_to(tmp_path / "nowhere.png")
    env = dict(os.environ, GEODISTILL_LOG="ERROR", GEODISTILL_QUIET="1")
    out = tmp_path / "a"
    r = subprocess.run([sys.executable, "-m", "stages.prepare", "--params", PARAMS, "--set", "data.source=folder",
                        "--set", f"data.root={root}", "--set", f"data.resolution={S}",
                        "--set", f"data.cache_dir={tmp_path / 'c'}", "--out-dir", str(out)],
                       cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and str(link) in lines[0] and "Traceback" not in r.stderr
    assert not (out / "manifest.parquet").exists()


def test_broken_symlink_mask_is_an_error_or_listed_with_its_image(tmp_path):
    root = folder(tmp_path / "data")
    link = root / "masks" / "good2.png"
    link.symlink_to(tmp_path / "nowhere.png")
    one_error_line(prepare(root, tmp_path / "a"), str(link), "broken symbolic link")
    res = prepare(root, tmp_path / "b", "--skip-bad")
    assert res.exit_code == 0, res.output
    sk = skipped(tmp_path / "b")
    assert "broken symbolic link" in sk[str(link)]
    assert "not used" in sk[str(root / "images" / "good2.png")]     # its image is listed too, never dropped silently
    assert sorted(open_artifact(tmp_path / "b" / "manifest.parquet").df["image_id"]) == ["good0", "good1", "good3"]


def test_duplicate_mask_stems_are_an_error_or_skippable(tmp_path):
    root = folder(tmp_path / "data")
    dup = _mask(root / "masks" / "good1.jpg")
    line = one_error_line(prepare(root, tmp_path / "a"), str(dup), "2 mask files for stem 'good1'", "--skip-bad")
    assert "good1.png" in line
    res = prepare(root, tmp_path / "b", "--skip-bad")
    assert res.exit_code == 0, res.output
    sk = skipped(tmp_path / "b")
    for p in (dup, root / "masks" / "good1.png"):
        assert "ambiguous" in sk[str(p)]
    assert "mask is ambiguous" in sk[str(root / "images" / "good1.png")]
    df = open_artifact(tmp_path / "b" / "manifest.parquet").df
    assert sorted(df["image_id"]) == ["good0", "good2", "good3"]


@pytest.mark.parametrize("case", ["orphan_mask", "mask_subfolder"])
def test_every_unused_file_is_an_error_or_listed(tmp_path, case):
    root = folder(tmp_path / "data")
    # a mask in a sub-folder of masks/ belongs to the image at the same relative path (none here)
    bad = {"orphan_mask": root / "masks" / "ghost.png", "mask_subfolder": root / "masks" / "old" / "x.png"}[case]
    _mask(bad)
    needle = "mask without an image"
    one_error_line(prepare(root, tmp_path / "a"), str(bad), needle)
    res = prepare(root, tmp_path / "b", "--skip-bad")
    assert res.exit_code == 0, res.output
    assert needle in skipped(tmp_path / "b")[str(bad)]


def test_sub_folders_are_read_recursively_and_non_images_listed(tmp_path):
    """The sub-folder rule of label, distill and segment (docs/own-data.md): images in sub-folders are
    images (id = relative path without suffix), a mask at the same relative path is theirs; a file
    that is not an image is listed, not an error."""
    root = folder(tmp_path / "data")
    _img(root / "images" / "more" / "x.png")
    _mask(root / "masks" / "more" / "x.png")
    (root / "masks" / "notes.txt").write_text("not a mask")
    res = prepare(root, tmp_path / "a")
    assert res.exit_code == 0, res.output
    df = open_artifact(tmp_path / "a" / "manifest.parquet").df
    row = df.set_index("image_id").loc["more/x"]
    assert row["split"] in ("val", "test") and row["mask_path"] == str(root / "masks" / "more" / "x.png")
    assert "not an image file" in skipped(tmp_path / "a")[str(root / "masks" / "notes.txt")]


def test_hidden_files_are_listed_not_an_error(tmp_path):
    root = folder(tmp_path / "data")
    (root / "images" / ".DS_Store").write_bytes(b"\0\0")
    res = prepare(root, tmp_path / "a")
    assert res.exit_code == 0, res.output
    assert "hidden file" in skipped(tmp_path / "a")[str(root / "images" / ".DS_Store")]


# ---------------------------------------------------------------------------------------------------
# 2. label masks: foreground = value > 0, one warning naming a multi-valued file
# ---------------------------------------------------------------------------------------------------
def test_label_mask_values_0_to_3_are_foreground_with_one_warning(tmp_path, caplog):
    root = folder(tmp_path / "data", n_images=2, n_masks=0)
    labels = _mask(root / "masks" / "good0.png", values=(1, 2, 3))
    binary = _mask(root / "masks" / "good1.png", values=(255,))
    with caplog.at_level(logging.WARNING, logger="pipeline.datasets.loading"):
        res = prepare(root, tmp_path / "a")
    assert res.exit_code == 0, res.output
    df = open_artifact(tmp_path / "a" / "manifest.parquet").df
    masks = dict(zip(df["image_id"], open_artifact(tmp_path / "a" / "reference.zarr").numpy("mask")))
    expected = np.zeros((S, S), bool)
    expected[8:20, 8:20] = True                                              # labels 1, 2, 3: all foreground
    np.testing.assert_array_equal(masks["good0"], expected)
    expected[:, 12:] = False
    np.testing.assert_array_equal(masks["good1"], expected)                  # 0/255: unchanged
    warned = [r.getMessage() for r in caplog.records if str(labels) in r.getMessage()]
    assert len(warned) == 1 and "value > 0" in warned[0]                    # once, though read in two passes
    assert not [r for r in caplog.records if str(binary) in r.getMessage()]
    # a second run reads the decode cache: the same masks, and the warning is not lost
    caplog.clear()
    L._warned.clear()
    with caplog.at_level(logging.WARNING, logger="pipeline.datasets.loading"):
        assert prepare(root, tmp_path / "b").exit_code == 0
    assert [r for r in caplog.records if str(labels) in r.getMessage()]
    np.testing.assert_array_equal(open_artifact(tmp_path / "b" / "reference.zarr").numpy("mask"),
                                  np.stack([masks[i] for i in df["image_id"]]))


# ---------------------------------------------------------------------------------------------------
# 3. imported teacher rows
# ---------------------------------------------------------------------------------------------------
def _imported_dir(tmp_path: Path, bad_index=None, bad_score=None) -> Path:
    import yaml

    prompts = yaml.safe_load(Path(PARAMS).read_text())["teacher"]["prompts"]
    d = tmp_path / "imported"
    rows = []
    for i in range(6):
        for k, p in enumerate(prompts):
            for view, stem in (("identity", f"{k}"), ("vflip", f"vflip_{k}")):
                rows.append({"image_id": f"img{i:03d}", "prompt_index": k, "prompt": p, "score": 0.5, "view": view})
                _mask(d / "masks" / f"img{i:03d}" / f"{stem}.png")
    table = pd.DataFrame(rows).astype({"prompt_index": object, "score": object})
    if bad_index is not None:
        table.at[6, "prompt_index"] = bad_index
    if bad_score is not None:
        table.at[6, "score"] = bad_score
    table.to_csv(d / "scores.csv", index=False)
    return d


@pytest.mark.parametrize("bad_index, bad_score, needle", [
    ("three", None, "prompt_index 'three' is not a number"),
    (2.5, None, "must be an integer"),
    (-1, None, "must be an integer"),
    (10 ** 9, None, "must be an integer"),
    (1, None, "prompt_index 1 is used by another prompt"),
    (None, "high", "score 'high' is not a number"),
    (None, "inf", "must be a finite number in [0, 1]"),
    (None, "-inf", "must be a finite number in [0, 1]"),
    (None, 7.5, "must be a finite number in [0, 1]"),
    (None, -0.2, "must be a finite number in [0, 1]"),
])
def test_imported_teacher_bad_rows_exit_2_naming_file_and_row(tmp_path, bad_index, bad_score, needle):
    d = _imported_dir(tmp_path, bad_index, bad_score)
    paths = build_artifacts(tmp_path / "a")
    res = run_stage(paths, tmp_path / "cache", sets=["teacher.backend=imported", f"teacher.imported_dir={d}"])
    line = one_error_line(res, str(d / "scores.csv"), "row 6, line 8", needle)
    assert "img000" in line


def test_imported_teacher_good_rows_pass(tmp_path):
    d = _imported_dir(tmp_path)
    paths = build_artifacts(tmp_path / "a")
    res = run_stage(paths, tmp_path / "cache", sets=["teacher.backend=imported", f"teacher.imported_dir={d}"])
    assert res.exit_code == 0, res.output
    assert open_artifact(paths["out"]).numpy("masks").any()


# ---------------------------------------------------------------------------------------------------
# 4. cache entries carry and check their own key; never unpickled
# ---------------------------------------------------------------------------------------------------
def test_teacher_cache_entry_copied_over_another_key_is_recomputed(tmp_path, caplog):
    cache = TeacherCache(tmp_path, "fp")
    ka, kb = cache.key("sha-a", "spacecraft"), cache.key("sha-b", "spacecraft")
    cache.put(ka, np.ones((4, 4), bool), 0.9)
    cache.put(kb, np.zeros((4, 4), bool), 0.1)
    shutil.copyfile(cache.path(ka), cache.path(kb))          # a valid entry, in the wrong place
    with caplog.at_level(logging.WARNING, logger="pipeline.teachers.cache"):
        assert cache.get(kb) is None
    assert cache.stats.corrupt == 1 and not cache.path(kb).exists()
    assert [r for r in caplog.records if str(cache.path(kb)) in r.getMessage() and "recomputed" in r.getMessage()]
    assert cache.get(ka)[1] == pytest.approx(0.9)              # the original is untouched


def test_teacher_stage_recomputes_a_swapped_entry(tmp_path):
    paths, cache = build_artifacts(tmp_path / "a"), tmp_path / "cache"
    assert run_stage(paths, cache).exit_code == 0
    ref = open_artifact(paths["out"])
    masks, scores, fp = ref.numpy("masks"), ref.numpy("scores"), ref.fingerprint
    answers = {p: decode_entry(p.read_bytes()) for p in cache_files(cache)}
    src, dst = next((a, b) for a in answers for b in answers
                    if a != b and (answers[a][1] != answers[b][1] or (answers[a][0] != answers[b][0]).any()))
    shutil.copyfile(src, dst)                                   # dst now holds src's valid, checksummed answer
    res = run_stage(paths, cache)
    assert res.exit_code == 0, res.output
    out = open_artifact(paths["out"])
    np.testing.assert_array_equal(out.numpy("masks"), masks)
    np.testing.assert_array_equal(out.numpy("scores"), scores)
    assert out.fingerprint == fp
    assert dst.read_bytes() != src.read_bytes()                  # rewritten with its own answer


def test_cache_entries_are_never_unpickled(tmp_path, monkeypatch):
    calls = []
    for name in ("load", "loads"):
        monkeypatch.setattr(pickle, name, lambda *a, _n=name, **k: calls.append(_n))
    # teacher cache: a pickle in place of an entry is corrupt, not loaded
    tc = TeacherCache(tmp_path / "t", "fp")
    key = entry_key("sha", "fp", "spacecraft")
    tc.path(key).parent.mkdir(parents=True)
    tc.path(key).write_bytes(pickle.dumps({"mask": np.ones((2, 2), bool), "score": 1.0}))
    assert tc.get(key) is None and tc.stats.corrupt == 1
    # decode cache: an .npz entry holding an object array (a pickle) is a miss, then rewritten
    p = _img(tmp_path / "i.png")
    dc = L.DecodeCache(tmp_path / "d")
    sha = L.load_rgb(p, S, dc).sha256
    entry = dc.path(sha, "rgb", S)
    with open(entry, "wb") as f:
        np.savez(f, a=np.array([{"x": 1}], dtype=object), hw=np.array([S, S]), k=np.str_(dc.key(sha, "rgb", S)),
                 w=np.str_(""))
    assert dc.get(sha, "rgb", S) is None
    assert calls == []
    # and an entry copied over another key's file is a miss too
    q = _img(tmp_path / "j.png", value=90)
    other = L.load_rgb(q, S, dc)
    shutil.copyfile(dc.path(other.sha256, "rgb", S), entry)
    assert dc.get(sha, "rgb", S) is None
    np.testing.assert_array_equal(L.load_rgb(p, S, dc).array, L.read_rgb(p))
