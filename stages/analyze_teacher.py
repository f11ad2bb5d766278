"""Stage analyze_teacher: the quality of the teacher's pseudo-masks per prompt and voted, and whether the gate
separates poor from good ones.  Post-hoc only: reference masks measure here, nothing feeds training (the logic:
:func:`pipeline.report.analysis.teacher_metrics`)."""

from __future__ import annotations

import click

from pipeline import catalog
from pipeline.artifacts.lineage import require_same_run
from pipeline.artifacts.store import open_artifact, write_parquet
from pipeline.catalog import ARTIFACTS_DIR, dvc_path
from pipeline.params import section
from pipeline.report.analysis import base_prompt_index, prompt_source, teacher_metrics
from pipeline.report.dvc_results import teacher_metric_files, write_metrics_dir
from pipeline.teacher_table import is_simulator
from stages._common import stage_command, stage_context


@stage_command("analyze_teacher")
@click.option("--artifacts", "art", default=ARTIFACTS_DIR, show_default=True, type=click.Path(file_okay=False))
@click.option("--out", default=dvc_path("teacher_metrics"), show_default=True, type=click.Path(dir_okay=False))
@click.option("--metrics-dir", default=None, type=click.Path(file_okay=False),
              help="DVC metrics <group>.json, replaced [default: reports/metrics/teacher beside --artifacts]")
def main(params, device, art, out, metrics_dir):
    """Teacher prompt / vote quality on val+test, prompt selection on val, gate-vs-quality analysis."""
    cfg = section(params, "evaluate")
    manifest, reference, teacher, consensus, gates = (
        open_artifact(catalog.path(name, art), name)  # each schema is its catalogue name
        for name in ("manifest", "reference", "teacher", "consensus", "gates"))
    require_same_run(manifest, reference, teacher, consensus, gates)
    backend = str(teacher.attrs.get("backend", "unknown"))
    tm, selected, val_means = teacher_metrics(manifest, reference, teacher, consensus, cfg["bf1_tolerance"],
                                              cfg["small_region_max_fraction"])
    meta = stage_context("analyze_teacher", __file__, params).meta(
                    "teacher_metrics", [manifest, reference, teacher, consensus, gates],
                    teacher_backend=backend, simulator=is_simulator(backend),
                    base_source=prompt_source(base_prompt_index(teacher.meta)), selected_source=selected,
                    prompts=list(teacher.attrs.get("prompts", [])),
                    val_prompt_iou={k: float(v) for k, v in val_means.items()})
    write_parquet(out, tm, meta)

    write_metrics_dir(metrics_dir or catalog.path("metrics_teacher", art), teacher_metric_files(tm, gates.df))
    n_images, n_sources = int((tm["source"] == "vote").sum()), teacher["masks"].shape[1] + 1
    click.echo(f"analyze_teacher: {n_images} images x {n_sources} sources -> {out} "
               f"(teacher backend: {backend}{' = SIMULATOR' if is_simulator(backend) else ''})", err=True)


if __name__ == "__main__":
    main()
