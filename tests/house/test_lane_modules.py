"""The modules the lane ran in a pytest process of its own (tests/conftest.py, ``LANE_MODULES``): all their
selected tests passed there.  Without this test in the session (e.g. ``pytest tests/training``) they run
in this process as usual."""

from __future__ import annotations


def test_the_modules_on_the_lane_pass(lane_modules):
    nodeids, proc = lane_modules
    tail = proc.stdout[-6000:] + proc.stderr[-2000:]
    assert proc.returncode == 0, tail
    summary = proc.stdout.strip().splitlines()[-1]
    counts = {word: int(n) for n, word in
              (part.strip().split()[:2] for part in summary.split(" in ")[0].strip("= ").split(","))}
    assert counts.get("passed", 0) + counts.get("skipped", 0) == len(nodeids), summary
    assert not counts.get("failed") and not counts.get("error") and not counts.get("errors"), summary
