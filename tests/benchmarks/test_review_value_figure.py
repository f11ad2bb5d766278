"""The review-value benchmark's summary from saved runs (one --out file per seed) and its curve figure."""

from __future__ import annotations

import json

import numpy as np

from benchmarks import review_value as rv


def _runs(seed: int, rng) -> list[dict]:
    groups = ["a"] * 4 + ["b"] * 4
    out = [{"selection": "none", "k": 0, "seed": seed, "draw": 0}]
    out += [{"selection": how, "k": k, "seed": seed, "draw": 0} for k in (2, 4) for how in rv.SELECTIONS]
    for r in out:  # the ranking gains most, random least
        lift = {"none": 0.0, rv.DEFAULT_RANKING: 0.04, "gate": 0.03, "random": 0.01}[r["selection"]] * r["k"]
        ious = np.clip(0.5 + lift + rng.normal(0, 0.005, len(groups)), 0, 1)
        r.update(iou=float(ious.mean()), ious=ious.tolist(), groups=groups)
    return out


def test_runs_of_several_files_summarize_into_the_table_and_the_curve(tmp_path, capsys):
    rng = np.random.default_rng(0)
    files = []
    for seed in (1, 2, 3):
        files.append(tmp_path / f"seed{seed}.json")
        files[-1].write_text(json.dumps({"runs": _runs(seed, rng)}))
    png = tmp_path / "curve.png"
    rows = rv.main(["--workdir", str(tmp_path / "none"), "--runs", *map(str, files), "--figure", str(png), "--out", str(tmp_path / "all.json")])
    by = {(r["selection"], r["k"]): r for r in rows}
    assert set(by) == {("none", 0), *((s, k) for s in rv.SELECTIONS for k in (2, 4))}
    top = by[(rv.DEFAULT_RANKING, 4)]
    assert top["gain"] > by[("random", 4)]["gain"] > 0 and top["vs_random_low"] > 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(json.loads((tmp_path / "all.json").read_text())["runs"]) == 3 * len(_runs(0, rng))
    assert "by construction" in capsys.readouterr().out
