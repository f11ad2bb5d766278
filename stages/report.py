"""Stage report: the paper's tables and figures (report.md, a self-contained report.html, figures, plot CSVs,
environment.json) and the distillation-efficiency DVC metrics; missing inputs are reported, not fatal."""

from __future__ import annotations

from pathlib import Path

import click

from pipeline import catalog
from pipeline.artifacts.atomic import write_json
from pipeline.artifacts.store import artifact_dir
from pipeline.catalog import ARTIFACTS_DIR, dvc_path
from pipeline.runtime.device import resolve_device
from pipeline.report.dvc_results import efficiency_metric_files, write_metrics_dir
from pipeline.artifacts.provenance import collect
from pipeline.params import section
from pipeline.report.document import render_html, render_markdown
from pipeline.report.environment import environment_record
from stages._common import stage_command, stage_context


@stage_command("report")
@click.option("--artifacts", "art", default=ARTIFACTS_DIR, show_default=True, type=click.Path(file_okay=False))
@click.option("--out", default=dvc_path("report", profile="demo"), show_default=True, type=click.Path(file_okay=False),
              help="report directory (dvc.yaml: reports/${profile})")
@click.option("--metrics-dir", default=None, type=click.Path(file_okay=False),
              help="DVC metrics <group>/<method>.json of the distillation efficiency, replaced "
                   "[default: reports/metrics/efficiency beside --artifacts]")
def main(params, device, art, out, metrics_dir):
    """Write report.md, a self-contained report.html, figures and plot CSVs."""
    from pipeline.report.build import MASK_INPUTS, build_report, vote_means
    cfg = section(params, "report")
    profile = params["profile"]
    env = collect()
    report, plots, inp = build_report(art, cfg, profile, resolve_device(device), environment=env)
    meta = stage_context("report", __file__, params).meta("report", list(inp.found.values()),
                    missing_inputs=sorted(inp.missing))
    with artifact_dir(out, meta) as tmp:
        files = catalog.output_names("report")
        (tmp / files["figures"]).mkdir()
        for fig in report.figures():
            (tmp / files["figures"] / fig.filename).write_bytes(fig.png)
            if fig.svg is not None:
                (tmp / files["figures"] / fig.svg_filename).write_bytes(fig.svg)
        (tmp / files["plots"]).mkdir()
        for name, df in plots.items():
            df.to_csv(tmp / files["plots"] / f"{name}.csv", index=False)
        (tmp / files["markdown"]).write_text(render_markdown(report))
        (tmp / files["html"]).write_text(render_html(report))
        write_json(tmp / files["environment"], environment_record(env, inp.runs))
    summary, vote = inp.get("summary"), vote_means(inp)
    efficiency = {} if summary is None or vote is None else efficiency_metric_files(
        summary.df, {str(g): float(v) for g, v in vote["iou"].items()})
    write_metrics_dir(metrics_dir or catalog.path("metrics_efficiency", art), efficiency)
    not_computed = sorted(n for n in inp.missing if inp.no_masks and n in MASK_INPUTS)
    absent = sorted(n for n in inp.missing if n not in not_computed)
    missing = (f" (not computed without validation/test masks: {', '.join(not_computed)})" if not_computed else "") \
        + (f" (missing inputs: {', '.join(absent)})" if absent else "")
    click.echo(f"report: {len(report.tables())} tables, {len(report.figures())} figures -> {Path(out)}{missing}",
               err=True)


if __name__ == "__main__":
    main()
