"""Segmenting a folder end to end against the engine alone, for every CPU engine of ``segment --engine``: a deploy
bundle of a random TinyUNet (int8 calibrated on the images, agreement gate off), generated photo-like images, and
round-robin rounds of the engine alone, the serial loop and the overlapped loop; images/s (median, best round) and
end to end / model-only against the target (>= 0.8 on 2 cores at 384^2 from 640x480), printed, not asserted.

    python -m benchmarks.bench_segment [--images 200 --engines onnxruntime_fp32,openvino_int8]
"""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.common import medians, minima, parser, round_robin, seconds
from pipeline.artifacts.lineage import make_meta
from pipeline.datasets.loading import read_rgb, resize_image
from pipeline.deploy import image_files as F
from pipeline.deploy.segmenter import load_segmenter
from pipeline.engine_table import ENGINE_TABLE, SEGMENT_ENGINES, engine_name
from pipeline.runtime.errors import InputError
from pipeline.deploy.export import plan_export, write_export
from pipeline.evaluation.inference import save_checkpoint
from pipeline.model import TinyUNet
from pipeline.params import PAPER

TARGET_RATIO = 0.8  # end to end >= this x the model-only throughput (2 cores, 384^2, 640x480 inputs)
MODES = ("model", "serial", "overlapped")


def photo_like_images(folder: Path, n: int, width: int, height: int, fmt: str = "jpg", seed: int = 0) -> list[Path]:
    """``n`` files ``img000.<fmt>``: a smooth random background, one to three bright ellipses, sensor noise."""
    import cv2

    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    yy, xx = np.mgrid[0:height, 0:width]
    paths = [folder / f"img{i:03d}.{fmt}" for i in range(n)]
    for p in paths:
        low = rng.uniform(0, 90, (6, 8, 3)).astype(np.float32)
        img = cv2.resize(low, (width, height), interpolation=cv2.INTER_CUBIC)
        for _ in range(int(rng.integers(1, 4))):
            cy, cx = rng.uniform(0.2, 0.8) * height, rng.uniform(0.2, 0.8) * width
            ry, rx = rng.uniform(0.05, 0.3) * height, rng.uniform(0.05, 0.3) * width
            img[((yy - cy) / ry) ** 2 + ((xx - cx) / rx) ** 2 < 1] = rng.uniform(150, 250, 3)
        cv2.imwrite(str(p), np.clip(img + rng.normal(0, 6, img.shape), 0, 255).astype(np.uint8))
    return paths


def random_student(channels, seed: int = 0) -> TinyUNet:
    """A randomly initialised TinyUNet whose BatchNorm statistics are not the identity (logits vary)."""
    import torch

    torch.manual_seed(seed)
    model = TinyUNet(channels=tuple(channels))
    for mod in model.modules():
        if isinstance(mod, torch.nn.BatchNorm2d):
            mod.running_mean.uniform_(-0.2, 0.2)
            mod.running_var.uniform_(0.5, 1.5)
    return model.eval()


def build_bundle(workdir: Path, resolution: int, channels, calibration: np.ndarray) -> Path:
    """A deploy bundle of :func:`random_student` by the export code, int8 calibrated on ``calibration``, gate off."""
    import pandas as pd

    ckpt = workdir / "checkpoint"
    log = pd.DataFrame({"epoch": [1], "stage": [1], "loss": [0.0], "val_iou": [0.0], "val_bf1": [0.0], "lr": [0.0]})
    save_checkpoint(ckpt, random_student(channels), make_meta("checkpoint", "train", "bench_segment", {}), log,
                    method="random", seed=0, stage=1, selected_epoch=1, resolution=int(resolution))
    plan = plan_export(ckpt, PAPER.model_dump(), tau=0.5)
    plan = dataclasses.replace(plan, calibration_images=calibration, calibration_note=None,
                               settings={**plan.settings, "int8_settings": dataclasses.replace(
                                   plan.settings["int8_settings"], int8_min_mask_iou=0.0)})
    out = workdir / "deploy"
    write_export(plan, out, make_meta("deploy", "export", "bench_segment", plan.params, plan.inputs))
    return out


def load_engines(bundle: Path, names) -> tuple[dict, dict[str, str]]:
    """({engine: Segmenter}, {engine: why skipped}) on the CPU."""
    loaded, skipped = {}, {}
    for name in dict.fromkeys(map(engine_name, names)):
        if name not in SEGMENT_ENGINES:
            raise InputError(f"--engines: unknown engine {name!r} (expected some of {', '.join(SEGMENT_ENGINES)})")
        if name == "cuda":
            skipped[name] = "the GPU fast path: needs a CUDA device (on a CPU it is the torch engine)"
            continue
        try:
            loaded[name] = load_segmenter(bundle, name, "cpu")
        except (InputError, ImportError) as e:
            skipped[name] = str(e).splitlines()[0]
    return loaded, skipped


def time_round(seg, files, stems, work: np.ndarray, *, tau: float, resolution: int, batch: int,
               workers: int) -> dict[str, float]:
    """Seconds of one pass over the folder per mode (:data:`MODES`)."""
    out = {"model": seconds(lambda: seg.predict_probs(work, batch_size=batch))}
    for mode, w in (("serial", 0), ("overlapped", workers)):
        r = F.segment_files(seg, files, stems, tau=tau, resolution=resolution, batch_size=batch, workers=w)
        out[mode] = r.total_seconds
    return out


def summarise(times: dict[str, list[float]], n: int) -> dict:
    """images/s per mode (median and best round) and the end to end / model-only ratios of the medians
    (``<mode>_ratio``, the verdict's) and of the best rounds (``<mode>_best_ratio``)."""
    med, low = medians(times), minima(times)
    row = {mode: {"median": n / med[mode], "best": n / low[mode]} for mode in MODES}
    for mode in ("serial", "overlapped"):
        row[f"{mode}_ratio"] = row[mode]["median"] / row["model"]["median"]
        row[f"{mode}_best_ratio"] = row[mode]["best"] / row["model"]["best"]
    row["meets_target"] = row["overlapped_ratio"] >= TARGET_RATIO
    return row


def format_table(rows: dict[str, dict], skipped: dict[str, str], setting: str) -> str:
    head = (f"{'engine':14s} {'model img/s':>16s} {'serial img/s':>16s} {'overlapped img/s':>17s} "
            f"{'serial/model':>13s} {'overl./model':>13s}  target")
    lines = [setting, head, "-" * len(head)]
    for name, r in rows.items():
        cells = [f"{r[m]['median']:8.1f} ({r[m]['best']:5.1f})" for m in MODES]
        ratios = [f"{r[f'{m}_ratio']:.2f} ({r[f'{m}_best_ratio']:.2f})" for m in ("serial", "overlapped")]
        lines.append(f"{name:14s} {cells[0]:>16s} {cells[1]:>16s} {cells[2]:>17s} {ratios[0]:>13s} {ratios[1]:>13s}"
                     f"  {'met' if r['meets_target'] else 'NOT met'}")
    lines += [f"{name:14s} skipped: {why}" for name, why in skipped.items()]
    lines.append(f"(images/s: median over rounds (best round); ratios of the medians (of the best rounds); the "
                 f"verdict reads the medians.  Target: end to end >= "
                 f"{TARGET_RATIO:g} x model-only for every engine, on 2 cores at 384^2 from 640x480 -- printed, "
                 f"not asserted)")
    return "\n".join(lines)


def main(argv=None) -> dict:
    ap = parser(__doc__, repeats=3)
    ap.add_argument("--images", type=int, default=64, help="generated images in the folder")
    ap.add_argument("--size", default="640x480", help="WIDTHxHEIGHT of the generated images")
    ap.add_argument("--format", default="jpg", choices=("jpg", "png"))
    ap.add_argument("--resolution", type=int, default=384, help="the model's working resolution R")
    ap.add_argument("--channels", default="24,48,96", help="TinyUNet channels (the student's by default)")
    ap.add_argument("--batch", type=int, default=8, help="segment --batch-size (model-only uses the same)")
    ap.add_argument("--workers", type=int, default=F.IO_WORKERS, help="reader threads of the overlapped loop")
    ap.add_argument("--engines", default=",".join(n for n in SEGMENT_ENGINES if not ENGINE_TABLE[n].cuda_only),
                    help="comma-separated segment engines")
    ap.add_argument("--json", default=None, help="write the results here")
    args = ap.parse_args(argv)
    width, height = (int(v) for v in args.size.lower().split("x"))
    channels = [int(c) for c in args.channels.split(",")]
    names = [n.strip() for n in args.engines.split(",") if n.strip()]

    import torch

    with tempfile.TemporaryDirectory(prefix="bench_segment-") as td:
        td = Path(td)
        files = photo_like_images(td / "in", args.images, width, height, args.format)
        work = np.stack([resize_image(read_rgb(f), args.resolution) for f in files])
        bundle = build_bundle(td, args.resolution, channels, work[:32])
        segs, skipped = load_engines(bundle, names)
        stems = F.plan_outputs(td / "in", files, td / "out", True)
        for seg in segs.values():  # warm-up: sessions, oneDNN primitives, allocators
            seg.predict_probs(work[:args.batch], batch_size=args.batch)
        rounds = round_robin({name: (lambda i, seg=seg: time_round(
            seg, files, stems, work, tau=0.5, resolution=args.resolution, batch=args.batch, workers=args.workers))
            for name, seg in segs.items()}, max(1, args.repeats))
    times = {name: {m: [r[m] for r in rs] for m in MODES} for name, rs in rounds.items()}
    rows = {name: summarise(t, len(files)) for name, t in times.items()}
    setting = (f"bench_segment: {len(files)} {args.format} images {width}x{height} -> {args.resolution}^2, batch "
               f"{args.batch}, {args.workers} reader thread(s) + 1 writer, {args.repeats} round(s), "
               f"{os.cpu_count()} CPU(s), torch {torch.get_num_threads()} thread(s)")
    print(format_table(rows, skipped, setting))
    result = {"setting": setting, "target_ratio": TARGET_RATIO, "engines": rows, "skipped": skipped, "seconds": times}
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
