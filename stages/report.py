"""Stage report: the paper's tables and figures from the evaluation artifacts.

Writes ``<out>/report.md``, ``<out>/report.html`` (ONE self-contained page: figures inline as base64
PNG, no external resources), ``<out>/figures/*.png`` (and ``*.svg`` of every chart, for papers),
``<out>/environment.json`` (where the numbers were computed: this machine's software, torch build and
CPU, and each training run's precision, threads and device; pipeline.environment; not fingerprinted)
and the DVC plot tables
``<out>/plots/training_curves.csv`` (epoch, val_iou, ..., method, seed) and
``<out>/plots/threshold_curve.csv`` (tau, val_iou, method, seed) and ``<out>/plots/area_curve.csv``
(tau, area_ratio, method, seed: median predicted / reference foreground area on the validation split).
The controls and threshold-diagnostics section states in words, computed from the numbers, what they
show about the fixed-tau reversal (pipeline.report.analysis.fixed_tau_findings).  Inputs that do not exist (e.g.
efficiency.parquet before the benchmark ran) are reported as missing in the page, not fatal.
"""

from __future__ import annotations

from pathlib import Path

import click

from pipeline.artifacts import artifact_dir, write_json
from pipeline.catalog import ARTIFACTS_DIR, dvc_path
from pipeline.device import resolve_device
from pipeline.environment import collect
from pipeline.params import section
from pipeline.report.document import render_html, render_markdown
from pipeline.report.environment import environment_record
from stages._common import stage_command, stage_context



@stage_command("report")
@click.option("--artifacts", "art", default=ARTIFACTS_DIR, show_default=True, type=click.Path(file_okay=False))
@click.option("--out", default=dvc_path("report", profile="demo"), show_default=True, type=click.Path(file_okay=False),
              help="report directory (dvc.yaml: reports/${profile})")
def main(params, device, art, out):
    """Write report.md, a self-contained report.html, figures and plot CSVs."""
    from pipeline.report.build import build_report
    cfg = section(params, "report")
    profile = str(params.get("profile", ""))
    env = collect()
    report, plots, inp = build_report(art, cfg, profile, resolve_device(device), environment=env)
    meta = stage_context("report", __file__, params).meta("report", list(inp.found.values()),
                    missing_inputs=sorted(inp.missing))
    with artifact_dir(out, meta) as tmp:
        (tmp / "figures").mkdir()
        for fig in report.figures():
            (tmp / "figures" / fig.filename).write_bytes(fig.png)
            if fig.svg is not None:
                (tmp / "figures" / fig.svg_filename).write_bytes(fig.svg)
        (tmp / "plots").mkdir()
        for name, df in plots.items():
            df.to_csv(tmp / "plots" / f"{name}.csv", index=False)
        (tmp / "report.md").write_text(render_markdown(report))
        (tmp / "report.html").write_text(render_html(report))
        write_json(tmp / "environment.json", environment_record(env, inp.runs))
    from pipeline.report.build import MASK_INPUTS

    not_computed = sorted(n for n in inp.missing if inp.no_masks and n in MASK_INPUTS)
    absent = sorted(n for n in inp.missing if n not in not_computed)
    missing = (f" (not computed without validation/test masks: {', '.join(not_computed)})" if not_computed else "") \
        + (f" (missing inputs: {', '.join(absent)})" if absent else "")
    click.echo(f"report: {len(report.tables())} tables, {len(report.figures())} figures -> {Path(out)}{missing}",
               err=True)


if __name__ == "__main__":
    main()
