"""Stage evaluate: per-image metrics of every student on every test group, seed summaries and gains.

* thresholds: the validation-calibrated tau of each (method, seed), applied unchanged, and the fixed
  tau (``calibrate.fixed_tau`` recorded in thresholds.parquet, 0.5) -- ``threshold_mode`` =
  calibrated | fixed;
* ``metrics.parquet``: one row per (group, method, seed, image, threshold_mode) with Image IoU,
  Boundary F1 (evaluate.bf1_tolerance px), precision, recall, predicted area ratio and small-region
  IoU (pipeline.metrics);
* ``summary.parquet``: mean and sample std over seeds of the per-seed means, plus the gain of each
  method over ``plain`` with a paired hierarchical bootstrap CI (spacecraft, then images;
  evaluate.bootstrap_resamples, evaluate.ci, seeded by evaluate.bootstrap_seed);
* ``metrics/summary.json``: a small flat-ish digest for ``dvc metrics show``.

Reference masks are used here only to score predictions.
"""

from __future__ import annotations


import click
import numpy as np
import pandas as pd

from pipeline.params import section
from stages._common import declared_params, meta_for, stage_code_version, stage_command

GAIN_METRICS = ("iou", "bf1", "precision", "recall")
CHUNK = 64  # test images predicted and scored per batch (bounded memory for large test sets)


def run_thresholds(thresholds: pd.DataFrame, method: str, seed: int, path) -> tuple[float, float]:
    """(calibrated tau, fixed tau) of one run; ArtifactError when calibrate did not see the run."""
    from pipeline.errors import ArtifactError

    row = thresholds[(thresholds["method"] == method) & (thresholds["seed"] == seed)]
    if len(row) != 1:
        raise ArtifactError(f"{path}: no calibrated threshold for {method}/{seed} in thresholds.parquet; "
                            f"rerun calibrate")
    return float(row["tau"].iloc[0]), float(row["fixed_tau"].iloc[0])


def summary_json(summary: pd.DataFrame) -> dict:
    """{group: {method: {iou, bf1, [iou_std, bf1_std], [gain_iou, gain_iou_lo, ...]}}} at the
    calibrated threshold, rounded to 4 decimals (NaN left out)."""
    out: dict = {}
    cal = summary[summary["threshold_mode"] == "calibrated"]
    for _, r in cal.iterrows():
        d = {}
        for k in ("iou_mean", "bf1_mean", "iou_std", "bf1_std", "gain_iou", "gain_iou_lo", "gain_iou_hi",
                  "gain_bf1", "gain_bf1_lo", "gain_bf1_hi"):
            v = r.get(k)
            if v is not None and np.isfinite(v):
                d[k.replace("_mean", "")] = round(float(v), 4)
        out.setdefault(str(r["group"]), {})[str(r["method"])] = d
    return out


@stage_command("evaluate")
@click.option("--artifacts", "art", default="artifacts", show_default=True, type=click.Path(file_okay=False))
@click.option("--checkpoints", default="artifacts/checkpoints", show_default=True, type=click.Path(file_okay=False))
@click.option("--thresholds", default="artifacts/thresholds.parquet", show_default=True, type=click.Path(dir_okay=False))
@click.option("--out", default="artifacts/metrics.parquet", show_default=True, type=click.Path(dir_okay=False))
@click.option("--summary", "summary_out", default="artifacts/summary.parquet", show_default=True,
              type=click.Path(dir_okay=False))
@click.option("--metrics-json", default="artifacts/metrics/summary.json", show_default=True,
              type=click.Path(dir_okay=False))
def main(params, device, art, checkpoints, thresholds, out, summary_out, metrics_json):
    """Score every student on every test group; write per-image metrics, summaries with bootstrap CIs."""
    from pipeline.artifacts import open_artifact, read_chunk_rows, write_json, write_parquet
    from pipeline.device import resolve_device
    from pipeline.inference import active_runs, load_student, open_labelled_split, predict_probs
    from pipeline.metrics import per_image_metrics
    from pipeline.progress import progress
    from pipeline.stats import method_gains, seed_summary
    from pipeline.thresholds import mask_from_probs

    cfg = section(params, "evaluate")
    tol, small_frac = cfg["bf1_tolerance"], cfg["small_region_max_fraction"]
    n_boot, boot_seed, ci = cfg["bootstrap_resamples"], cfg["bootstrap_seed"], cfg["ci"]

    manifest, images, reference, test = open_labelled_split(art, "test", "nothing to evaluate")
    thr = open_artifact(thresholds, "thresholds")
    mdf = manifest.df
    runs = active_runs(checkpoints, "evaluate")

    dev = resolve_device(device)
    info = mdf.iloc[test][["image_id", "dataset", "domain", "group", "spacecraft"]].reset_index(drop=True)
    frames, inputs = [], [manifest, images, reference, thr]
    for method, seed, path in progress(runs, desc="evaluate"):
        tau_cal, tau_fixed = run_thresholds(thr.df, method, seed, path)
        model, _ = load_student(path, dev)
        inputs.append(open_artifact(path))
        for s in range(0, test.size, CHUNK):
            idx = test[s:s + CHUNK]
            probs = predict_probs(model, read_chunk_rows(images["image"], idx), device=dev)
            gts = read_chunk_rows(reference["mask"], idx).astype(bool)
            for mode, tau in (("calibrated", tau_cal), ("fixed", tau_fixed)):
                scores = per_image_metrics(mask_from_probs(probs, tau), gts, tol, max_fraction=small_frac)
                part = info.iloc[s:s + len(idx)].copy()
                part["method"], part["seed"], part["threshold_mode"], part["tau"] = method, int(seed), mode, tau
                for k, v in scores.items():
                    part[k] = v
                frames.append(part)
    metrics = pd.concat(frames, ignore_index=True)
    order = ["dataset", "domain", "group", "spacecraft", "method", "seed", "image_id", "threshold_mode", "tau"]
    metrics = metrics[order + [c for c in metrics.columns if c not in order]]

    by = ["dataset", "group", "method", "threshold_mode"]
    summary = seed_summary(metrics, by, ["iou", "bf1", "precision", "recall", "area_ratio", "small_iou"])
    gains = method_gains(metrics, GAIN_METRICS, control="plain", by=["dataset", "group", "threshold_mode"],
                         n_resamples=n_boot, ci=ci, seed=boot_seed)
    summary = summary.merge(gains, on=by, how="left")

    code = stage_code_version(__file__)
    write_parquet(out, metrics, meta_for("metrics", "evaluate", code, declared_params(params, "evaluate"), inputs))
    mmeta = open_artifact(out, "metrics")
    write_parquet(summary_out, summary, meta_for("summary", "evaluate", code, declared_params(params, "evaluate"), [mmeta],
                                                 control="plain", ci=ci, bootstrap_resamples=n_boot))
    write_json(metrics_json, summary_json(summary))
    click.echo(f"evaluate: {len(runs)} runs x {test.size} test images -> {out}, {summary_out}", err=True)


if __name__ == "__main__":
    main()
