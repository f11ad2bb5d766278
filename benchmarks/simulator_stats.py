"""How close is the teacher SIMULATOR to the paper's real SAM 3 teacher?  Prints both side by side.

    python -m benchmarks.simulator_stats --artifacts artifacts            # uses teacher.zarr if present
    python -m benchmarks.simulator_stats --artifacts /tmp/data --group KCP --seed 0

Paper targets (SpaceSense-Bench KCP; tables teacher-prompt-quality and gate-groups):

* mean over the six single prompts: Image IoU 0.3462 +- 0.2423 (mean and sample SD over prompts);
* base prompt ``spacecraft`` 0.4743; validation-selected single prompt 0.5691;
* six-prompt majority vote 0.6833 (Boundary F1 0.7794);
* reliability gate: 18 of 60 images (30 %) with g = 0, teacher Image IoU 0.2853 vs 0.8539 for g > 0.

The statistics use the project's single implementations: ``pipeline.consensus.vote_batch``
(eq:agreement-map, eq:majority-vote), ``pipeline.geometry`` (eq:foreground-agreement ..
eq:reliability-gate, a0 = median training pseudo-area) and ``pipeline.metrics`` (Image IoU,
Boundary F1).  A single prompt is evaluated as the teacher answered it: an invalid prompt (score 0)
contributes its empty mask.  The validation-selected prompt is the one with the best mean Image IoU
on the ``val`` split, as in the paper.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Sequence

import numpy as np
import yaml

from pipeline import catalog
from pipeline.artifacts.store import open_artifact
from pipeline.consensus import vote_batch
from pipeline.geometry import area_ratios, foreground_agreement, gate_factors, median_area, valid_ratio
from pipeline.metrics import boundary_f1, per_image_metrics
from pipeline.params import PAPER_PROMPTS
from pipeline.teachers.base import TeacherInput, manifest_extras
from pipeline.teachers.simulated import SimulatedFoundationTeacher

PAPER = {
    "mean_single_iou": 0.3462, "sd_single_iou": 0.2423, "base_iou": 0.4743, "selected_iou": 0.5691,
    "vote_iou": 0.6833, "vote_bf1": 0.7794, "gate0_fraction": 18 / 60, "gate0_iou": 0.2853, "gate_pos_iou": 0.8539,
    "gate0_bf1": 0.3258, "gate_pos_bf1": 0.9738,
}


@dataclasses.dataclass
class TeacherStats:
    group: str
    n_images: int
    prompt_iou: dict[str, float]          # per prompt, on the group
    mean_single_iou: float
    sd_single_iou: float
    base_iou: float
    selected_prompt: str
    selected_iou: float
    vote_iou: float
    vote_bf1: float
    gate0_fraction: float
    gate0_iou: float
    gate_pos_iou: float
    gate0_bf1: float
    gate_pos_bf1: float
    valid_rate: dict[str, float]


def _mean_iou(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    return per_image_metrics(pred, gt)["iou"]


def compute_teacher_stats(masks: np.ndarray, scores: np.ndarray, gt: np.ndarray, split: Sequence[str],
                          group: Sequence[str], prompts: Sequence[str], base_index: int = 0,
                          group_name: str = "KCP", bf1_tolerance: float = 2.0) -> TeacherStats:
    """Teacher-quality statistics of masks bool [N,K,H,W] / scores [N,K] against ground truth [N,H,W].

    ``split``/``group`` are per-image labels; the statistics are reported on ``group == group_name``
    (all test images when no image has that group), the prompt is selected on ``split == val`` and
    a0 is the median pseudo-area of the training images (eq:area-gate).
    """
    split = np.asarray(split).astype(str)
    group = np.asarray(group).astype(str)
    sel = group == group_name
    if not sel.any():
        sel, group_name = split == "test", "test"
    val = split == "val"
    k = len(prompts)
    single = np.stack([_mean_iou(masks[:, j], gt) for j in range(k)], axis=1)   # [N,K]
    prompt_iou = single[sel].mean(axis=0)
    chosen = int(np.argmax(single[val].mean(axis=0))) if val.any() else int(np.argmax(prompt_iou))
    cons = vote_batch(masks, scores)
    vote_iou = _mean_iou(cons.voted, gt)
    vote_bf1 = np.array([boundary_f1(cons.voted[i], gt[i], bf1_tolerance) for i in range(len(gt))])
    c = foreground_agreement(cons.agreement, cons.voted)
    v = valid_ratio(cons.n_valid, k)
    a = area_ratios(cons.voted)
    a0 = median_area(a, split == "train")
    g = np.asarray(gate_factors(c, v, a, a0).g)
    zero = g == 0

    def m(x, where):
        return float(x[where].mean()) if where.any() else float("nan")

    return TeacherStats(
        group=group_name, n_images=int(sel.sum()),
        prompt_iou={p: float(x) for p, x in zip(prompts, prompt_iou)},
        mean_single_iou=float(prompt_iou.mean()), sd_single_iou=float(prompt_iou.std(ddof=1)) if k > 1 else 0.0,
        base_iou=float(prompt_iou[base_index]), selected_prompt=prompts[chosen], selected_iou=float(prompt_iou[chosen]),
        vote_iou=m(vote_iou, sel), vote_bf1=m(vote_bf1, sel),
        gate0_fraction=float(zero[sel].mean()), gate0_iou=m(vote_iou, sel & zero), gate_pos_iou=m(vote_iou, sel & ~zero),
        gate0_bf1=m(vote_bf1, sel & zero), gate_pos_bf1=m(vote_bf1, sel & ~zero),
        valid_rate={p: float(x) for p, x in zip(prompts, (scores[sel] > 0).mean(axis=0))},
    )


def format_stats(s: TeacherStats) -> str:
    """A plain-text table: statistic | SIMULATOR | paper (SAM 3 on KCP)."""
    rows = [
        ("mean single-prompt Image IoU", s.mean_single_iou, PAPER["mean_single_iou"]),
        ("  SD across prompts", s.sd_single_iou, PAPER["sd_single_iou"]),
        ("base prompt 'spacecraft'", s.base_iou, PAPER["base_iou"]),
        (f"val-selected prompt ('{s.selected_prompt[:28]}')", s.selected_iou, PAPER["selected_iou"]),
        ("six-prompt vote Image IoU", s.vote_iou, PAPER["vote_iou"]),
        ("six-prompt vote Boundary F1", s.vote_bf1, PAPER["vote_bf1"]),
        ("fraction of images with g = 0", s.gate0_fraction, PAPER["gate0_fraction"]),
        ("vote Image IoU, g = 0", s.gate0_iou, PAPER["gate0_iou"]),
        ("vote Image IoU, g > 0", s.gate_pos_iou, PAPER["gate_pos_iou"]),
        ("vote Boundary F1, g = 0", s.gate0_bf1, PAPER["gate0_bf1"]),
        ("vote Boundary F1, g > 0", s.gate_pos_bf1, PAPER["gate_pos_bf1"]),
    ]
    out = [f"teacher SIMULATOR vs paper (SAM 3, SpaceSense-Bench KCP) -- group {s.group}, {s.n_images} images",
           f"{'statistic':52s} {'simulator':>10s} {'paper':>8s}"]
    out += [f"{name:52s} {sim:10.4f} {pap:8.4f}" for name, sim, pap in rows]
    out.append("per prompt (Image IoU, valid rate):")
    out += [f"  {p[:50]:50s} {s.prompt_iou[p]:8.4f} {s.valid_rate[p]:8.2f}" for p in s.prompt_iou]
    return "\n".join(out)


def simulate(artifacts: Path, prompts: Sequence[str], seed: int, vflip: bool = False):
    """Run the SIMULATOR over every image of an artifacts directory (no cache); masks, scores, gt, manifest."""
    man = open_artifact(catalog.path("manifest", artifacts), "manifest").df.reset_index(drop=True)
    images = open_artifact(catalog.path("images", artifacts), "images").numpy("image")
    ref = open_artifact(catalog.path("reference", artifacts), "reference")
    gt = ref.numpy("mask")
    parts = ref.numpy("parts") if "parts" in ref else None
    teacher = SimulatedFoundationTeacher(seed=seed, resolution=gt.shape[1:])
    extras = manifest_extras(man)
    items = [TeacherInput(str(r.image_id), str(r.sha256), images[i], "identity",
                          {"mask": gt[i], **({"parts": parts[i]} if parts is not None else {})},
                          extras[i]) for i, r in enumerate(man.itertuples())]
    masks, scores = teacher.predict(items, prompts)
    return masks, scores, gt, man


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
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
    if args.teacher is not None:

        t = open_artifact(args.teacher, "teacher")
        masks, scores, prompts = t.numpy("masks"), t.numpy("scores"), list(t.attrs["prompts"])
        man = open_artifact(catalog.path("manifest", args.artifacts), "manifest").df.reset_index(drop=True)
        gt = open_artifact(catalog.path("reference", args.artifacts), "reference").numpy("mask")
        print(f"evaluating {args.teacher} (backend {t.attrs.get('backend')})")
    else:
        masks, scores, gt, man = simulate(args.artifacts, prompts, seed)
        print(f"simulated teacher (SIMULATOR, seed {seed}) on {args.artifacts}")
    stats = compute_teacher_stats(masks, scores, gt, man["split"], man["group"], prompts, base, args.group)
    print(format_stats(stats))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
