"""Smoke test of benchmarks.fit_limit on two fabricated memorisation outputs: the paired difference, its verdict
against the noise floor, and the figure."""

from __future__ import annotations

import json

import numpy as np


def _fake(tmp_path, stem: str, per_image: np.ndarray, epochs: int, sets: list[str]):
    run = {"method": "plain", "seed": 42, "commit": "x", "epochs_run": epochs, "low_res_epochs": 0,
           "steps_run": epochs * 34, "seconds": 1.0, "annotation_free": True,
           "summary": {"cal": {"final": {"iou_ref": [float(per_image.mean()), 0.0, 1.0], "agreement_with_vote": 0.5},
                               "peak": {"iou_ref": [0.7, 0.6, 0.8]}, "peak_epoch": epochs, "final_tau_cal": 0.5}}}
    doc = {"info": {"seed": 42, "sets": sets}, "vote": {"iou_ref_ci": [0.675, 0.63, 0.72]}, "runs": {"plain": run}}
    path = tmp_path / f"{stem}.json"
    path.write_text(json.dumps(doc))
    scores = tmp_path / "work" / stem / "runs" / "reduced-64-progressive" / "plain-s42" / "scores"
    scores.mkdir(parents=True)
    np.savez(scores / "final.npz", iou_ref_cal=per_image)
    return path


def test_fit_limit_pairs_runs_per_image(tmp_path):
    from benchmarks import fit_limit

    rng = np.random.default_rng(0)
    base = rng.uniform(0.3, 0.9, 270)
    one = _fake(tmp_path, "p1", base, 220, ["train.epochs_stage1=220"])
    two = _fake(tmp_path, "p2", base + 0.05, 440, ["train.epochs_stage1=440"])  # +0.05 on every image
    same = _fake(tmp_path, "p3", base + rng.normal(0, 0.01, 270), 220, ["train.channels=[36,72,144]"])
    fig = tmp_path / "fit.png"
    doc = fit_limit.main(["--run", f"1x={one}", "--run", f"2x={two}", "--run", f"wide={same}",
                          "--workdir-root", str(tmp_path / "work"), "--out", str(tmp_path / "out.json"),
                          "--figure", str(fig)])
    by = {c["label"]: c for c in doc["comparisons"]}
    assert by["2x"]["paired"][0] == 0.05 and by["2x"]["paired"][1] == by["2x"]["paired"][2] == 0.05
    assert by["2x"]["verdict"] == "gain"
    assert by["wide"]["verdict"] == "no difference detected" and abs(by["wide"]["paired"][0]) < 0.005
    assert [r["channels"] for r in doc["runs"]][-1] == "[36,72,144]"
    assert fig.stat().st_size > 1000 and json.loads((tmp_path / "out.json").read_text())["info"]["base"] == "1x"
    # a comparison's interval is its own: the same without the 2x run beside it
    alone = fit_limit.main(["--run", f"1x={one}", "--run", f"wide={same}", "--workdir-root", str(tmp_path / "work"),
                            "--out", str(tmp_path / "alone.json")])
    assert alone["comparisons"][0]["paired"] == by["wide"]["paired"]
