"""Teacher and gate analyses on the per-image teacher table (paper section "Multi-Prompt Teacher and
Pseudo-Label Quality Analysis").  Pure functions on DataFrames; no I/O.

The per-image teacher table (``teacher_metrics.parquet``) has one row per (image, source) with
``source`` one of ``prompt_<k>`` (the k-th fixed prompt's raw teacher mask, k = 0..K-1 in the
teacher's prompt order), ``vote`` (the consensus mask M, eq:majority-vote) and ``val_selected`` (a copy
of the prompt chosen on the VALIDATION split by mean Image IoU; test annotations play no part in the
choice).  Reference masks enter here only to *measure* teacher quality post hoc.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from pipeline.stats import spearman

METRICS = ("iou", "bf1", "precision", "recall")


def prompt_source(k: int) -> str:
    return f"prompt_{int(k)}"


def prompt_sources(tm: pd.DataFrame) -> list[str]:
    """The ``prompt_<k>`` sources present, in k order."""
    ks = sorted(int(s.split("_", 1)[1]) for s in tm["source"].unique() if str(s).startswith("prompt_"))
    return [prompt_source(k) for k in ks]


def select_prompt(tm: pd.DataFrame, split: str = "val", metric: str = "iou") -> tuple[str | None, pd.Series]:
    """The single prompt with the highest mean ``metric`` on ``split`` (ties: lowest k), and the
    per-prompt means.  (None, empty) when ``split`` has no scored image."""
    sub = tm[(tm["split"] == split) & tm["source"].isin(prompt_sources(tm))]
    if sub.empty:
        return None, pd.Series(dtype=float)
    means = sub.groupby("source")[metric].mean()
    means = means.reindex([s for s in prompt_sources(tm) if s in means.index])
    return str(means.idxmax()), means


def teacher_prompt_quality(tm: pd.DataFrame, group: str, base_source: str, selected_source: str | None,
                           prompts: list[str] | None = None) -> pd.DataFrame:
    """Paper Table teacher-prompt-quality for one evaluation group.

    Rows: base prompt; validation-selected single prompt; mean +- sample std (ddof = 1, n = K) over
    the K single prompts' mean metrics (an average of separately evaluated prompts, not a fusion);
    K-prompt majority vote.  Columns: config, <metric>, <metric>_std (NaN except for the mean row), n.
    """
    g = tm[tm["group"] == group]
    srcs = prompt_sources(tm)

    def label(src):
        k = int(src.split("_", 1)[1])
        text = prompts[k] if prompts and k < len(prompts) else src
        return f"`{text}`"

    rows = []

    def add(config, part, std=None):
        r = {"config": config, "n": int(part["image_id"].nunique()) if len(part) else 0}
        for m in METRICS:
            r[m] = float(part[m].mean()) if len(part) else np.nan
            r[f"{m}_std"] = np.nan if std is None else float(std[m])
        rows.append(r)

    add(f"Base prompt: {label(base_source)}", g[g["source"] == base_source])
    if selected_source is not None:
        add(f"Validation-selected single prompt: {label(selected_source)}", g[g["source"] == selected_source])
    per_prompt = g[g["source"].isin(srcs)].groupby("source")[list(METRICS)].mean()
    if len(per_prompt):
        r = {"config": f"Mean over {len(per_prompt)} single prompts",
             "n": int(g[g["source"].isin(srcs)]["image_id"].nunique())}
        for m in METRICS:
            r[m] = float(per_prompt[m].mean())
            r[f"{m}_std"] = float(per_prompt[m].std(ddof=1)) if len(per_prompt) > 1 else np.nan
        rows.append(r)
    add(f"{len(srcs)}-prompt majority vote", g[g["source"] == "vote"])
    return pd.DataFrame(rows)


def teacher_domain_quality(tm: pd.DataFrame, source: str = "vote", split: str = "test") -> pd.DataFrame:
    """Paper Table teacher-domain-quality: mean teacher metrics per dataset / domain / group of
    ``split`` for ``source`` (the vote by default), plus an ``all`` row per dataset/domain when it
    has several groups."""
    sub = tm[(tm["source"] == source) & (tm["split"] == split)]
    keys = ["dataset", "domain", "group"]
    per = sub.groupby(keys, sort=True)[list(METRICS)].mean()
    per["n"] = sub.groupby(keys, sort=True)["image_id"].nunique()
    per = per.reset_index()
    pooled = []
    for (ds, dom), part in sub.groupby(["dataset", "domain"], sort=True):
        if part["group"].nunique() > 1:
            r = {"dataset": ds, "domain": dom, "group": "all"}
            r.update({m: float(part[m].mean()) for m in METRICS})
            r["n"] = int(part["image_id"].nunique())
            pooled.append(r)
    return pd.concat([per, pd.DataFrame(pooled)], ignore_index=True) if pooled else per


def gate_analysis(tm: pd.DataFrame, gates: pd.DataFrame, group: str | None = None,
                  split: str = "test") -> dict:
    """Paper section "Pseudo-Label Quality and Reliability Analysis" for one group (None: all of
    ``split``): Spearman rho (and p) between the gate g and the vote's Image IoU / Boundary F1, and the
    table of g = 0 (geometry suppressed) against g > 0 (geometry enabled) images.

    Returns {"group", "n", "rho_iou", "p_iou", "rho_bf1", "p_bf1", "table": DataFrame[state, images,
    iou, bf1]}; a state with no image has NaN means.
    """
    v = tm[(tm["source"] == "vote") & (tm["split"] == split)]
    if group is not None:
        v = v[v["group"] == group]
    d = v.merge(gates[["image_id", "g"]], on="image_id", how="inner")
    r_iou = spearman(d["g"].to_numpy(float), d["iou"].to_numpy(float))
    r_bf1 = spearman(d["g"].to_numpy(float), d["bf1"].to_numpy(float))
    rows = []
    for state, sel in (("g = 0: geometry suppressed", d["g"] <= 0), ("g > 0: geometry enabled", d["g"] > 0)):
        part = d[sel]
        rows.append({"state": state, "images": int(len(part)),
                     "iou": float(part["iou"].mean()) if len(part) else np.nan,
                     "bf1": float(part["bf1"].mean()) if len(part) else np.nan})
    return {"group": group if group is not None else "all", "n": int(len(d)),
            "rho_iou": r_iou.rho, "p_iou": r_iou.pvalue, "rho_bf1": r_bf1.rho, "p_bf1": r_bf1.pvalue,
            "table": pd.DataFrame(rows)}
