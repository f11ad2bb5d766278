"""Stage analyze_teacher: the quality of the teacher's pseudo-masks per prompt and voted, and whether the gate
separates poor from good ones.  Post-hoc only: reference masks measure here, nothing feeds training."""

from __future__ import annotations

import click
import numpy as np
import pandas as pd

from pipeline import catalog
from pipeline.artifacts.lineage import require_same_run
from pipeline.artifacts.store import open_artifact, read_chunk_rows, write_parquet
from pipeline.catalog import ARTIFACTS_DIR, dvc_path
from pipeline.report.dvc_results import teacher_metric_files, write_metrics_dir
from pipeline.runtime.errors import InputError
from pipeline.metrics import per_image_metrics
from pipeline.params import section
from pipeline.teacher_table import is_simulator
from pipeline.runtime.progress import progress
from pipeline.report.analysis import prompt_source, select_prompt
from stages._common import stage_command, stage_context

CHUNK = 32


def base_prompt_index(teacher_meta) -> int:
    """The base prompt's index as recorded in the teacher artifact's params (default 0, the paper's
    p1 = `spacecraft`)."""
    p = teacher_meta.params or {}
    cfg = p.get("teacher", p)
    return int(cfg.get("base_prompt_index", 0)) if isinstance(cfg, dict) else 0  # unvalidated: as recorded


@stage_command("analyze_teacher")
@click.option("--artifacts", "art", default=ARTIFACTS_DIR, show_default=True, type=click.Path(file_okay=False))
@click.option("--out", default=dvc_path("teacher_metrics"), show_default=True, type=click.Path(dir_okay=False))
@click.option("--metrics-dir", default=None, type=click.Path(file_okay=False),
              help="DVC metrics <group>.json, replaced [default: reports/metrics/teacher beside --artifacts]")
def main(params, device, art, out, metrics_dir):
    """Teacher prompt / vote quality on val+test, prompt selection on val, gate-vs-quality analysis."""
    cfg = section(params, "evaluate")
    tol, small_frac = cfg["bf1_tolerance"], cfg["small_region_max_fraction"]
    manifest, reference, teacher, consensus, gates = (
        open_artifact(catalog.path(name, art), name)  # each schema is its catalogue name
        for name in ("manifest", "reference", "teacher", "consensus", "gates"))
    require_same_run(manifest, reference, teacher, consensus, gates)
    mdf = manifest.df
    prompts = list(teacher.attrs.get("prompts", []))
    backend = str(teacher.attrs.get("backend", "unknown"))
    k_prompts = teacher["masks"].shape[1]
    base = prompt_source(base_prompt_index(teacher.meta))

    idx = np.flatnonzero(mdf["split"].isin(["val", "test"]).to_numpy() & reference.numpy("has_mask").astype(bool))
    if idx.size == 0:
        raise InputError(f"{manifest.path}: no validation/test image has a reference mask; nothing to analyse")
    info = mdf.iloc[idx][["image_id", "dataset", "domain", "split", "group", "spacecraft"]].reset_index(drop=True)
    frames = []
    for s in progress(range(0, idx.size, CHUNK), desc="analyze_teacher"):
        rows = idx[s:s + CHUNK]
        part_info = info.iloc[s:s + len(rows)]
        # reference masks: post-hoc measurement of teacher quality only
        gts = read_chunk_rows(reference["mask"], rows).astype(bool)
        masks = read_chunk_rows(teacher["masks"], rows).astype(bool)
        voted = read_chunk_rows(consensus["voted"], rows).astype(bool)
        sources = [(prompt_source(k), prompts[k] if k < len(prompts) else f"prompt {k}", masks[:, k])
                   for k in range(k_prompts)]
        sources.append(("vote", f"{k_prompts}-prompt majority vote", voted))
        for name, text, pred in sources:
            sc = per_image_metrics(pred, gts, tol, max_fraction=small_frac)
            part = part_info.copy()
            part["source"], part["prompt"] = name, text
            for k, v in sc.items():
                part[k] = v
            frames.append(part)
    tm = pd.concat(frames, ignore_index=True)
    selected, val_means = select_prompt(tm, "val")
    if selected is not None:
        sel = tm[tm["source"] == selected].copy()
        sel["source"] = "val_selected"
        tm = pd.concat([tm, sel], ignore_index=True)

    meta = stage_context("analyze_teacher", __file__, params).meta(
                    "teacher_metrics", [manifest, reference, teacher, consensus, gates],
                    teacher_backend=backend, simulator=is_simulator(backend), base_source=base,
                    selected_source=selected, prompts=prompts,
                    val_prompt_iou={k: float(v) for k, v in val_means.items()})
    write_parquet(out, tm, meta)

    write_metrics_dir(metrics_dir or catalog.path("metrics_teacher", art), teacher_metric_files(tm, gates.df))
    click.echo(f"analyze_teacher: {idx.size} images x {k_prompts + 1} sources -> {out} "
               f"(teacher backend: {backend}{' = SIMULATOR' if is_simulator(backend) else ''})", err=True)


if __name__ == "__main__":
    main()
