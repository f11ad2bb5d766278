"""``geodistill segment`` can be trusted with a user's folders: output names never collide (and the
case-only collisions a case-insensitive disk would cause are refused before anything is written), an
existing output is never replaced without ``--overwrite``, ``--output`` naming a file and links leaving
the input folder end in one line (or a skipped.csv row), never a traceback, and a checkpoint runs at the
resolution it was trained at, or asks for ``--resolution``.  32 px images, a tiny random checkpoint."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from pipeline.cli.segment import main as segment_main
from tests.builders.deploy import RES


@pytest.fixture(autouse=True)
def quiet(monkeypatch):
    monkeypatch.setenv("GEODISTILL_QUIET", "1")


def image(path: Path, value: int = 0) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(value)
    assert cv2.imwrite(str(path), rng.integers(0, 255, (RES, RES, 3), dtype=np.uint8))
    return path


def segment(ckpt: Path, inp: Path, out: Path, *args):
    return CliRunner().invoke(segment_main, ["--device", "cpu", "--checkpoint", str(ckpt), "--input", str(inp),
                                             "--output", str(out), *map(str, args)])


def snapshot(*folders: Path) -> dict[Path, tuple[bytes, int]]:
    return {p: (p.read_bytes(), p.stat().st_mtime_ns) for d in folders if d.exists()
            for p in sorted(d.rglob("*")) if p.is_file() and not p.is_symlink()}


def one_error_line(r, *needles: str) -> str:
    """Exit code 2, stdout empty, exactly one stderr line, naming each of ``needles``."""
    lines = r.stderr.strip().splitlines()
    assert r.exception is None or isinstance(r.exception, SystemExit), r.output  # no traceback
    assert r.exit_code == 2 and len(lines) == 1 and r.stdout == "", r.output
    assert "Traceback" not in r.output
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


def masks(out: Path) -> list[str]:
    return sorted(p.relative_to(out).as_posix() for p in out.rglob("*.mask.png"))


def test_distinct_names_for_inputs_that_used_to_collide(tmp_path, ckpts):
    inp = tmp_path / "in"
    for i, name in enumerate(["a.png", "a.jpg", "a_png.png", "sub/a.png", "sub/a.PNG.d/x.bmp"]):
        image(inp / name, i)
    before = snapshot(inp)
    r = segment(ckpts["with"], inp, tmp_path / "out", "--save-prob", "--overlay")
    assert r.exit_code == 0, r.output
    out = tmp_path / "out"
    assert masks(out) == ["a.jpg.mask.png", "a.png.mask.png", "a_png.png.mask.png", "sub/a.PNG.d/x.bmp.mask.png",
                          "sub/a.png.mask.png"]
    assert "wrote 5 mask(s)" in r.stderr
    assert len(list(out.rglob("*.prob.png"))) == len(list(out.rglob("*.overlay.png"))) == 5
    # each mask is its own image's: a.png and a.jpg hold different pixels
    assert all(cv2.imread(str(out / m), cv2.IMREAD_UNCHANGED).shape == (RES, RES) for m in masks(out))
    assert snapshot(inp) == before  # inputs never modified
    # a single file keeps its whole name too
    r = segment(ckpts["with"], inp / "a.jpg", tmp_path / "one")
    assert r.exit_code == 0 and masks(tmp_path / "one") == ["a.jpg.mask.png"], r.output


@pytest.mark.parametrize("names", [("b.png", "b.PNG"), ("Sub/c.png", "sub/c.png")])
def test_case_only_collision_is_refused_before_writing(tmp_path, ckpts, names):
    inp = tmp_path / "in"
    for i, n in enumerate(names):
        image(inp / n, i)
    image(inp / "z.png", 9)
    r = segment(ckpts["with"], inp, tmp_path / "out")
    line = one_error_line(r, str(inp / names[0]), str(inp / names[1]))
    assert "letter case" in line
    assert not (tmp_path / "out").exists()


def test_output_file_where_a_folder_is_needed_is_refused(tmp_path, ckpts):
    inp = tmp_path / "in"
    image(inp / "x.png")
    image(inp / "x.png.mask.png" / "y.png", 1)  # a folder named like x.png's mask
    r = segment(ckpts["with"], inp, tmp_path / "out")
    one_error_line(r, str(inp / "x.png"), str(inp / "x.png.mask.png" / "y.png"))
    assert not (tmp_path / "out").exists()


def test_output_that_is_a_file_is_one_line(tmp_path, ckpts):
    image(tmp_path / "in" / "a.png")
    target = tmp_path / "masks.txt"
    target.write_text("keep me")
    for out in (target, target / "sub"):
        r = segment(ckpts["with"], tmp_path / "in", out)
        line = one_error_line(r, str(target))
        assert "is a file" in line
    assert target.read_text() == "keep me"
    # a file inside the output tree where a mirrored sub-folder is needed
    image(tmp_path / "in" / "sub" / "b.png", 1)
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "sub").write_text("in the way")
    r = segment(ckpts["with"], tmp_path / "in", tmp_path / "out")
    one_error_line(r, str(tmp_path / "out" / "sub"))
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["sub"]


def test_links_leaving_the_input_folder_are_skipped_and_listed(tmp_path, ckpts):
    inp = tmp_path / "in"
    image(inp / "a.png")
    outside = image(tmp_path / "private" / "secret.png", 1)
    (tmp_path / "private" / "more.png").write_bytes(outside.read_bytes())
    os.symlink(outside, inp / "escape.png")
    os.symlink(tmp_path / "private", inp / "linked_dir")
    os.symlink(tmp_path / "gone.png", inp / "broken.png")
    os.symlink(inp / "a.png", inp / "alias.png")  # a link inside the folder is an ordinary input
    # without --skip-bad: the first one stops the run, one line naming it and the option, nothing written
    r = segment(ckpts["with"], inp, tmp_path / "out")
    one_error_line(r, str(inp / "broken.png"), "--skip-bad")
    assert not (tmp_path / "out").exists()
    r = segment(ckpts["with"], inp, tmp_path / "out", "--skip-bad")
    assert r.exit_code == 0, r.output
    assert "Traceback" not in r.output
    out = tmp_path / "out"
    assert masks(out) == ["a.png.mask.png", "alias.png.mask.png"]
    rows = {Path(row["path"]).name: row["reason"] for row in csv.DictReader(open(out / "skipped.csv"))}
    assert set(rows) == {"escape.png", "linked_dir", "broken.png"}
    assert "outside the input folder" in rows["escape.png"] and str(outside) in rows["escape.png"]
    assert "not followed" in rows["linked_dir"] and "broken" in rows["broken.png"]
    # never silent: one summary line names the first and the listing
    assert f"segment: skipped 3 bad file(s) (first: {inp / 'broken.png'}: broken" in r.stderr
    assert str(out / "skipped.csv") in r.stderr
    assert not (tmp_path / "private" / "secret.png.mask.png").exists()
    # only links that leave the folder: one line, nothing written
    only = tmp_path / "only"
    only.mkdir()
    os.symlink(outside, only / "escape.png")
    r = segment(ckpts["with"], only, tmp_path / "out2")
    one_error_line(r, str(only))
    assert not (tmp_path / "out2").exists()


def test_rerun_replaces_its_own_outputs_and_refuses_a_users_file_unless_asked(tmp_path, ckpts):
    inp = tmp_path / "in"
    image(inp / "a.png")
    image(inp / "b.png", 1)
    out = tmp_path / "out"
    assert segment(ckpts["with"], inp, out).exit_code == 0
    first = snapshot(out)
    # 2 masks + skipped.csv + confidence.csv + segment.json (the record of what segment wrote)
    assert len(first) == 5
    # a file segment did not write, where a new input's mask goes: refused, naming it; nothing written
    image(inp / "c.png", 2)
    (out / "c.png.mask.png").write_bytes(b"my own hand-made mask")
    first = snapshot(out)
    r = segment(ckpts["with"], inp, out)
    line = one_error_line(r, str(out / "c.png.mask.png"), "--overwrite")
    assert "was not written by geodistill segment" in line
    assert snapshot(out) == first
    # a stale skipped.csv alone (no segment.json) is not segment's either
    lone = tmp_path / "lone"
    lone.mkdir()
    (lone / "skipped.csv").write_text("path,reason\n")
    one_error_line(segment(ckpts["with"], inp / "c.png", lone), str(lone / "skipped.csv"))
    assert (lone / "skipped.csv").read_text() == "path,reason\n"
    # without the user's file, a rerun replaces segment's own outputs (same bytes) and adds the new one
    (out / "c.png.mask.png").unlink()
    r = segment(ckpts["with"], inp, out)
    assert r.exit_code == 0, r.output
    assert masks(out) == ["a.png.mask.png", "b.png.mask.png", "c.png.mask.png"]
    after = snapshot(out)
    assert all(after[p][0] == first[p][0] for p in first if p.name in ("a.png.mask.png", "b.png.mask.png"))
    # --overwrite replaces only what segment wrote: a user's file in the way stays refused
    (lone / "c.png.mask.png").write_bytes(b"mine")
    one_error_line(segment(ckpts["with"], inp / "c.png", lone, "--overwrite"), str(lone / "c.png.mask.png"))
    assert (lone / "c.png.mask.png").read_bytes() == b"mine"


def test_resolution_comes_from_the_checkpoint_or_is_asked_for(tmp_path, ckpts):
    image(tmp_path / "in" / "a.png")
    # recorded in the payload: used, and said so (params.yaml's data.resolution is never consulted)
    r = segment(ckpts["with"], tmp_path / "in", tmp_path / "o1", "--params", tmp_path / "none.yaml")
    assert r.exit_code == 0 and f"{RES}px (checkpoint {ckpts['with']})" in r.stderr, r.output
    # not recorded: one line asking for --resolution, nothing written, params file not used as a guess
    r = segment(ckpts["without"], tmp_path / "in", tmp_path / "o2")
    line = one_error_line(r, str(ckpts["without"]), "--resolution N")
    assert "records no training resolution" in line
    assert not (tmp_path / "o2").exists()
    r = segment(ckpts["without"], tmp_path / "in", tmp_path / "o2", "--resolution", RES)
    assert r.exit_code == 0 and f"{RES}px (--resolution)" in r.stderr, r.output
    # same weights, same resolution: same mask as the checkpoint that recorded it
    assert (tmp_path / "o1" / "a.png.mask.png").read_bytes() == (tmp_path / "o2" / "a.png.mask.png").read_bytes()
    # an override that differs from the recorded resolution is honoured, with a warning
    r = segment(ckpts["with"], tmp_path / "in", tmp_path / "o3", "--resolution", 16)
    assert r.exit_code == 0 and "warning: --resolution 16 differs from the 32px" in r.stderr, r.output
    one_error_line(segment(ckpts["with"], tmp_path / "in", tmp_path / "o4", "--resolution", 4), "--resolution 4")
    assert not (tmp_path / "o4").exists()
