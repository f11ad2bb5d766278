"""A distill report without masks shows what can be shown (the students beside their pseudo-labels for
the lowest- and highest-gate images, the gate distribution, the training loss), and a distill project
is a git repository whose `dvc repro` prints no "Use `dvc push`" line."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from pipeline.artifacts.lineage import make_meta
from pipeline.artifacts.store import open_artifact, write_zarr
from pipeline.report import figures as F
from tests.builders.evaluation import build_tiny_artifacts, invoke, write_params


@pytest.fixture(scope="module")
def no_mask_art(tmp_path_factory) -> Path:
    """Tiny artifacts in which no image has a reference mask (a distill project without --val-masks),
    with the calibrate stage's fixed thresholds."""
    from stages.calibrate import main as calibrate

    root = tmp_path_factory.mktemp("nomask")
    art = build_tiny_artifacts(root / "artifacts", seeds=(1,))
    ref = open_artifact(art / "reference.zarr")
    masks, ids = ref.numpy("mask"), list(ref.attrs["image_ids"])
    write_zarr(art / "reference.zarr", {"mask": np.zeros_like(masks), "has_mask": np.zeros(len(ids), bool)},
               make_meta("reference", "fixture", "test", {}, []), {"image_ids": ids})
    params = write_params(root / "params.yaml")
    res = invoke(calibrate, ["--params", str(params), "--artifacts", str(art), "--checkpoints",
                             str(art / "checkpoints"), "--out", str(art / "thresholds.parquet")])
    assert res.exit_code == 0, res.output
    return art


def test_gate_extremes_lowest_then_highest():
    from pipeline.report.build import gate_extremes

    g = np.array([0.5, 0.0, 0.9, 0.0, 1.0, 0.3])
    assert gate_extremes(g, 4).tolist() == [1, 3, 4, 2]      # two lowest (ties in order), two highest
    assert gate_extremes(g, 1).tolist() == [1, 4]            # at least one of each end
    assert gate_extremes(np.array([0.2]), 4).tolist() == [0]  # each image once


def test_report_without_masks_shows_students_gates_and_loss(no_mask_art):
    from pipeline.report.build import NOT_COMPUTED, build_report
    from pipeline.report.document import Figure, Text, render_markdown

    report, _, inp = build_report(no_mask_art, {"qualitative_images": 2, "pseudo_target_images": 1})
    assert inp.no_masks
    by_title = {s.title: s for s in report.sections}
    figures = {b.key: b for b in report.figures()}
    # the qualitative section is no longer "Not computed": the students beside the pseudo-labels
    qual = by_title["Qualitative results"]
    assert not any(isinstance(b, Text) and NOT_COMPUTED in b.text for b in qual.blocks)
    fig = figures["fig:student-vs-pseudo-labels"]
    assert isinstance(fig, Figure) and fig.png.startswith(b"\x89PNG") and "not a true mask" in fig.caption
    # the gate distribution, its counts from gates.parquet's training rows
    gates = open_artifact(no_mask_art / "gates.parquet").df
    g = gates.loc[gates["split"] == "train", "g"].to_numpy(float)
    teacher = by_title["Multi-prompt teacher and reliability gate"]
    words = " ".join(b.text for b in teacher.blocks if isinstance(b, Text))
    assert f"over the {g.size} training images" in words and f"{int((g == 0).sum())} (" in words
    assert "fig:gate-distribution" in figures and "fig:training-loss" in figures
    md = render_markdown(report)
    assert "student_vs_pseudo_labels.png" in md and "gate_distribution.png" in md
    # what needs masks still says so (the results), and no accuracy is claimed
    assert "Not computed: no validation or test masks" in md and "agreement, not accuracy" in md


def test_pseudo_label_panel_rows_are_the_gate_extremes(no_mask_art, monkeypatch):
    """The panel's rows are the lowest- then the highest-gate training images, and each student tile's
    caption is its IoU against that image's pseudo-label."""
    from pipeline.report import build

    rows_seen = []
    real = F.qualitative_row
    monkeypatch.setattr(F, "qualitative_row", lambda *a, **k: rows_seen.append((a, k)) or real(*a, **k))
    inp = build.load_inputs(no_mask_art)
    blocks = build.pseudo_label_panels(inp, 2, "cpu")
    assert [type(b).__name__ for b in blocks] == ["Figure"]
    gates = inp.get("gates").df
    train = gates[gates["split"] == "train"].sort_values("g", kind="mergesort")
    titles = [a[4] for a, _ in rows_seen]
    assert [t.split()[1] for t in titles] == [f"g={train['g'].iloc[0]:.2f}", f"g={train['g'].iloc[-1]:.2f}"]
    assert all(k["reference"][0] == "pseudo-label M" for _, k in rows_seen)
    image, voted, preds, scores = rows_seen[0][0][:4]
    assert set(preds) == {"Plain Student", "GeoDistill-Refine"}
    for name, pred in preds.items():
        inter, union = (pred & voted).sum(), (pred | voted).sum()
        assert scores[name] == f"IoU vs M {(inter / union if union else 1.0):.2f}"


def test_histogram_counts_bins():
    fig = F.histogram([0.0, 0.0, 0.12, 0.97], np.linspace(0, 1, 21), "t", "g", "n")
    heights = [p.get_height() for p in fig.axes[0].patches]
    assert len(heights) == 20 and heights[0] == 2 and heights[2] == 1 and heights[-1] == 1 and sum(heights) == 4
    assert F.png_bytes(fig) == F.png_bytes(F.histogram([0.0, 0.0, 0.12, 0.97], np.linspace(0, 1, 21), "t", "g", "n"))


def _git(project: Path, *args) -> str:
    return subprocess.run(["git", "-C", str(project), *args], capture_output=True, text=True, check=True).stdout


@pytest.mark.skipif(shutil.which("git") is None, reason="git is not installed")
def test_distill_project_is_a_git_repository_and_repro_prints_no_dvc_push(tmp_path, capfd):
    """A new project is a git repository with one commit of distill's files (so `dvc exp` can start),
    listed in distill.json; `dvc repro` there prints neither DVC's "dvc push" line nor `git add` hints."""
    import pipeline
    from pipeline.orchestration.standalone import DVC_PUSH_HINT, run_project
    from tests.builders.teacher import make_image_folder

    images, _ = make_image_folder(tmp_path / "data", n=3, masks=False)
    out = pipeline.distill(images, out=tmp_path / "run", backend="imported", imported_dir=tmp_path / "imp", run=False)
    project = out["deploy"].parents[1]
    assert _git(project, "log", "--format=%an|%s").strip() == "geodistill distill|geodistill distill: the project"
    committed = set(_git(project, "ls-files").split())
    assert {"params.yaml", "dvc.yaml", "distill.json", ".gitignore", ".dvc/config"} <= committed
    assert "/.cache/" in (project / ".gitignore").read_text()
    assert "no_scm" not in (project / ".dvc" / "config").read_text()
    record = json.loads((project / "distill.json").read_text())
    assert {".git", ".gitignore"} <= set(record["outputs"])
    # dvc repro through distill's relay, with a one-stage DAG standing in for the real one
    (project / "dvc.yaml").write_text("stages:\n  hello:\n    cmd: python -c \"open('hello.txt','w').write('hi')\"\n"
                                      "    outs: [hello.txt]\n")
    capfd.readouterr()
    run_project(project, "cpu")
    seen = "".join(capfd.readouterr())
    assert "Running stage 'hello'" in seen and (project / "hello.txt").read_text() == "hi"
    assert DVC_PUSH_HINT not in seen and "dvc push" not in seen and "git add" not in seen
    assert "hello.txt" in (project / ".gitignore").read_text()  # DVC keeps its output out of git


def test_distill_project_without_git_is_no_scm(tmp_path, monkeypatch):
    import pipeline
    from pipeline.orchestration import standalone
    from tests.builders.teacher import make_image_folder

    images, _ = make_image_folder(tmp_path / "data", n=3, masks=False)
    real = shutil.which
    monkeypatch.setattr(standalone.shutil, "which", lambda name, *a, **k: None if name == "git" else real(name, *a, **k))
    pipeline.distill(images, out=tmp_path / "run", backend="imported", imported_dir=tmp_path / "imp", run=False)
    assert not (tmp_path / "run" / ".git").exists() and not (tmp_path / "run" / ".gitignore").exists()
    assert "no_scm = True" in (tmp_path / "run" / ".dvc" / "config").read_text()
    assert ".git" not in json.loads((tmp_path / "run" / "distill.json").read_text())["outputs"]
