"""segment's overlapped I/O (pipeline.deploy.image_files.segment_files, ``workers`` >= 1) against the serial
loop (``workers=0``): the same bytes in the same files, the same skips in the same order, errors of the
reader, the engine and the writer raised with the same files left behind, and reads that stay a bounded
distance ahead of the inference."""

from __future__ import annotations

import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.deploy import image_files as F
from pipeline.deploy.segmenter import load_segmenter
from pipeline.runtime.errors import InputError
from pipeline.deploy.image_files import segment_images
from tests.builders.deploy import make_checkpoint

RES = 32


@pytest.fixture(autouse=True)
def quiet(monkeypatch):
    monkeypatch.setenv("GEODISTILL_QUIET", "1")


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory) -> Path:
    return make_checkpoint(tmp_path_factory.mktemp("ckpt") / "ckpt")


def name(i: int) -> str:
    return f"im{i:02d}.{'jpg' if i % 3 == 1 else 'png'}"


def write_inputs(folder: Path, n: int = 11, bad: tuple[int, ...] = (4,)) -> list[Path]:
    """``n`` images of different sizes and formats (blobs on noise), corrupt files at positions ``bad``."""
    rng = np.random.default_rng(3)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(n):
        p = folder / name(i)
        if i in bad:
            p.write_bytes(b"\x89PNG\r\n\x1a\n not really a png")
        else:
            h, w = int(rng.integers(20, 70)), int(rng.integers(20, 70))
            yy, xx = np.mgrid[0:h, 0:w]
            blob = (((yy - h / 2) / (h / 3)) ** 2 + ((xx - w / 2) / (w / 4)) ** 2 < 1)[..., None]
            img = np.where(blob, 200, 30) + rng.integers(0, 40, (h, w, 3))
            cv2.imwrite(str(p), img.astype(np.uint8))
        paths.append(p)
    return paths


def outputs(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def run(ckpt, files, out: Path, workers: int, on_skip=None, batch_size: int = 3):
    seg = load_segmenter(ckpt, "torch", "cpu")
    stems = F.plan_outputs(files[0].parent, files, out, True, suffixes=F.output_suffixes(True, True))
    return F.segment_files(seg, files, stems, tau=0.5, resolution=RES, batch_size=batch_size, save_prob=True,
                           overlay=True, on_skip=on_skip, workers=workers)


def test_overlapped_segment_writes_the_serial_loops_bytes_and_skipped_csv(ckpt, tmp_path):
    inputs = tmp_path / "in"
    files = write_inputs(inputs, bad=(4, 9))
    results = {}
    for workers in (0, 1, 3):
        out = tmp_path / f"out{workers}"
        results[workers] = segment_images(ckpt, inputs, out, tau=0.5, resolution=RES, batch_size=3, save_prob=True,
                                          overlay=True, device="cpu", skip_bad=True, workers=workers,
                                          echo=lambda line: None)
    serial = outputs(tmp_path / "out0")
    assert len([k for k in serial if k.endswith(".mask.png")]) == len(files) - 2
    assert sum(k.endswith(".prob.png") for k in serial) == len(files) - 2 and "skipped.csv" in serial
    # the probability maps are not constant (a trivial model would make the comparison empty)
    probs = [cv2.imdecode(np.frombuffer(v, np.uint8), cv2.IMREAD_UNCHANGED) for k, v in serial.items()
             if k.endswith(".prob.png")]
    assert max(int(p.max()) - int(p.min()) for p in probs) > 0
    for workers in (1, 3):
        assert outputs(tmp_path / f"out{workers}") == serial, workers  # every byte; segment.json names no run
        assert results[workers].skipped == results[0].skipped
        assert [p.name for p in results[workers].written] == [p.name for p in results[0].written]
    assert [Path(p).name for p, _ in results[0].skipped] == [name(4), name(9)]


def test_a_bad_file_without_skip_bad_stops_both_loops_with_the_same_files_written(ckpt, tmp_path, monkeypatch):
    files = write_inputs(tmp_path / "in", n=12, bad=(7,))
    real_write = F.write_png

    def slow_write(path, array):  # the writer lags behind the inference: the stop must wait for it
        threading.Event().wait(0.02)
        real_write(path, array)

    monkeypatch.setattr(F, "write_png", slow_write)

    def refuse(path, reason, error):
        raise InputError(f"{path}: {reason} (pass --skip-bad to leave it out)")

    left = {}
    for workers in (0, 2):
        out = tmp_path / f"out{workers}"
        with pytest.raises(InputError, match=name(7)):
            run(ckpt, files, out, workers, on_skip=refuse)
        left[workers] = outputs(out)
    # batches of 3: the first two batches (im00..im05) are written, the third stops at im07
    assert sorted(k for k in left[0] if k.endswith(".mask.png")) == [f"{name(i)}.mask.png" for i in range(6)]
    assert left[2] == left[0]


def test_errors_of_the_writer_and_the_reader_propagate_after_the_same_outputs(ckpt, tmp_path, monkeypatch):
    files = write_inputs(tmp_path / "in", n=10, bad=())
    real_write, real_read = F.write_png, F.read_rgb

    def failing_write(path, array):
        if path.name.startswith("im05"):
            raise InputError(f"{path}: cannot write (disk full)")
        real_write(path, array)

    monkeypatch.setattr(F, "write_png", failing_write)
    left = {}
    for workers in (0, 2):
        with pytest.raises(InputError, match="disk full"):
            run(ckpt, files, tmp_path / f"w{workers}", workers)
        left[workers] = outputs(tmp_path / f"w{workers}")
    assert len([k for k in left[0] if k.endswith(".mask.png")]) == 5 and left[2] == left[0]
    monkeypatch.setattr(F, "write_png", real_write)

    def failing_read(path, **options):
        if Path(path).name.startswith("im08"):
            raise RuntimeError("decoder crashed")
        return real_read(path, **options)

    monkeypatch.setattr(F, "read_rgb", failing_read)
    for workers in (0, 2):
        with pytest.raises(RuntimeError, match="decoder crashed"):
            run(ckpt, files, tmp_path / f"r{workers}", workers)
        left[workers] = outputs(tmp_path / f"r{workers}")
    assert len([k for k in left[0] if k.endswith(".mask.png")]) == 6 and left[2] == left[0]


class CountingSegmenter:
    """A fake engine: P = 0.5 everywhere; records how many images were read when each batch ran.  Frames
    are read as a Segmenter's defaults read them (bit depth from the file, squashed to a square)."""

    bit_depth = "auto"
    letterbox = False

    def __init__(self, loads: list):
        self.loads = loads
        self.seen = 0
        self.ahead: list[int] = []

    def predict_probs(self, images, batch_size=8):
        self.seen += len(images)
        self.ahead.append(len(self.loads) - self.seen)
        threading.Event().wait(0.01)  # an engine takes time: the readers run ahead meanwhile
        return np.full(images.shape[:3], 0.5, np.float32)


def test_reads_stay_a_bounded_distance_ahead_and_workers_are_checked(tmp_path, monkeypatch):
    files = write_inputs(tmp_path / "in", n=40, bad=())
    loads: list = []
    real_load = F._load

    def counting_load(*a):
        loads.append(a[0])
        return real_load(*a)

    monkeypatch.setattr(F, "_load", counting_load)
    seg = CountingSegmenter(loads)
    stems = F.plan_outputs(tmp_path / "in", files, tmp_path / "out", True)
    result = F.segment_files(seg, files, stems, tau=0.5, resolution=RES, batch_size=4, workers=2)
    assert len(result.written) == 40 and len(loads) == 40
    # at most the next two batches are read ahead of the one running: memory does not grow with the folder
    assert max(seg.ahead) <= 2 * 4 and max(seg.ahead) > 0
    with pytest.raises(InputError, match="workers=-1"):
        F.segment_files(seg, files, stems, tau=0.5, resolution=RES, workers=-1)
