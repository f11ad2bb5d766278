"""``--overwrite`` replaces only what the command wrote (pipeline/artifacts/ownership.py, docs/own-data.md 1): a
user's file inside each command's output folder survives a run with ``--overwrite``, or is refused by
name when it sits where an output must go (export, which replaces its bundle folder whole); label's
own files of an earlier run in other formats are removed, nothing else.  Each run uses the tests'
tiny random SAM 3 on four 32 px images, or a tiny checkpoint; seconds."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from pipeline.artifacts.ownership import remove_stale
from tests.builders.teacher import make_image_folder

FAST = ["--set", "data.resolution=32", "--set", "teacher.score_threshold=0", "--device", "cpu"]
MINE = b"the user's own file"


@pytest.fixture(autouse=True)
def quiet(monkeypatch):
    monkeypatch.setenv("GEODISTILL_QUIET", "1")
    monkeypatch.setenv("GEODISTILL_LOG", "ERROR")


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    img, _ = make_image_folder(tmp_path_factory.mktemp("data"), n=4, masks=False)
    return img


def cli(*args):
    from pipeline.cli.main import main

    return CliRunner().invoke(main, [str(a) for a in args])


def error_line(res) -> str:
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.stderr.strip().splitlines() if "error" in ln.lower()]
    assert len(lines) == 1 and "Traceback" not in res.output, res.output
    return lines[0]


def put(path, data: bytes = MINE):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path


def test_label_overwrite_keeps_a_users_file_in_masks_and_refuses_one_in_the_way(tmp_path, images, tiny_sam3):
    out = tmp_path / "own"
    label = ("label", images, "--out", out, "--checkpoint", tiny_sam3, *FAST)
    assert cli(*label).exit_code == 0
    hand = put(out / "masks" / "hand.png")
    note = put(out / "yolo" / "notes.txt")
    r = cli(*label, "--overwrite")
    assert r.exit_code == 0, r.output
    assert hand.read_bytes() == MINE and note.read_bytes() == MINE
    assert "masks/hand.png" not in json.loads((out / "label.json").read_text())["outputs"]
    # a user's own masks/ folder: refused without --overwrite, written into with it; the file stays
    fresh = tmp_path / "fresh"
    hand2 = put(fresh / "masks" / "hand.png")
    assert str(fresh / "masks") in error_line(cli("label", images, "--out", fresh, "--checkpoint", tiny_sam3, *FAST))
    r = cli("label", images, "--out", fresh, "--checkpoint", tiny_sam3, *FAST, "--overwrite")
    assert r.exit_code == 0, r.output
    assert hand2.read_bytes() == MINE and len(list((fresh / "masks").glob("*.png"))) == 5
    # a user's file exactly where a mask goes: named, --overwrite or not, and kept
    first = sorted((out / "masks").glob("img*.png"))[0]
    other = tmp_path / "other"
    mine = put(other / "masks" / first.name)
    line = error_line(cli("label", images, "--out", other, "--checkpoint", tiny_sam3, *FAST, "--overwrite"))
    assert str(mine) in line and "replaces only what geodistill label wrote" in line
    assert mine.read_bytes() == MINE and not (other / "label.json").exists()


def test_label_removes_its_own_files_of_formats_not_asked_for_and_writes_no_placeholder(tmp_path, images, tiny_sam3):
    out = tmp_path / "own"
    label = ("label", images, "--out", out, "--checkpoint", tiny_sam3, *FAST)
    assert cli(*label, "--format", "coco,yolo").exit_code == 0
    assert (out / "coco.json").is_file() and (out / "yolo" / "data.yaml").is_file()
    assert not (out / "masks").exists()  # no placeholder folder for a format not asked for
    keep = put(out / "yolo" / "labels" / "notes.txt")
    assert cli(*label, "--format", "png").exit_code == 0
    assert not (out / "coco.json").exists() and not (out / "yolo" / "data.yaml").exists()
    assert not (out / "yolo" / "images").exists()  # emptied folders of label's own go too
    assert keep.read_bytes() == MINE  # the user's file, and the folders holding it, stay
    record = json.loads((out / "label.json").read_text())
    assert record["formats"] == ["png"] and not any(p.startswith(("yolo/", "coco")) for p in record["outputs"])


def test_remove_stale_never_walks_an_earlier_versions_folder_entry(tmp_path):
    put(tmp_path / "masks" / "a.png")
    put(tmp_path / "coco.json")
    assert remove_stale(tmp_path, {"masks", "coco.json"}, {"labels.csv"}) == ["coco.json"]
    assert (tmp_path / "masks" / "a.png").exists()


def test_distill_overwrite_keeps_users_files_in_its_folders_and_refuses_its_project_files(tmp_path, images,
                                                                                          tiny_sam3):
    out = tmp_path / "run"
    mine = [put(out / d / "mine.txt") for d in ("artifacts", "reports", ".cache")]
    distill = ("distill", images, "--out", out, "--checkpoint", tiny_sam3, "--no-run", *FAST)
    assert "pass --overwrite to write into it" in error_line(cli(*distill))
    r = cli(*distill, "--overwrite")
    assert r.exit_code == 0, r.output
    assert all(p.read_bytes() == MINE for p in mine) and (out / "dvc.yaml").is_file()
    other = tmp_path / "run2"
    params = put(other / "params.yaml", b"my: params\n")
    line = error_line(cli("distill", images, "--out", other, "--checkpoint", tiny_sam3, "--no-run", *FAST,
                          "--overwrite"))
    assert str(params) in line and "replaces only what geodistill distill wrote" in line
    assert params.read_bytes() == b"my: params\n"


def test_segment_overwrite_keeps_a_users_file_in_its_output_folder(tmp_path, ckpts):
    from tests.builders.deploy import RES

    import cv2
    import numpy as np

    inp = tmp_path / "in"
    inp.mkdir()
    cv2.imwrite(str(inp / "a.png"), np.full((RES, RES, 3), 90, np.uint8))
    out = tmp_path / "masks"
    hand = put(out / "hand.png")
    r = cli("segment", "--checkpoint", ckpts["with"], "--input", inp, "--output", out, "--device", "cpu",
            "--overwrite")
    assert r.exit_code == 0, r.output
    assert hand.read_bytes() == MINE and (out / "a.png.mask.png").is_file()


def test_export_refuses_a_users_file_inside_its_bundle_folder_even_with_overwrite(tmp_path, ckpts):
    deploy = tmp_path / "deploy"
    put(deploy / "meta.json", json.dumps({"schema": "deploy"}).encode())  # an earlier bundle's folder
    put(deploy / "deploy.json", json.dumps({"files": {"model.ts": "0"}}).encode())
    put(deploy / "model.ts", b"an earlier bundle's model")
    notes = put(deploy / "notes.txt")
    for extra in ((), ("--overwrite",)):
        line = error_line(cli("export", "--checkpoint", ckpts["with"], "--out", deploy, "--device", "cpu",
                              "--no-int8", *extra))
        assert str(notes) in line and "replaces only what geodistill export wrote" in line
    assert notes.read_bytes() == MINE and (deploy / "model.ts").read_bytes() == b"an earlier bundle's model"


def test_profile_overwrite_never_replaces_a_users_params_file(tmp_path):
    mine = put(tmp_path / "params.yaml", b"my: params\n")
    beside = put(tmp_path / "notes.txt")
    line = error_line(cli("profile", "demo", "--out", mine, "--overwrite"))
    assert str(mine) in line and "replaces only what geodistill profile wrote" in line
    assert mine.read_bytes() == b"my: params\n" and beside.read_bytes() == MINE


def test_distill_refuses_a_users_file_inside_a_folder_dvc_replaces_whole_before_dvc_repro(tmp_path, images,
                                                                                         tiny_sam3, monkeypatch):
    import pipeline.cli.distill

    out = tmp_path / "run"
    distill = ("distill", images, "--out", out, "--checkpoint", tiny_sam3, *FAST)
    assert cli(*distill, "--no-run").exit_code == 0
    # an earlier run's bundle (export's own files) with the user's notes inside it
    deploy = out / "artifacts" / "deploy"
    put(deploy / "meta.json", json.dumps({"schema": "deploy"}).encode())
    put(deploy / "deploy.json", json.dumps({"files": {"model.ts": "0"}}).encode())
    put(deploy / "model.ts", b"an earlier bundle's model")
    notes = put(deploy / "my_notes.txt")
    monkeypatch.setattr(pipeline.cli.distill, "run_project", lambda *a, **k: pytest.fail("dvc repro ran"))
    for extra in ((), ("--overwrite",)):
        line = error_line(cli(*distill, *extra))
        assert str(notes) in line and "`dvc repro` replaces artifacts/deploy/ whole" in line, line
    assert notes.read_bytes() == MINE
    notes.unlink()
    # a folder DVC recorded (dvc.lock + its .dir listing in the project's cache): a file it did not list
    ck = out / "artifacts" / "checkpoints" / "plain" / "42"
    put(ck / "model.safetensors", b"weights")
    listing = json.dumps([{"relpath": "model.safetensors", "md5": "0"}]).encode()
    put(out / ".dvc" / "cache" / "files" / "md5" / "ab" / "cdef.dir", listing)
    lock = {"schema": "2.0", "stages": {"train_plain": {"cmd": "x", "outs": [
        {"path": "artifacts/checkpoints/plain/42", "hash": "md5", "md5": "abcdef.dir"}]}}}
    put(out / "dvc.lock", json.dumps(lock).encode())  # JSON is YAML
    mine = put(ck / "notes.txt")
    line = error_line(cli(*distill, "--overwrite"))
    assert str(mine) in line and mine.read_bytes() == MINE


def test_a_label_rerun_that_would_remove_the_masks_of_gone_images_is_refused_unless_overwrite(tmp_path, images,
                                                                                             tiny_sam3):
    import shutil

    out = tmp_path / "labels"
    assert cli("label", images, "--out", out, "--checkpoint", tiny_sam3, *FAST, "--format", "png").exit_code == 0
    more = tmp_path / "more"
    shutil.copytree(images, more)
    (more / "extra.png").write_bytes((more / "img00.png").read_bytes())
    # adding images to a labelled folder stays allowed (the input changed, every earlier image is there)
    assert cli("label", more, "--out", out, "--checkpoint", tiny_sam3, *FAST, "--format", "png").exit_code == 0
    before = sorted(p.name for p in (out / "masks").iterdir())
    assert "extra.png" in before
    fewer = tmp_path / "fewer"
    shutil.copytree(images, fewer)
    (fewer / "img00.png").unlink()
    line = error_line(cli("label", fewer, "--out", out, "--checkpoint", tiny_sam3, *FAST, "--format", "png"))
    assert "holds the labels of 2 image(s) no longer in" in line and "masks/extra.png" in line, line
    assert "--overwrite" in line and sorted(p.name for p in (out / "masks").iterdir()) == before
    r = cli("label", fewer, "--out", out, "--checkpoint", tiny_sam3, *FAST, "--format", "png", "--overwrite")
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in (out / "masks").iterdir()) == sorted(set(before) - {"img00.png", "extra.png"})


def test_a_label_that_fails_before_any_output_leaves_no_folder_it_made(tmp_path, images, tiny_sam3):
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(images, bad)
    (bad / "zz_broken.png").write_bytes(b"not an image")  # read after the good ones: their decode is cached
    out = tmp_path / "labels"
    line = error_line(cli("label", bad, "--out", out, "--checkpoint", tiny_sam3, *FAST))
    assert "zz_broken.png" in line and not out.exists()   # no .cache/decode left behind
    # an output folder that was there stays, with what was in it
    out.mkdir()
    mine = put(out / "notes.txt")
    error_line(cli("label", bad, "--out", out, "--checkpoint", tiny_sam3, *FAST))
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"] and mine.read_bytes() == MINE
