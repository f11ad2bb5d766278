"""Report stage end to end (Markdown + one self-contained HTML page), missing inputs, tables, figures,
and the page rendered in headless Chromium."""

from __future__ import annotations

import base64
import re
import shutil
import subprocess
from xml.etree import ElementTree
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

from pipeline.artifacts.lineage import make_meta
from pipeline.artifacts.store import open_artifact, write_parquet
from pipeline.report import figures as F
from pipeline.report import tables as T
from tests.builders.evaluation import build_tiny_artifacts, invoke, run_result_stages, write_params

CHROMIUM = shutil.which("chromium") or ("/usr/bin/chromium" if Path("/usr/bin/chromium").exists() else None)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """Tiny artifacts + calibrate/evaluate/analyze_teacher outputs + efficiency table + the report."""
    from stages.report import main as report

    root = tmp_path_factory.mktemp("report")
    art = build_tiny_artifacts(root / "artifacts")
    params = write_params(root / "params.yaml")
    common = ["--params", str(params), "--artifacts", str(art)]
    run_result_stages(root, art, params)
    eff = pd.DataFrame({"variant": ["fp32_eager", "bf16_channels_last"], "params": [263_000, 263_000],
                        "gflops": [18.2, 18.2], "latency_ms": [500.0, 110.0], "throughput": [2.0, 9.1],
                        "peak_mb": [100.0, 80.0], "iou_delta": [0.0, -0.001]})
    write_parquet(art / "efficiency.parquet", eff, make_meta("efficiency", "fixture", "test", {}, []))
    out = root / "reports" / "demo"
    res = invoke(report, common + ["--out", str(out)])
    assert res.exit_code == 0, res.output
    return root, art, params, out


def test_report_files_and_tables(built):
    root, art, params, out = built
    for f in ("report.md", "report.html", "meta.json", "figures/qualitative.png", "figures/pseudo_targets.png",
              "figures/threshold_curves.png", "figures/training_curves.png", "figures/reliability.png",
              "figures/area_vs_tau.png", "figures/training_curves_calibrated.png", "plots/training_curves.csv",
              "plots/area_curve.csv",
              "plots/threshold_curve.csv"):
        assert (out / f).is_file(), f
    assert open_artifact(out, "report").meta.stage == "report"
    md, html = (out / "report.md").read_text(), (out / "report.html").read_text()
    for key in ("tab:spacesense-results", "tab:teacher-prompt-quality", "tab:teacher-domain-quality",
                "tab:gate-groups", "tab:efficiency", "tab:thresholds"):
        assert f'<table data-key="{key}">' in html, key
    # every results table exists at the calibrated and at the fixed threshold
    assert "(validation-calibrated tau)" in md and "(fixed tau = 0.5)" in md
    # honesty: synthetic data and a simulated teacher are named as such
    assert "SYNTHETIC" in md and md.count("SIMULATOR") >= 3
    # numbers in the table are the summary's
    s = open_artifact(art / "summary.parquet").df
    r = s[(s.group == "KCP") & (s.method == "geodistill") & (s.threshold_mode == "calibrated")].iloc[0]
    assert f"{r.iou_mean:.4f} ± {r.iou_std:.4f}" in md
    assert f"{r.gain_iou:+.4f} [{r.gain_iou_lo:.4f}, {r.gain_iou_hi:.4f}]" in md
    # plots for DVC
    tc = pd.read_csv(out / "plots" / "training_curves.csv")
    assert {"epoch", "val_iou", "method", "seed"} <= set(tc.columns) and len(tc) == 4 * 3
    th = pd.read_csv(out / "plots" / "threshold_curve.csv")
    assert list(th.columns) == ["tau", "val_iou", "method", "seed"] and len(th) == 4 * 19


def test_html_is_one_self_contained_page(built):
    _, _, _, out = built
    html = (out / "report.html").read_text()
    assert html.count("<table") == len(re.findall(r"^\|---", (out / "report.md").read_text(), re.M))
    srcs = re.findall(r'src="([^"]+)"', html)
    # qualitative, pseudo-targets, threshold curves, reliability, area vs tau, training curves (at 0.5 and at
    # the per-epoch calibrated tau)
    assert len(srcs) == len(list((out / "figures").glob("*.png"))) == 7
    assert all(s.startswith("data:image/png;base64,") for s in srcs)
    # inline images decode to the PNGs written under figures/
    png = base64.b64decode(srcs[0].split(",", 1)[1])
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None and img.shape[0] > 50
    # nothing external: no links, scripts or stylesheets to fetch
    assert not re.search(r'(href|src)="(https?:|//|/)', html) and "<script" not in html and "<link" not in html


def test_report_writes_svg_charts(built, tmp_path):
    """Every figure is also written as SVG beside its PNG: the SVG parses as XML and each chart holds
    one series per method of the runs it draws; a second report run writes the same bytes."""
    from stages.report import main as report

    root, art, params, out = built
    charts = ("threshold_curves", "training_curves", "training_curves_calibrated", "reliability", "area_vs_tau")
    panels = ("qualitative", "pseudo_targets")
    assert sorted(p.stem for p in (out / "figures").glob("*.svg")) == sorted(charts + panels)
    for name in panels:
        tree = ElementTree.parse(out / "figures" / f"{name}.svg")
        assert list(tree.iter("{http://www.w3.org/2000/svg}image")), name      # the tiles, as images
        assert f"figures/{name}.svg" in (out / "report.md").read_text()
    methods = set(open_artifact(art / "thresholds.parquet").df["method"])
    for name in charts:
        tree = ElementTree.parse(out / "figures" / f"{name}.svg")
        ids = [g.get("id") for g in tree.iter("{http://www.w3.org/2000/svg}g")]
        series = [i.removeprefix("series-") for i in ids if i and i.startswith("series-")]
        assert sorted(m for m in series if not m.isdigit()) == sorted(methods), name   # one per method
        assert f"figures/{name}.svg" in (out / "report.md").read_text()
    # the two meanings of "area ratio" have two names
    md = (out / "report.md").read_text()
    assert "Foreground fraction" in md and "Pred./ref. area at tau" in md and "Area ratio" not in md
    again = tmp_path / "again"
    res = invoke(report, ["--params", str(params), "--artifacts", str(art), "--out", str(again)])
    assert res.exit_code == 0, res.output
    for name in charts + panels:
        for ext in ("svg", "png"):
            f = f"figures/{name}.{ext}"
            assert (again / f).read_bytes() == (out / f).read_bytes(), f


def test_report_with_missing_tables_says_so(tmp_path, built):
    """Only the data artifacts exist: every other section names the missing artifact and its stage."""
    from stages.report import main as report

    root, art, params, _ = built
    part = tmp_path / "artifacts"
    part.mkdir()
    for f in ("manifest.parquet", "images.zarr", "reference.zarr"):
        src = art / f
        (shutil.copytree if src.is_dir() else shutil.copy)(src, part / f)
    out = tmp_path / "rep"
    res = invoke(report, ["--params", str(params), "--artifacts", str(part), "--out", str(out)])
    assert res.exit_code == 0, res.output
    md = (out / "report.md").read_text()
    for f, stage in (("summary.parquet", "evaluate"), ("thresholds.parquet", "calibrate"),
                     ("teacher_metrics.parquet", "analyze_teacher"), ("efficiency.parquet", "benchmark")):
        assert f"**Missing: `{f}`.**" in md and f"`{stage}` stage" in md
    assert "Missing: training logs" in md
    assert (out / "report.html").read_text().count('class="missing"') >= 5
    # an empty artifacts directory still gives a (mostly "missing") report
    res = invoke(report, ["--params", str(params), "--artifacts", str(tmp_path / "none"), "--out", str(tmp_path / "r2")])
    assert res.exit_code == 0 and "Missing: `manifest.parquet`" in (tmp_path / "r2" / "report.md").read_text()


def test_ablation_tables_from_method_definitions():
    rows = []
    for method, base in (("plain", 0.5), ("geodistill", 0.6), ("sdf_gated", 0.58), ("no_gate", 0.55),
                         ("full_scratch_10", 0.4)):
        for i in range(4):
            rows.append(dict(group="KCP", seed=42, threshold_mode="calibrated", method=method, image_id=i,
                             iou=base + 0.01 * i, bf1=base + 0.1))
    means = T.ablation_means(pd.DataFrame(rows), "KCP", 42, "calibrated")
    assert means.loc["geodistill", "iou"] == pytest.approx(0.615)
    epochs = {"plain": 20, "geodistill": 10, "sdf_gated": 10, "no_gate": 10, "full_scratch_10": 10}
    warm = T.warm_start_table(means, epochs, "KCP", 42, "calibrated")
    got = {r[0]: r[1:4] for r in warm.rows}
    assert got["Plain Student"] == ["20", "--", "20"]
    assert got["GeoDistill-Refine"] == ["20", "10", "30"]          # warm start: Stage I from plain
    assert got["Full geometry, from scratch (10)"] == ["--", "10", "10"]
    comp = {r[0]: r[1:5] for r in T.component_table(means, "KCP", 42, "calibrated").rows}
    assert comp["Stage I -> gated SDF"] == ["✓", "", "", "✓"]
    assert comp["SDF + skeleton + area, no gate"] == ["✓", "✓", "✓", ""]
    assert comp["GeoDistill-Refine"] == ["✓", "✓", "✓", "✓"]
    # no ablation run -> no ablation table
    assert T.warm_start_table(means.loc[["plain", "geodistill"]], epochs, "KCP", 42, "calibrated") is None


def test_formatting_helpers():
    assert T.fmt_pm(0.5, np.nan) == "0.5000"
    assert T.fmt_pm(0.5, 0.01) == "0.5000 ± 0.0100"
    assert T.fmt_ci(0.0576, 0.0351, 0.0813) == "+0.0576 [0.0351, 0.0813]"
    assert T.fmt(np.nan) == "--"
    assert T.main_methods(["geodistill", "no_gate", "plain", "gabi"]) == ["plain", "gabi", "geodistill"]


def test_error_overlay_colours():
    img = np.zeros((8, 8, 3), np.uint8)
    gt = np.zeros((8, 8), bool)
    pred = np.zeros((8, 8), bool)
    gt[2:6, 2:6] = True
    pred[2:6, 4:8] = True
    out = F.error_overlay(img, pred, gt, 8, contour=False)
    tp, fp, fn = out[3, 4], out[3, 7], out[3, 2]
    assert tp[1] > tp[0] and tp[1] > tp[2]        # green
    assert fp[0] > fp[1] and fp[0] > fp[2]        # red
    assert fn[2] > fn[0] and fn[2] > fn[1]        # blue
    assert (out[0, 0] == 0).all()                 # true negative untouched
    with_contour = F.error_overlay(img, pred, gt, 8)
    assert tuple(with_contour[2, 2]) == F.GT_CONTOUR


def test_image_grid_captions_each_tile_with_matplotlib():
    """Image panels are matplotlib figures: every tile an image axis with its caption as the axis
    title, in rows; the tile's pixels are drawn unchanged; two renders give the same bytes."""
    img = np.zeros((16, 16, 3), np.uint8)
    gt = np.zeros((16, 16), bool)
    gt[4:12, 4:12] = True
    rows = [F.qualitative_row(img, gt, {"A": gt, "B": ~gt}, {"A": "IoU 1.000", "B": "IoU 0.000"}, f"({c})",
                              size=16) for c in "ab"]
    fig = F.image_grid(rows)
    titles = [ax.get_title(loc="left") for ax in fig.axes]
    assert titles == [
        "(a)", "ground truth\n(yellow contour)", "A\nIoU 1.000", "B\nIoU 0.000",
        "(b)", "ground truth\n(yellow contour)", "A\nIoU 1.000", "B\nIoU 0.000"]
    shown = fig.axes[2].get_images()[0].get_array()
    assert np.array_equal(np.asarray(shown), rows[0][2][0])                   # the overlay, pixel for pixel
    assert F.png_bytes(fig) == F.png_bytes(F.image_grid(rows))
    assert F.svg_bytes(fig) == F.svg_bytes(F.image_grid(rows))
    ragged = F.image_grid([rows[0], rows[1][:2]])                                # a short row: empty cells
    assert sum(bool(ax.get_images()) for ax in ragged.axes) == 6


def test_line_plot_draws_series():
    """Each series is one line in its own colour; the chart encodes to PNG and to SVG that parses."""
    from matplotlib.colors import to_hex

    fig = F.line_plot([{"x": [0, 1, 2], "y": [0.1, 0.5, 0.3], "label": "a", "marker": 1.0},
                       {"x": [0, 2], "y": [0.2, 0.2], "label": "b", "color": (0, 200, 0)}], "t", "x", "y")
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    assert isinstance(fig.canvas, FigureCanvasAgg)                       # Agg, no pyplot, no GUI backend
    lines = [ln for ln in fig.axes[0].get_lines() if ln.get_gid()]
    assert [ln.get_label() for ln in lines] == ["a", "b"]
    assert to_hex(lines[0].get_color()) == to_hex(np.divide(F.PALETTE[0], 255))
    assert to_hex(lines[1].get_color()) == "#00c800"
    png = F.png_bytes(fig)
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    blended = 0.85 * np.array((0, 200, 0)[::-1]) + 0.15 * 255            # alpha 0.85 over white (BGR)
    assert (np.abs(img - blended).max(axis=2) < 12).sum() > 100            # b's line is drawn
    root = ElementTree.fromstring(F.svg_bytes(fig))
    ids = [g.get("id") for g in root.iter("{http://www.w3.org/2000/svg}g")]
    assert ids.count("series-0") == 1 and ids.count("series-1") == 1


def test_charts_are_byte_identical(monkeypatch):
    """Two renders of the same chart give the same PNG and SVG bytes (no date, no random ids), with
    and without SOURCE_DATE_EPOCH."""
    series = [{"x": np.linspace(0, 1, 11), "y": np.linspace(0, 1, 11) ** k, "label": m, **F.method_style(m)}
              for k, m in enumerate(("plain", "geodistill", "continuation"), 1)]
    renders = []
    for epoch in (None, "1700000000", "1800000000"):
        if epoch is None:
            monkeypatch.delenv("SOURCE_DATE_EPOCH", raising=False)
        else:
            monkeypatch.setenv("SOURCE_DATE_EPOCH", epoch)
        fig = F.line_plot(series, "t", "x", "y")
        renders.append((F.png_bytes(fig), F.svg_bytes(fig)))
    assert renders[0] == renders[1] == renders[2]
    assert b"<dc:date>" not in renders[0][1]


#: the screenshot's height: tall enough to reach the first figure below the results tables and their notes
SHOT_HEIGHT = 8000


@pytest.mark.skipif(CHROMIUM is None, reason="Chromium not installed (apt-get install chromium) -- "
                                             "the headless-browser check of report.html is skipped")
def test_report_renders_in_headless_chromium(built, tmp_path):
    _, _, _, out = built
    flags = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             "--disable-dev-shm-usage"]
    url = (out / "report.html").resolve().as_uri()
    dom = subprocess.run(flags + [f"--user-data-dir={tmp_path / 'u1'}", "--dump-dom", url],
                         capture_output=True, text=True, timeout=120)
    assert dom.returncode == 0, dom.stderr[-2000:]
    html = dom.stdout
    assert "GeoDistill-Refine report" in html
    assert len(re.findall(r'<table data-key="tab:spacesense-results"', html)) == 2
    assert 'data-key="tab:gate-groups"' in html and 'data-key="tab:efficiency"' in html
    assert len(re.findall(r'<img [^>]*src="data:image/png;base64,', html)) == 7
    shot = tmp_path / "shot.png"
    res = subprocess.run(flags + [f"--user-data-dir={tmp_path / 'u2'}", f"--screenshot={shot}",
                                  f"--window-size=1200,{SHOT_HEIGHT}", url], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and shot.exists(), res.stderr[-2000:]
    img = cv2.imread(str(shot))
    assert img is not None and img.shape[:2] == (SHOT_HEIGHT, 1200)
    # the page painted content: dark text pixels and coloured figure pixels, not a blank page
    assert (img.min(axis=2) < 60).mean() > 0.002
    hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)
    assert (hsv[..., 1] > 120).sum() > 500


def test_efficiency_table_marks_untimed_and_emulated_variants():
    """Issue 18 item 5: an untimed (pathologically slow) variant shows the reason, not a latency."""
    from pipeline.report.tables import efficiency_table

    eff = pd.DataFrame({"variant": ["fp32_eager_nchw", "bf16_eager", "int8_onnx"], "params": [259000] * 3,
                        "gflops": [2.0] * 3, "latency_ms": [10.0, 5000.0, 4.0], "throughput": [100.0, 0.2, 250.0],
                        "peak_mb": [50.0] * 3, "timed": [True, False, True],
                        "remark": ["", "not timed: probe 5000 ms = 500x the fp32_eager_nchw probe", "bf16 emulated"]})
    rows = {r[0]: r for r in efficiency_table(eff).rows}
    assert rows["fp32_eager_nchw"][3] == "10.00"
    slow = rows["bf16_eager"]
    assert slow[3].startswith("not timed: probe 5000 ms") and slow[4] == "--" and "5000.00" not in slow
    assert "int8_onnx (bf16 emulated)" in rows and rows["int8_onnx (bf16 emulated)"][3] == "4.00"


def test_report_records_its_environment(built):
    """The Environment section and environment.json: this machine's software and CPU, and one record per
    training run (the fixture's checkpoints predate extra.runtime, so the table says 'not recorded')."""
    import json

    from pipeline.evaluation.inference import iter_runs

    root, art, params, out = built
    env = json.loads((out / "environment.json").read_text())
    assert env["report"]["libraries"]["torch"] and env["report"]["cpu"]["logical_cpus"] >= 1
    assert env["report"]["lock"]["found"]
    assert {(r["method"], r["seed"]) for r in env["training_runs"]} == {(m, s) for m, s, _ in
                                                                        iter_runs(art / "checkpoints")}
    md = (out / "report.md").read_text()
    html = (out / "report.html").read_text()
    assert "## Environment" in md and 'data-key="tab:environment-training"' in html and "not recorded" in md
    assert f"| torch | {env['report']['libraries']['torch']} |" in md
    assert 'data-key="tab:environment-machine"' in html


def test_report_has_one_glossary_and_shows_no_internal_labels(built):
    """The glossary's terms (pipeline.report.glossary, written once) are the report's "Terms" section; no
    table, figure or equation label (tab:..., fig:..., eq:...) is in the text a reader sees."""
    from pipeline.report.glossary import TERMS

    _, _, _, out = built
    md, html = (out / "report.md").read_text(), (out / "report.html").read_text()
    assert md.count("## Terms used in this report") == 1
    terms = [t for t, _ in TERMS]
    assert len(set(terms)) == len(terms) and {"vote", "gate", "ceiling", "noise floor", "primary endpoint",
                                               "lockbox", "HJM"} <= set(terms)
    for term, meaning in TERMS:
        assert f"| {term} | {meaning} |" in md, term
        assert 1 <= meaning.count(".") <= 3, term                 # one or two plain sentences
    visible = re.sub(r"<[^>]+>", " ", re.sub(r"<(style|script)[^>]*>.*?</\1>", " ", html, flags=re.S))
    for text in (md, visible):
        assert not re.search(r"\b(tab|fig|eq):[a-z]", text), re.search(r"\b(tab|fig|eq):[a-z].{0,40}", text)


def test_the_interval_footnote_states_the_spacecraft_the_data_table_shows(built):
    """The split table's spacecraft per test group and the results footnote come from the same manifest
    (tiny data: KCP 3, CVI 2 -- not the "3 per group" of the design)."""
    _, art, _, out = built
    md = (out / "report.md").read_text()
    lines = md.splitlines()
    start = lines.index("**Images per split and group**")
    rows = [[c.strip() for c in ln.strip("|").split("|")] for ln in lines[start + 4:] if ln.startswith("|")]
    rows = rows[:next((i for i, r in enumerate(rows) if len(r) != 5), len(rows))]
    test = sorted({int(r[4]) for r in rows if r[1] == "test"})
    manifest = open_artifact(art / "manifest.parquet").df
    assert test == sorted(manifest[manifest.split == "test"].groupby("group")["spacecraft"].nunique()) == [2, 3]
    assert md.count("with 2-3 spacecraft per test group") >= 2 and "with 3 spacecraft per group" not in md


def test_efficiency_says_the_benchmark_was_skipped_on_purpose(tmp_path):
    """A distill project made with --no-benchmark (dvc.yaml without the benchmark stage) says so in the
    Efficiency section; with the stage, or outside a DVC project, it is the usual missing-input note."""
    from pipeline.orchestration.dag import render_dvc_yaml
    from pipeline.report.build import BENCHMARK_SKIPPED, efficiency_section, load_inputs
    from pipeline.report.document import Missing, Text
    from pipeline.orchestration.standalone import BENCHMARK_STAGE

    art = tmp_path / "artifacts"
    art.mkdir()
    assert isinstance(efficiency_section(load_inputs(art)).blocks[0], Missing)          # no dvc.yaml
    (tmp_path / "dvc.yaml").write_text(render_dvc_yaml(omit=(BENCHMARK_STAGE,)))
    block = efficiency_section(load_inputs(art)).blocks[0]
    assert isinstance(block, Text) and block.text == BENCHMARK_SKIPPED.format(stage=BENCHMARK_STAGE)
    assert "--no-benchmark" in block.text and "missing" not in block.text.lower()
    (tmp_path / "dvc.yaml").write_text(render_dvc_yaml())
    assert isinstance(efficiency_section(load_inputs(art)).blocks[0], Missing)


def test_panel_captions_wrap_instead_of_being_cut():
    """A caption line wider than the widest tile wraps (inside a word where it must): every character
    is in the figure, and the tile stays at most MAX_TILE_INCHES wide."""
    title = "(a) g=0.42 flight-7/camera_left/frame-000123-with-a-very-long-name"
    tile = np.zeros((8, 8, 3), np.uint8)
    lines = F.wrap_caption(title)
    assert "".join(lines).replace(" ", "") == title.replace(" ", "")
    assert len(lines) > 1 and all(F.caption_inches(x) <= F.MAX_TILE_INCHES for x in lines)
    fig = F.image_grid([[(tile, [title]), (tile, ["ground truth"])]])
    shown = [ax.get_title(loc="left") for ax in fig.axes]
    assert shown[0].replace("\n", "").replace(" ", "") == title.replace(" ", "")
    assert fig.get_size_inches()[0] <= 2 * F.MAX_TILE_INCHES + 0.2  # two tiles, their margins and the gap
