"""How close is the teacher SIMULATOR to the paper's real SAM 3 teacher (SpaceSense-Bench KCP; tables
teacher-prompt-quality and gate-groups)?  Prints the single-prompt, selected-prompt and six-prompt-vote Image IoU
and the reliability gate's split beside the paper's, computed with the project's own vote, gate and metrics.

    python -m benchmarks.simulator_stats --artifacts artifacts [--teacher artifacts/teacher.zarr] [--group KCP]
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Sequence

import numpy as np
import yaml

from pipeline import catalog
from pipeline.artifacts.store import open_artifact
from pipeline.consensus import vote_batch
from pipeline.geometry import area_ratios, foreground_agreement, gate_factors, median_area, valid_ratio
from pipeline.metrics import boundary_f1, image_ious
from pipeline.params import PAPER_PROMPTS
from pipeline.teachers.base import TeacherInput, manifest_extras
from pipeline.teachers.simulated import SimulatedFoundationTeacher

PAPER = {
    "mean_single_iou": 0.3462, "sd_single_iou": 0.2423, "base_iou": 0.4743, "selected_iou": 0.5691,
    "vote_iou": 0.6833, "vote_bf1": 0.7794, "gate0_fraction": 18 / 60, "gate0_iou": 0.2853, "gate_pos_iou": 0.8539,
    "gate0_bf1": 0.3258, "gate_pos_bf1": 0.9738,
}
#: the printed rows: (statistic, label)
ROWS = (("mean_single_iou", "mean single-prompt Image IoU"), ("sd_single_iou", "  SD across prompts"),
        ("base_iou", "base prompt 'spacecraft'"), ("selected_iou", "val-selected prompt ('{prompt}')"),
        ("vote_iou", "six-prompt vote Image IoU"), ("vote_bf1", "six-prompt vote Boundary F1"),
        ("gate0_fraction", "fraction of images with g = 0"), ("gate0_iou", "vote Image IoU, g = 0"),
        ("gate_pos_iou", "vote Image IoU, g > 0"), ("gate0_bf1", "vote Boundary F1, g = 0"),
        ("gate_pos_bf1", "vote Boundary F1, g > 0"))


def compute_teacher_stats(masks: np.ndarray, scores: np.ndarray, gt: np.ndarray, split: Sequence[str],
                          group: Sequence[str], prompts: Sequence[str], base_index: int = 0,
                          group_name: str = "KCP", bf1_tolerance: float = 2.0) -> dict:
    """Teacher-quality statistics of masks bool [N,K,H,W] / scores [N,K] against ground truth [N,H,W] on
    ``group == group_name`` (else every test image); the prompt is selected on ``val`` and a0 is the median
    training pseudo-area (eq:area-gate)."""
    split, group = np.asarray(split).astype(str), np.asarray(group).astype(str)
    sel = group == group_name
    if not sel.any():
        sel, group_name = split == "test", "test"
    val = split == "val"
    k = len(prompts)
    single = np.stack([image_ious(masks[:, j], gt) for j in range(k)], axis=1)   # [N,K]
    prompt_iou = single[sel].mean(axis=0)
    chosen = int(np.argmax(single[val].mean(axis=0))) if val.any() else int(np.argmax(prompt_iou))
    cons = vote_batch(masks, scores)
    vote_iou = image_ious(cons.voted, gt)
    vote_bf1 = np.array([boundary_f1(cons.voted[i], gt[i], bf1_tolerance) for i in range(len(gt))])
    a = area_ratios(cons.voted)
    g = np.asarray(gate_factors(foreground_agreement(cons.agreement, cons.voted), valid_ratio(cons.n_valid, k), a,
                                median_area(a, split == "train")).g)
    zero = g == 0

    def m(x, where):
        return float(x[where].mean()) if where.any() else float("nan")

    return {"group": group_name, "n_images": int(sel.sum()),
            "prompt_iou": {p: float(x) for p, x in zip(prompts, prompt_iou)},
            "mean_single_iou": float(prompt_iou.mean()), "sd_single_iou": float(prompt_iou.std(ddof=1)) if k > 1 else 0.0,
            "base_iou": float(prompt_iou[base_index]), "selected_prompt": prompts[chosen],
            "selected_iou": float(prompt_iou[chosen]), "vote_iou": m(vote_iou, sel), "vote_bf1": m(vote_bf1, sel),
            "gate0_fraction": float(zero[sel].mean()), "gate0_iou": m(vote_iou, sel & zero),
            "gate_pos_iou": m(vote_iou, sel & ~zero), "gate0_bf1": m(vote_bf1, sel & zero),
            "gate_pos_bf1": m(vote_bf1, sel & ~zero),
            "valid_rate": {p: float(x) for p, x in zip(prompts, (scores[sel] > 0).mean(axis=0))}}


def format_stats(s: dict) -> str:
    """A plain-text table: statistic | SIMULATOR | paper (SAM 3 on KCP)."""
    out = [f"teacher SIMULATOR vs paper (SAM 3, SpaceSense-Bench KCP) -- group {s['group']}, {s['n_images']} images",
           f"{'statistic':52s} {'simulator':>10s} {'paper':>8s}"]
    out += [f"{label.format(prompt=s['selected_prompt'][:28]):52s} {s[k]:10.4f} {PAPER[k]:8.4f}" for k, label in ROWS]
    out.append("per prompt (Image IoU, valid rate):")
    out += [f"  {p[:50]:50s} {s['prompt_iou'][p]:8.4f} {s['valid_rate'][p]:8.2f}" for p in s["prompt_iou"]]
    return "\n".join(out)


def simulate(artifacts: Path, man, ref, prompts: Sequence[str], seed: int):
    """(masks, scores) of the SIMULATOR over every image of ``artifacts`` (no cache)."""
    images = open_artifact(catalog.path("images", artifacts), "images").numpy("image")
    gt = ref.numpy("mask")
    parts = ref.numpy("parts") if "parts" in ref else None
    teacher = SimulatedFoundationTeacher(seed=seed, resolution=gt.shape[1:])
    extras = manifest_extras(man)
    items = [TeacherInput(str(r.image_id), str(r.sha256), images[i], "identity",
                          {"mask": gt[i], **({"parts": parts[i]} if parts is not None else {})},
                          extras[i]) for i, r in enumerate(man.itertuples())]
    return teacher.predict(items, prompts)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--artifacts", default=catalog.ARTIFACTS_DIR, type=Path,
                    help="directory with manifest.parquet, images.zarr, reference.zarr (and maybe teacher.zarr)")
    ap.add_argument("--teacher", default=None, type=Path, help="teacher.zarr to evaluate (default: simulate now)")
    ap.add_argument("--group", default="KCP", help="test group to report (paper: KCP)")
    ap.add_argument("--seed", default=None, type=int, help="simulator seed (default: params teacher.seed)")
    ap.add_argument("--params", default="params.yaml", type=Path)
    args = ap.parse_args(argv)
    cfg = (yaml.safe_load(args.params.read_text()) or {}).get("teacher", {}) if args.params.exists() else {}
    prompts = cfg.get("prompts") or list(PAPER_PROMPTS)
    base = int(cfg.get("base_prompt_index", 0))
    seed = args.seed if args.seed is not None else int(cfg.get("seed", 0))
    man = open_artifact(catalog.path("manifest", args.artifacts), "manifest").df.reset_index(drop=True)
    ref = open_artifact(catalog.path("reference", args.artifacts), "reference")
    if args.teacher is not None:
        t = open_artifact(args.teacher, "teacher")
        masks, scores, prompts = t.numpy("masks"), t.numpy("scores"), list(t.attrs["prompts"])
        print(f"evaluating {args.teacher} (backend {t.attrs.get('backend')})")
    else:
        masks, scores = simulate(args.artifacts, man, ref, prompts, seed)
        print(f"simulated teacher (SIMULATOR, seed {seed}) on {args.artifacts}")
    stats = compute_teacher_stats(masks, scores, ref.numpy("mask"), man["split"], man["group"], prompts, base,
                                  args.group)
    print(format_stats(stats))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
