"""``label`` says what the teacher costs: measured seconds per image in its summary, and after the first
batch the projected total for the folder (serial; under Ray workers in tests/teachers/test_teacher_scale.py),
with ``-q`` too."""

from __future__ import annotations

import json
import re

from pipeline.labeling.run import TeacherClock, duration
from tests.builders.teacher import FAST, cli, make_image_folder


class FakeClock:
    def __init__(self):
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_clock_projects_from_the_first_batch_serially_and_under_workers():
    for workers, expect in ((0, "about 50.0 min serially"), (2, "about 25.0 min under 2 Ray workers")):
        lines, clock = [], FakeClock()
        tc = TeacherClock(lines.append, workers, clock=clock)
        assert tc.seconds_per_image is None          # nothing computed: nothing measured
        clock.now += 20.0
        tc(2, 300)                                   # first batch: 2 images in 20 s -> 10 s per image
        clock.now += 100.0
        tc(12, 300)                                  # later batches: no second projection
        assert len(lines) == 1 and expect in lines[0], lines
        assert "2 image(s) in 20.0 s (10.00 s per image)" in lines[0] and "300 image(s)" in lines[0]
        assert tc.seconds_per_image == 120.0 / 12


def test_duration_reads_as_a_wait():
    assert [duration(s) for s in (0.25, 42, 300, 7200, 3 * 86400)] == ["0.25 s", "42 s", "5.0 min", "2.0 h",
                                                                       "3.0 days"]


def test_label_prints_seconds_per_image_and_its_projection_with_q(tmp_path):
    images, masks = make_image_folder(tmp_path / "data", n=6)
    out = tmp_path / "out"
    args = ("label", images, "--out", out, "--backend", "simulated", "--reference-masks", masks, "--format", "png",
            "-q", *FAST, "--set", "teacher.batch_size=2")
    first = cli(*args)
    assert first.exit_code == 0, first.output
    projection = re.search(r"first batch: 2 image\(s\) in [\d.]+ s \(([\d.]+) s per image\); projected for the "
                           r"6 image\(s\) to label: about [\d.]+ \w+ serially", first.output)
    assert projection, first.output
    summary = [line for line in first.output.splitlines() if line.startswith("label: 6 images")]
    assert len(summary) == 1 and re.search(r"\(([\d.]+) s per image, measured on 6\)", summary[0]), first.output
    record = json.loads((out / "label.json").read_text())
    assert record["teacher_seconds_per_image"] > 0 and record["teacher_images_timed"] == 6
    again = cli(*args)                               # every answer cached: nothing to time or project
    assert again.exit_code == 0 and "first batch" not in again.output and "s per image" not in again.output
    assert json.loads((out / "label.json").read_text())["teacher_seconds_per_image"] is None


def test_label_summary_says_why_cpu_caches_miss_under_auto_bf16(tmp_path, tiny_sam3, monkeypatch):
    """On a CPU whose flags make ``auto`` bf16, label's summary says that fp32-cached answers are not reused and
    how to keep them; with ``teacher.dtype: fp32`` pinned it says nothing of the kind. The first-batch projection
    and the summary name the path (engine, dtype, device) either way."""
    from pipeline.runtime import device
    from pipeline.teachers import attention

    monkeypatch.setattr(device, "cpu_flags", lambda: frozenset({"avx2", "avx512_bf16"}))
    monkeypatch.setattr(device, "cpu_vendor", lambda: "AuthenticAMD")  # where auto is bf16 without AMX
    images, _ = make_image_folder(tmp_path / "data", n=2, masks=False)
    for dtype, said in (("auto", True), ("fp32", False)):
        res = cli("label", images, "--out", tmp_path / dtype, "--checkpoint", tiny_sam3, "--format", "png", "-q",
                  *FAST, "--set", f"teacher.dtype={dtype}")
        assert res.exit_code == 0, res.output
        summary = [line for line in res.output.splitlines() if line.startswith("label: 2 images")][0]
        assert ("teacher.dtype auto is bf16 on this CPU" in summary) == said, summary
        assert ("set teacher.engine: torch to keep them" in summary) == bool(said and attention.openvino_version())
        # the projection and the summary name the path the answers took
        engine = " + openvino attention" if said and attention.openvino_version() else ""  # auto: avx512_bf16
        path = re.escape(f"sam3 torch eager {'bf16' if said else 'fp32'}{engine} on cpu")
        assert re.search(rf"first batch: .* s per image on {path}\); projected", res.output), res.output
        assert re.search(rf"s per image on {path}, measured on 2\)", summary), summary
        assert json.loads((tmp_path / dtype / "label.json").read_text())["teacher_dtype"] == ("bf16" if said else "fp32")
