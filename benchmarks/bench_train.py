"""Training speed of Stage-I ``plain``: fp32 eager NCHW against the fast path (channels_last + bf16 autocast),
seconds per epoch (interleaved one-epoch rounds: median, minimum, ratio), then an ``--epochs`` run of each for
validation Image IoU / Boundary F1 on held-out images of an in-memory synthetic set (ellipse + bar on noise).

    python -m benchmarks.bench_train [--quick] [--images 270 --size 384 --epochs 2 --device cuda]
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from benchmarks.common import parser, round_robin
from pipeline.runtime.device import resolve_device
from pipeline.methods import STAGE_ONE, get_method
from pipeline.params import load_params, section
from pipeline.training.inputs import TrainData, ValData
from pipeline.training.checkpointing import NoCheckpointer

PAPER_IMAGES = 270


def synthetic_set(n: int, size: int, seed: int):
    """uint8 images [n,size,size,3] and bool masks: a bright ellipse body with a panel bar on noise."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size]
    masks = np.zeros((n, size, size), bool)
    for i in range(n):
        cy, cx = rng.uniform(0.3, 0.7, 2) * size
        ry, rx = rng.uniform(0.08, 0.2, 2) * size
        m = ((yy - cy) / ry) ** 2 + ((xx - cx) / rx) ** 2 <= 1
        h = max(1, size // 64)
        m[int(cy) - h:int(cy) + h, int(max(cx - 2.5 * rx, 0)):int(min(cx + 2.5 * rx, size))] = True
        masks[i] = m
    images = rng.integers(0, 60, (n, size, size, 3), dtype=np.uint8)
    fg = rng.integers(120, 255, (n, 1, 1, 3), dtype=np.uint8)
    images = np.where(masks[..., None], fg, images).astype(np.uint8)
    return images, masks


def train_variant(cfg: dict, data, val, device, seed: int) -> dict:
    """Train ``plain`` with ``cfg``; per-epoch training seconds (callback marks) and final val metrics."""
    from pipeline.training import loop as training
    marks = [time.perf_counter()]
    res = training.train(get_method(STAGE_ONE), cfg, data, None, seed, checkpointer=NoCheckpointer(),
                         device=device, callback=lambda epoch, row: marks.append(time.perf_counter()),
                         show_progress=False)
    out = {"epoch_seconds": list(np.diff(marks)), "autocast": res.info["autocast"],
           "final_loss": float(res.log["loss"].iloc[-1])}
    if val is not None:
        out["val_iou"], out["val_bf1"] = training.validate(res.model, val, device, precision=cfg["precision"],
                                                           channels_last=cfg["channels_last"],
                                                           tolerance=cfg["val_bf1_tolerance"])
    return out


def main(argv=None) -> dict:
    ap = parser(__doc__, device="auto")
    ap.add_argument("--images", type=int, default=PAPER_IMAGES)
    ap.add_argument("--size", type=int, default=384)
    ap.add_argument("--epochs", type=int, default=2)
    ap.add_argument("--val-images", type=int, default=16)
    ap.add_argument("--reps", type=int, default=3, help="interleaved one-epoch timing rounds")
    ap.add_argument("--quick", action="store_true", help="32 images at 256^2, 3 epochs, 2 timing rounds")
    ap.add_argument("--threads", type=int, default=0, help="torch CPU threads (0 = default)")
    ap.add_argument("--seed", type=int, default=42)
    ap.add_argument("--fast-precision", default="auto", help="precision of the fast path (auto|bf16)")
    args = ap.parse_args(argv)
    if args.quick:
        args.images, args.size, args.epochs, args.reps = 32, 256, 3, 2

    import torch


    device = resolve_device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    images, masks = synthetic_set(args.images + args.val_images, args.size, args.seed)
    n = args.images
    data = TrainData(image_ids=[f"b{i}" for i in range(n)], images=images[:n], mask=masks[:n],
                     area=masks[:n].reshape(n, -1).mean(1).astype(np.float32), gate=np.ones(n, np.float32))
    val = ValData(image_ids=[f"v{i}" for i in range(args.val_images)], images=images[n:], masks=masks[n:])
    base = section(load_params(Path(__file__).resolve().parents[1] / "params.yaml"), "train")
    base.update({"epochs_stage1": args.epochs, "num_threads": 0})

    variants = {"fp32 eager NCHW": {**base, "precision": "fp32", "channels_last": False},
                "channels_last + autocast": {**base, "precision": args.fast_precision, "channels_last": True}}
    one_epoch = {name: (lambda i, cfg=cfg: train_variant({**cfg, "epochs_stage1": 1}, data, None, device,
                                                        args.seed)["epoch_seconds"][0]) for name, cfg in variants.items()}
    round_robin(one_epoch, 1)  # warm-up: oneDNN primitive creation, allocator
    timing = round_robin(one_epoch, max(args.reps, 1))
    results = []
    for name, cfg in variants.items():
        acc = train_variant({**cfg, "epochs_stage1": args.epochs}, data, val, device, args.seed)
        results.append({"variant": name, "precision": cfg["precision"], "channels_last": cfg["channels_last"],
                        "autocast": acc["autocast"], "timing_seconds": timing[name],
                        "seconds_per_epoch": float(np.median(timing[name])),
                        "min_seconds_per_epoch": float(np.min(timing[name])),
                        "accuracy_run_epoch_seconds": acc["epoch_seconds"], "val_iou": acc["val_iou"],
                        "val_bf1": acc["val_bf1"], "final_loss": acc["final_loss"]})
    ratio = results[0]["seconds_per_epoch"] / results[1]["seconds_per_epoch"]
    print(f"device {device} ({torch.get_num_threads()} threads), {n} images at {args.size}^2, "
          f"batch {base['batch_size']}; timing: median of {args.reps} interleaved epochs; "
          f"accuracy: {args.epochs} epochs, {args.val_images} val images; torch {torch.__version__}")
    print(f"{'variant':28s} {'autocast':>9s} {'s/epoch':>9s} {'min':>7s} {'s/epoch@270':>12s} {'val IoU':>8s} {'val BF1':>8s}")
    for r in results:
        print(f"{r['variant']:28s} {r['autocast']:>9s} {r['seconds_per_epoch']:9.2f} {r['min_seconds_per_epoch']:7.2f} "
              f"{r['seconds_per_epoch'] * PAPER_IMAGES / n:12.1f} {r['val_iou']:8.4f} {r['val_bf1']:8.4f}")
    print(f"speed-up (fp32 eager / fast, median): {ratio:.2f}x  "
          f"(min: {results[0]['min_seconds_per_epoch'] / results[1]['min_seconds_per_epoch']:.2f}x; target >= 3x)")
    out = {"device": str(device), "images": n, "size": args.size, "epochs": args.epochs, "reps": args.reps,
           "ratio": ratio, "results": results}
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
