"""Teacher speed of the SAM 3 backend on the same images: the former params defaults (fp32, 2 images per forward,
eager) against ``--dtype`` / ``--batch-size`` / ``--compile`` and their answers' agreement, the encoder reused
across the six prompts against six separate calls, and the SIMULATOR; or, with ``--ray-workers``, the runner's
whole fill, serial loop against Ray Data pools (round-robin: medians, minima, steady rates and start-up).

With ``--roofline``: the teacher at the CPU's limit -- FLOPs per image for six prompts by module (vision encoder
once per image, text once per run, the six detector and mask-head passes), a per-module CPU time profile, the
host's fp32 / bf16 / AMX limits from its flags and a measured matmul peak, fp32 eager against the default path
(``teacher.dtype: auto``) round-robin with medians and minima, measured / limit, and the fidelity gate (mean mask
IoU >= 0.99 against fp32 eager with score_threshold 0, pairs of two empty masks left out). fp32 eager runs the code
of main at 3056231 (the pinned baseline of issue 65), timed beside the default path as 3056231 ran it and as it
runs now, beside the torch engine and each other ``teacher.engine`` that runs here (OpenVINO's attention, oneDNN's
fused MLPs), each with its fidelity gate; both defaults and the torch engine also get per-module times and the
shares of attention, matmul, copies and elementwise work in torch.profiler's self CPU time.  Random weights test
the numerics only, not the masks of a trained SAM 3.

    python -m benchmarks.bench_teacher [--size real --device cuda --images 16 --compile] [--ray-workers 1,2]
    python -m benchmarks.bench_teacher --roofline --size real --images 1 --repeats 2 --json reports/teacher/x.json
    python -m benchmarks.bench_teacher --batch-sweep 1,2,4,8,16,32 --size real --device cuda --dtype bf16 \\
        --paths compiled,eager --deadline 200 --json teacher_gpu.json

With ``--attention-kernels``: SAM 3's attention shapes alone, torch's bf16 kernel against ``teacher.engine: openvino``'s
(:func:`attention_kernels`).

With ``--batch-sweep`` (issue 58 item 4, reports/gpu/run.sh's ``teacher`` section): per batch size, each path's
first call (the compilation), ms per image round-robin and peak GPU memory; see :func:`batch_sweep`.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path
from unittest import mock

import numpy as np

from benchmarks.common import best_of, host_limits, host_record, medians, parser, round_robin, seconds
from pipeline.artifacts.atomic import write_json
from pipeline.artifacts.provenance import cpu
from pipeline.metrics import image_ious
from pipeline.params import PAPER_PROMPTS as PROMPTS
from pipeline.teachers import check_teacher_params
from pipeline.teachers.attention import OPENVINO_ATTENTION_EVENT, OpenVINOAttention
from pipeline.teachers.base import TeacherInput
from pipeline.teachers.distributed import ray_session
from pipeline.teachers.jobs import in_view
from pipeline.teachers.runner import open_runner
from pipeline.teachers import sam3 as sam3_module
from pipeline.teachers.sam3 import Sam3Teacher
from pipeline.teachers.simulated import SimulatedFoundationTeacher
from pipeline.teachers.tiny_sam3 import build_tiny_sam3


def main(argv: list[str] | None = None) -> None:
    ap = parser(__doc__, device="cpu", repeats=3)
    ap.add_argument("--size", choices=["tiny", "real"], default="tiny")
    ap.add_argument("--dtype", choices=["auto", "fp32", "bf16"], default="auto")
    ap.add_argument("--images", type=int, default=6)
    ap.add_argument("--resolution", type=int, default=128, help="working resolution of the input images")
    ap.add_argument("--batch-size", type=int, default=0, help="0 = from free GPU memory (2 on a CPU)")
    ap.add_argument("--compile", action="store_true", help="torch.compile the vision encoder (CUDA only)")
    ap.add_argument("--checkpoint", default=None, help="use this SAM 3 directory instead of building a random one")
    ap.add_argument("--ray-workers", default=None, metavar="N,M",
                    help="teacher throughput instead: serial loop vs a Ray Data pool of N, M ... teachers")
    ap.add_argument("--serial-threads", type=int, default=1, help="torch threads of the serial baseline")
    ap.add_argument("--input-size", type=int, default=56,
                    help="tiny SAM 3's input size (a multiple of 14); larger = more work per image")
    ap.add_argument("--roofline", action="store_true",
                    help="FLOPs, per-module profile, host limits, fp32 eager vs the default path, fidelity gate")
    ap.add_argument("--json", default=None, help="--roofline, --batch-sweep: also write the table as JSON here")
    ap.add_argument("--no-warmup", action="store_true",
                    help="--roofline: no untimed call per path first (at real size a call takes minutes, oneDNN's "
                         "per-shape set-up milliseconds)")
    ap.add_argument("--batch-sweep", default=None, metavar="1,2,4",
                    help="the GPU rows instead: per batch size, first-call (compile) seconds, ms per image and "
                         "peak GPU memory of each of --paths, round-robin (reports/gpu/run.sh's teacher section)")
    ap.add_argument("--paths", default=None, metavar="compiled,eager",
                    help="--batch-sweep: the paths timed round-robin (default: compiled with --compile, else eager)")
    ap.add_argument("--deadline", type=float, default=float("inf"),
                    help="--batch-sweep: seconds from the start after which no new batch starts")
    ap.add_argument("--attention-kernels", action="store_true",
                    help="SAM 3's attention shapes alone: torch's bf16 kernel against teacher.engine openvino's, "
                         "round-robin, with their error against fp32 (--shapes)")
    ap.add_argument("--shapes", default="real", choices=sorted(ATTENTION_SHAPES),
                    help="--attention-kernels: SAM 3's real attention shapes, or tiny ones (the smoke test)")
    args = ap.parse_args(argv)
    mode = (ray_throughput if args.ray_workers else roofline if args.roofline else
            batch_sweep if args.batch_sweep else attention_kernels if args.attention_kernels else encoder_reuse)
    mode(args)


#: SAM 3's attention calls at real size, [B, H, N, D] (one image, six prompts): the backbone's 9 windows of 24²
#: tokens and its global attention over 72² tokens (16 heads of 64), the DETR encoder's self-attention (8 of 32)
ATTENTION_SHAPES = {"real": {"backbone window": (9, 16, 576, 64), "backbone global": (1, 16, 5184, 64),
                             "DETR encoder": (6, 8, 5184, 32)},
                    "tiny": {"tiny": (2, 2, 49, 16)}}


def attention_kernels(args) -> dict:
    """torch's bf16 attention against :class:`pipeline.teachers.attention.OpenVINOAttention` on SAM 3's shapes:
    round-robin (alternating order), median and minimum seconds, GFLOP/s (Q K^T and P V) and the largest |error|
    of each against fp32 attention; Q, K and V laid out [B, N, H, D] as the model's projections leave them."""
    import torch
    import torch.nn.functional as F
    from transformers.integrations.sdpa_attention import sdpa_attention_forward

    ov = OpenVINOAttention(sdpa_attention_forward, torch.get_num_threads())
    module = torch.nn.Module()
    out = {"threads": torch.get_num_threads(), "repeats": args.repeats, "load_average_before": os.getloadavg(),
           "shapes": {}}
    for name, (b, h, n, d) in ATTENTION_SHAPES[args.shapes].items():
        g = torch.Generator().manual_seed(0)
        q, k, v = (torch.randn(b, n, h, d, generator=g).bfloat16().transpose(1, 2) for _ in range(3))
        ref = F.scaled_dot_product_attention(q.float(), k.float(), v.float()).transpose(1, 2)
        qkv = (q, k, v)
        paths = {"torch bf16": lambda a=qkv: F.scaled_dot_product_attention(*a).transpose(1, 2).contiguous(),
                 "openvino bf16": lambda a=qkv: ov(module, *a)[0]}
        error = {p: float((f().float() - ref).abs().max()) for p, f in paths.items()}  # also the warm-up
        times = round_robin({p: (lambda rep, f=f: seconds(f)) for p, f in paths.items()}, args.repeats,
                            order="alternate")
        flops = 4 * b * h * n * n * d
        row = {p: {"median_s": statistics.median(t), "min_s": min(t), "gflops": flops / statistics.median(t) / 1e9,
                   "max_abs_error_vs_fp32": error[p]} for p, t in times.items()}
        row["torch_over_openvino"] = row["torch bf16"]["median_s"] / row["openvino bf16"]["median_s"]
        out["shapes"][name] = {"shape": [b, h, n, d], **row}
        print(f"  {name} {b}x{h}x{n}x{d}: " + "; ".join(
            f"{p} median {r['median_s'] * 1e3:.1f} ms (min {r['min_s'] * 1e3:.1f}), {r['gflops']:.0f} GFLOP/s, "
            f"max |error| vs fp32 {r['max_abs_error_vs_fp32']:.1e}" for p, r in row.items() if isinstance(r, dict))
              + f"; torch / openvino {row['torch_over_openvino']:.2f}x", flush=True)
    out["load_average_after"] = os.getloadavg()
    print(f"attention kernels: {args.repeats} round-robin repeats, {out['threads']} threads, load average "
          f"{fmt_load(out['load_average_before'])} before, {fmt_load(out['load_average_after'])} after")
    if args.json:
        write_json(Path(args.json), out)
    return out


def sam3_checkpoint(args, tmp: str) -> Path:
    """``--checkpoint``, or a random SAM 3 of ``--size`` and ``--input-size`` built in ``tmp``."""
    if args.checkpoint:
        return Path(args.checkpoint)
    return build_tiny_sam3(Path(tmp) / "sam3", size=args.size, image_size=args.input_size,
                           words=tuple(w for p in PROMPTS for w in p.split()))


def encoder_reuse(args) -> None:
    """Today's path against the new one, encoder reuse against six separate calls, the SIMULATOR."""
    import torch

    rng = np.random.default_rng(0)
    r = args.resolution
    items = [TeacherInput(f"img{i}", f"sha{i}", rng.integers(0, 255, (r, r, 3), dtype=np.uint8))
             for i in range(args.images)]
    with tempfile.TemporaryDirectory() as tmp:
        ckpt = sam3_checkpoint(args, tmp)
        teacher = Sam3Teacher(ckpt, device=args.device, dtype=args.dtype, batch_size=args.batch_size,
                              resolution=(r, r), score_threshold=0.0, compile=args.compile)
        today = Sam3Teacher(ckpt, device=args.device, dtype="fp32", batch_size=2, resolution=(r, r),
                            score_threshold=0.0)
        model = teacher.load()
        n_params = sum(p.numel() for p in model.parameters())
        teacher.predict(items[:1], PROMPTS)  # warm-up (text features cached here, as in a run)
        sync = torch.cuda.synchronize if teacher.device.type == "cuda" else (lambda: None)

        paths = {"batched": teacher.predict, "separate": teacher.predict_one_prompt_at_a_time, "today": today.predict}
        calls = {k: (lambda f=f: (f(items, PROMPTS), sync())) for k, f in paths.items()}  # timed to the device's end
        for call in calls.values():  # warm-up of every path: CPU kernels and CUDA graphs are built per tensor shape
            call()
        t = {k: best_of(call, args.repeats) for k, call in calls.items()}
        m_new, s_new = teacher.predict(items, PROMPTS)
        m_old, s_old = today.predict(items, PROMPTS)
        agree = float(np.mean(image_ious(m_new.reshape(-1, r, r), m_old.reshape(-1, r, r))))
        score_diff = float(np.max(np.abs(s_new - s_old))) if s_new.size else 0.0
        del today, paths, calls  # frees the fp32 model before the simulator's timing
    m = np.zeros((r, r), bool)
    m[r // 4: r // 2, r // 4: 3 * r // 4] = True
    sim_items = [TeacherInput(it.image_id, it.image_sha256, it.image, reference={"mask": m}) for it in items]
    sim = SimulatedFoundationTeacher(resolution=(r, r))
    t_sim = best_of(lambda: sim.predict(sim_items, PROMPTS), args.repeats)

    n = args.images
    print(f"SAM 3 ({args.size}, {n_params / 1e6:.2f} M parameters, random weights) on {teacher.device} "
          f"{teacher.dtype_name}{'+tf32' if teacher.tf32 else ''} (--dtype {args.dtype}), {n} images {r}x{r}, "
          f"6 prompts, batch {teacher.batch_size}, compile {teacher.compile}, best of {args.repeats}")
    print(f"  today's path (fp32, batch 2, eager):  {t['today'] / n * 1e3:9.1f} ms/image")
    print(f"  new path:                             {t['batched'] / n * 1e3:9.1f} ms/image")
    print(f"  new / today speed-up:                 {t['today'] / t['batched']:9.2f} x  (target 25 ms/image on an H100)")
    print(f"  answers vs today: mean mask IoU {agree:.4f}, max |score difference| {score_diff:.3g}")
    print(f"  encoder reused (one pass, 6 prompts): {t['batched'] / n * 1e3:9.1f} ms/image")
    print(f"  six separate calls (baseline):        {t['separate'] / n * 1e3:9.1f} ms/image")
    print(f"  encoder-reuse speed-up:               {t['separate'] / t['batched']:9.2f} x")
    print(f"  teacher seconds per image:            {t['batched'] / n:9.4f} s")
    print(f"SIMULATOR (simulated backend):          {t_sim / n * 1e3:9.2f} ms/image")
    print("paper: SAM 3 teacher 447.9 ms/image (six prompts, RTX 4090)")


class ArrayInputs:
    """(row, view) -> TeacherInput over images held in memory (picklable: Ray's decode tasks use it)."""

    def __init__(self, images: np.ndarray):
        self.images = images
        self.shas = [hashlib.sha256(im.tobytes()).hexdigest() for im in images]

    def __call__(self, row: int, view: str) -> TeacherInput:
        return TeacherInput(f"img{row}", self.shas[row], in_view(self.images[row], view), view)


def ray_throughput(args) -> None:
    """The serial loop against Ray Data pools of teachers, round-robin (the order rotates every repeat)."""
    import torch

    pools = [int(w) for w in str(args.ray_workers).split(",")]
    r, n = args.resolution, args.images
    load = ArrayInputs(np.random.default_rng(0).integers(0, 255, (n, r, r, 3), dtype=np.uint8))
    torch.set_num_threads(args.serial_threads)
    variants = ["serial"] + [f"ray x{w}" for w in pools]
    with tempfile.TemporaryDirectory() as tmp, ray_session() as ray:
        ckpt = sam3_checkpoint(args, tmp)
        base = check_teacher_params({"backend": "sam3", "checkpoint": str(ckpt), "dtype": args.dtype,
                                     "batch_size": args.batch_size or 2, "prompts": PROMPTS,
                                     "vflip_base_prompt": False})

        def fill(rep: int, v: str) -> tuple[float, float, float]:
            """(wall seconds, steady images/s, start-up seconds) of one fill into a fresh cache."""
            cfg = {**base, "cache_dir": str(Path(tmp) / f"cache-{rep}-{v.replace(' ', '')}")}
            t0, t0_wall = time.perf_counter(), time.time()  # wall clock: compared with file times
            runner, _ = open_runner(cfg, (r, r), args.device, load, load.shas)
            stats = runner.fill(range(n), workers=0 if v == "serial" else int(v.split("x")[1]))
            wall = time.perf_counter() - t0
            assert stats.answers_computed == n * len(PROMPTS), stats
            stamps = sorted(p.stat().st_mtime for p in Path(cfg["cache_dir"]).rglob("*.tce"))  # entries written
            return wall, steady_rate(stamps, len(PROMPTS)), stamps[0] - t0_wall

        res = round_robin({v: (lambda rep, v=v: fill(rep, v)) for v in variants}, args.repeats, order="rotate")
        cpus = ray.cluster_resources().get("CPU", 0)
    times, steady, startup = ({v: [x[k] for x in res[v]] for v in variants} for k in range(3))
    med, steady_med, startup_med = medians(times), medians(steady), medians(startup)
    one = variants[1] if len(variants) > 1 else None
    print(f"teacher throughput, SAM 3 {args.size} (random weights, input {args.input_size}) on {args.device}, "
          f"{n} images {r}x{r}, {len(PROMPTS)} prompts, {args.repeats} round-robin repeats; "
          f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {platform.node()}, {os.cpu_count()} cores, "
          f"Ray sees {cpus:g} CPUs, load average {' '.join(f'{x:.1f}' for x in os.getloadavg())}")
    for v in variants:
        rel = f"  {med[one] / med[v]:5.2f}x the 1-worker pool" if one and v.startswith("ray") else ""
        print(f"  {v:9s} wall median {med[v]:7.2f} s ({n / med[v]:6.1f} images/s), min {min(times[v]):7.2f} s{rel}  "
              f"[{', '.join(f'{t:.2f}' for t in times[v])}]")
    for v in variants:
        rel = f"  {steady_med[v] / steady_med[one]:5.2f}x the 1-worker pool" if one and v.startswith("ray") else ""
        print(f"  {v:9s} steady median {steady_med[v]:6.1f} images/s, max {max(steady[v]):6.1f}{rel}  "
              f"[{', '.join(f'{x:.1f}' for x in steady[v])}]")
    for v in variants:
        print(f"  {v:9s} start-up median {startup_med[v]:6.2f} s (fill start to first entry)  "
              f"[{', '.join(f'{x:.2f}' for x in startup[v])}]")
    if len(variants) > 2:
        print("  projected whole fill, start-up + images / steady rate (medians above; a model, not a measurement):")
        for images in (n, 10 * n, 100_000):
            walls = {v: startup_med[v] + images / steady_med[v] for v in variants[1:]}
            print(f"    {images:7d} images: " + ", ".join(f"{v} {walls[one] / w:4.2f}x" for v, w in
                                                     list(walls.items())[1:]) + " the 1-worker pool")
    print("wall: the whole fill (a Ray fill includes starting its actors, which import torch and transformers and "
          "load the model); steady: images whose entries were written after the first entry, over the time from "
          "the first to the last write (the pool's throughput); start-up: paid once per fill, the actors starting "
          "side by side, so the whole-fill ratio approaches the steady one as the number of images grows")
    print("target: 2 workers >= 1.7x one worker")


def steady_rate(stamps: list[float], per_image: int) -> float:
    """Images per second from the cache's sorted write times: entries written after the first one (its
    job's burst excluded), divided by the time from the first write to the last (start-up excluded)."""
    later = sum(1 for t in stamps if t > stamps[0] + 1e-3)
    span = stamps[-1] - stamps[0]
    return later / per_image / span if span > 0 else float("nan")


#: the fidelity gate of a faster teacher path against fp32 eager (issue 58): mean mask IoU over the pairs that are
#: not both empty, and the largest score difference allowed (scores are products of two sigmoids, in [0, 1])
GATE_IOU, GATE_SCORE = 0.99, 0.02


def fidelity(masks, scores, ref_masks, ref_scores) -> dict:
    """The fidelity gate of ``masks`` / ``scores`` against the reference path's (fp32 eager, score_threshold 0):
    mean IoU over the (image, prompt) pairs where either mask has a pixel -- two empty masks agree trivially
    and would inflate the figure, so they are counted apart --, the largest |score difference|, and pass."""
    a = np.asarray(masks, bool).reshape(-1, *np.shape(masks)[-2:])
    b = np.asarray(ref_masks, bool).reshape(a.shape)
    both_empty = ~(a | b).any(axis=(1, 2))
    ious = image_ious(a, b)[~both_empty]
    mean_iou = float(ious.mean()) if ious.size else float("nan")
    score_diff = float(np.max(np.abs(np.asarray(scores, np.float64) - np.asarray(ref_scores, np.float64))))
    return {"mean_iou": mean_iou, "min_iou": float(ious.min()) if ious.size else float("nan"),
            "pairs": int(a.shape[0]), "pairs_both_empty": int(both_empty.sum()), "max_score_diff": score_diff,
            "passes": bool(ious.size and mean_iou >= GATE_IOU and score_diff <= GATE_SCORE)}


def sdpa_cpu_flops(query_shape, key_shape, value_shape, *args, out_shape=None, **kwargs) -> int:
    """FLOPs of the CPU flash-attention kernel, which torch's counter does not know: Q K^T and P V."""
    from torch.utils.flop_counter import sdpa_flop_count

    return sdpa_flop_count(query_shape, key_shape, value_shape)


def module_flops(teacher, items, prompts) -> dict:
    """FLOPs of one call of ``teacher.predict`` per top-level module (torch's counter plus CPU attention); the
    text features counted apart on a fresh tokenisation (once per run)."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    model = teacher.load()
    mapping = {torch.ops.aten._scaled_dot_product_flash_attention_for_cpu: sdpa_cpu_flops}
    teacher._text.clear()
    with FlopCounterMode(display=False, custom_mapping=mapping) as counter:
        teacher.text_features(prompts)
    text = counter.get_total_flops()
    with FlopCounterMode(display=False, custom_mapping=mapping) as counter:
        teacher.predict(items, prompts)
    top = {name for name, _ in model.named_children()}
    flops = {}  # the tracker names a module by its call path: Sam3Model.detr_encoder, Sam3VisionModel.backbone
    for k, v in counter.get_flop_counts().items():
        parts = k.split(".")
        if len(parts) == 2 and parts[1] in top | {"backbone", "neck"}:
            flops[parts[1]] = int(sum(v.values()))
    flops["total"] = int(counter.get_total_flops())
    flops["text_encoder (once per run)"] = int(text)
    return flops


#: how :func:`module_times_and_shares` sorts torch.profiler's operators (self CPU time); anything else is "other"
#: (normalisations, upsampling, reductions, the profiler's own rows)
OP_KINDS = {
    "attention": ("aten::_scaled_dot_product_flash_attention_for_cpu", "aten::_scaled_dot_product_attention_math",
                  "aten::_softmax", OPENVINO_ATTENTION_EVENT),
    "matmul": ("aten::addmm", "aten::mm", "aten::bmm", "aten::mkldnn_convolution", "aten::_mkldnn_linear",
               "aten::mkldnn_linear"),
    "copies": ("aten::copy_", "aten::cat", "aten::fill_", "aten::zero_", "aten::index_select", "aten::index",
               "aten::repeat_interleave", "aten::clone", "aten::_to_copy", "aten::flip", "aten::constant_pad_nd"),
    "elementwise": ("aten::add", "aten::add_", "aten::mul", "aten::mul_", "aten::sub", "aten::div", "aten::neg",
                    "aten::clamp_min", "aten::clamp", "aten::gelu", "aten::relu", "aten::sigmoid", "aten::sin",
                    "aten::cos", "aten::sign", "aten::abs", "aten::log2", "aten::log", "aten::exp", "aten::pow",
                    "aten::rsub", "aten::where", "aten::gt", "aten::lt"),
}


def module_times_and_shares(teacher, items, prompts) -> tuple[dict, dict, float]:
    """One call of ``teacher.predict`` under torch.profiler: wall seconds per top-level module (between its
    forward hooks), the share of self CPU time per :data:`OP_KINDS` kind, and the call's wall seconds (the
    profiler adds a little to it)."""
    import torch

    model = teacher.load()
    times: dict[str, float] = {}
    hooks = []
    for name, child in model.named_children():
        def pre(mod, args, name=name):
            times[name] = times.get(name, 0.0) - time.perf_counter()

        def post(mod, args, out, name=name):
            times[name] += time.perf_counter()
        hooks += [child.register_forward_pre_hook(pre), child.register_forward_hook(post)]
    t0 = time.perf_counter()
    try:
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
            teacher.predict(items, prompts)
    finally:
        for h in hooks:
            h.remove()
    wall = time.perf_counter() - t0
    kind_of = {op: kind for kind, ops in OP_KINDS.items() for op in ops}
    self_s: dict[str, float] = {kind: 0.0 for kind in [*OP_KINDS, "other"]}
    for row in prof.key_averages():
        if row.key.startswith("aten::") or row.key == OPENVINO_ATTENTION_EVENT:
            self_s[kind_of.get(row.key, "other")] += row.self_cpu_time_total / 1e6
    total = sum(self_s.values()) or 1.0
    return times, {k: {"seconds": v, "share": v / total} for k, v in self_s.items()}, wall


#: the roofline's paths: fp32 eager and the default as the code of 3056231 ran them (:class:`AsOf3056231`, the
#: pinned baseline of issue 65), the default dtype with torch's attention (``teacher.engine: torch``: the exact
#: savings only), and the default path as it runs now (``teacher.engine: auto``); then each other engine that can
#: run here (:func:`engine_path`)
FP32, OLD_DEFAULT, TORCH_ENGINE, DEFAULT = "fp32 eager", "default at 3056231", "torch attention", "default"
#: the engines the roofline tries beside the default's (``teacher.engine``), each as its own path where it runs here
OTHER_ENGINES = ("openvino", "onednn")


def engine_path(engine: str) -> str:
    """Name the roofline's path of ``teacher.engine: <engine>``."""
    return f"engine {engine}"
#: the roofline's targets for default / fp32 eager (medians), by host kind (issue 65)
TARGETS = "<= 0.35 on avx512_bf16, <= 0.25 on AMX, <= 1 on AVX2"


def roofline(args) -> None:
    """fp32 eager (3056231's code) against the default path of 3056231 and today's (round-robin, the same images,
    threads, batch and input size), the FLOPs of the default path, per-module times and op-kind shares of both
    defaults, the host's limits, measured / limit, the gate."""

    rng = np.random.default_rng(0)
    r = args.resolution
    items = [TeacherInput(f"img{i}", f"sha{i}", rng.integers(0, 255, (r, r, 3), dtype=np.uint8))
             for i in range(args.images)]
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        ckpt = sam3_checkpoint(args, tmp)
        kw = dict(device=args.device, batch_size=args.batch_size or 1, resolution=(r, r), score_threshold=0.0)
        default = Sam3Teacher(ckpt, dtype=args.dtype, **kw)
        torch_engine = Sam3Teacher(ckpt, dtype=args.dtype, engine="torch", **kw)
        paths = {FP32: AsOf3056231(Sam3Teacher(ckpt, dtype="fp32", engine="torch", **kw)),
                 OLD_DEFAULT: AsOf3056231(torch_engine), TORCH_ENGINE: torch_engine, DEFAULT: default}
        for engine in OTHER_ENGINES:  # each engine tried, where it runs here and is not the default's
            other = Sam3Teacher(ckpt, dtype=args.dtype, engine=engine, **kw)
            if other.engine == engine != default.engine:
                paths[engine_path(engine)] = other
        for t in paths.values():
            t.load()
            t.text_features(PROMPTS)  # once per run, as in a run
            if not args.no_warmup:
                t.predict(items[:1], PROMPTS)  # oneDNN primitives are made per shape and dtype
        n_params = sum(p.numel() for p in default.load().parameters())
        answers = {}

        def call(name):
            t0 = time.perf_counter()
            answers[name] = paths[name].predict(items, PROMPTS)
            return time.perf_counter() - t0

        times = round_robin({k: (lambda rep, k=k: call(k)) for k in paths}, args.repeats, order="alternate")
        gates = {k: fidelity(*answers[k], *answers[FP32]) for k in paths if k not in (FP32, OLD_DEFAULT)}
        gate, gate_torch = gates[DEFAULT], gates[TORCH_ENGINE]
        same = all(np.array_equal(a, b) for a, b in zip(answers[TORCH_ENGINE], answers[OLD_DEFAULT]))
        flops = module_flops(torch_engine, items, PROMPTS)  # torch's counter does not see OpenVINO's attention
        profiled = {k: module_times_and_shares(paths[k], items, PROMPTS) for k in (OLD_DEFAULT, TORCH_ENGINE, DEFAULT)}
        limits = host_limits()
        default_dtype, default_path = default.dtype_name, default.path()
        model_input = "x".join(map(str, default.input_size))  # the processor's size: 1008 at real size
    n = args.images
    med = {k: v / n for k, v in medians(times).items()}
    low = {k: min(v) / n for k, v in times.items()}
    per_image = {k: v / n for k, v in flops.items() if not k.startswith("text_encoder") and k != "total"}
    image_flops = flops["total"] / n
    peak = {k: limits["bf16_gflops"] if paths_dtype(paths, k) == "bf16" else limits["fp32_gflops"] for k in paths}
    host = {**host_record(), "load_average_before": load_before, "load_average_after": os.getloadavg()}
    print(f"teacher roofline: SAM 3 {args.size} ({n_params / 1e6:.0f} M parameters, random weights: numerics "
          f"only), {n} image(s) {r}x{r} -> input {model_input}, {len(PROMPTS)} prompts, batch "
          f"{kw['batch_size']}, {args.repeats} round-robin repeats on {args.device}")
    print(f"  host {host['cpu']}, {host['logical_cpus']} logical CPUs, torch threads {host['torch_threads']}, flags "
          f"{' '.join(host['flags'])}; {host['date']}; load average {fmt_load(load_before)} before, "
          f"{fmt_load(host['load_average_after'])} after (other processes share the cores)")
    print(f"  limits (measured {2048}^3 matmul, best / median): fp32 {limits['fp32_gflops']:.0f} / "
          f"{limits['fp32_gflops_median']:.0f} GFLOP/s; bf16 "
          + (f"{limits['bf16_gflops']:.0f} / {limits['bf16_gflops_median']:.0f} GFLOP/s" if limits["bf16_gflops"]
             else "n/a (not native here)")
          + f"; AMX {'%.0f GFLOP/s' % limits['amx_gflops'] if limits['amx_gflops'] else 'n/a (no amx_bf16)'}")
    print(f"  FLOPs per image, {len(PROMPTS)} prompts: {image_flops / 1e12:.2f} TFLOP "
          + ", ".join(f"{k} {v / 1e9:.4g} G" for k, v in sorted(per_image.items(), key=lambda kv: -kv[1]))
          + f"; text once per run {flops['text_encoder (once per run)'] / 1e9:.4g} G")
    for k, (module_s, shares, wall) in profiled.items():
        print(f"  per-module wall time, {k} ({paths_dtype(paths, k)}), one profiled call of {wall:.1f} s: "
              + ", ".join(f"{m} {v:.1f} s" for m, v in sorted(module_s.items(), key=lambda kv: -kv[1])))
        print("    shares of self CPU time: " + ", ".join(f"{kind} {v['share']:.0%} ({v['seconds']:.1f} s)"
                                                          for kind, v in shares.items()))
    for k in paths:
        att = image_flops / med[k] / 1e9
        print(f"  {k:18s} ({paths_dtype(paths, k)}): median {med[k]:8.2f} s/image, min {low[k]:8.2f}  "
              f"[{', '.join(f'{t / n:.2f}' for t in times[k])}]  {att:6.1f} GFLOP/s = "
              f"{att / peak[k]:.2f} of the {paths_dtype(paths, k)} matmul peak")
    ratio, ratio_old = med[DEFAULT] / med[FP32], med[OLD_DEFAULT] / med[FP32]
    pairs = [d / f for d, f in zip(times[DEFAULT], times[FP32])]
    print(f"  {DEFAULT} ({default_path}) / {FP32} (medians): {ratio:.3f}  (targets {TARGETS}); per round-robin "
          f"pair {', '.join(f'{x:.3f}' for x in pairs)}; {OLD_DEFAULT} / {FP32}: {ratio_old:.3f}; {TORCH_ENGINE} / "
          f"{FP32}: {med[TORCH_ENGINE] / med[FP32]:.3f}; {DEFAULT} / {OLD_DEFAULT}: "
          f"{med[DEFAULT] / med[OLD_DEFAULT]:.3f}")
    for k in paths:
        if k.startswith("engine "):
            print(f"  {k} / {FP32} (medians): {med[k] / med[FP32]:.3f}; / {DEFAULT}: {med[k] / med[DEFAULT]:.3f}")
    for name, g in gates.items():
        print(f"  fidelity of {name} vs fp32 eager: mean mask IoU {g['mean_iou']:.4f} over "
              f"{g['pairs'] - g['pairs_both_empty']} pairs (min {g['min_iou']:.4f}; {g['pairs_both_empty']} pairs "
              f"both empty, left out), max |score difference| {g['max_score_diff']:.2e}; gate (IoU >= {GATE_IOU}, "
              f"scores within {GATE_SCORE}): {'passes' if g['passes'] else 'FAILS'}")
    print(f"  {TORCH_ENGINE} against {OLD_DEFAULT}: answers {'identical' if same else 'DIFFERENT'} (masks and scores)")
    if args.json:
        doc = {"host": host, "limits": limits, "model": {"size": args.size, "parameters": n_params,
               "weights": "random", "input": model_input}, "images": n, "resolution": r,
               "prompts": len(PROMPTS), "batch_size": kw["batch_size"], "repeats": args.repeats,
               "default_dtype": default_dtype, "default_path": default_path, "seconds": times, "median_s_per_image": med, "min_s_per_image": low,
               "default_over_fp32": ratio, "default_over_fp32_pairs": pairs, "old_default_over_fp32": ratio_old,
               "targets": TARGETS, "flops_per_image": per_image,
               "text_flops_per_run": flops["text_encoder (once per run)"],
               "module_seconds": {k: v[0] for k, v in profiled.items()},
               "op_shares": {k: v[1] for k, v in profiled.items()}, "fidelity": gate,
               "fidelity_torch_attention": gate_torch, "torch_attention_identical_to_3056231": same,
               "fidelity_by_path": gates, "paths": {k: paths[k].path() for k in paths}}
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(doc, indent=1) + "\n")
        print(f"  written {args.json}")


def fmt_load(load) -> str:
    return " ".join(f"{x:.1f}" for x in load)


def _repeat_vision_copies(vision, k: int):
    """``Sam3Teacher._repeat_vision`` as of 3056231: every FPN level and position encoding copied per prompt."""
    from transformers.models.sam3.modeling_sam3 import Sam3VisionEncoderOutput

    rep = lambda ts: tuple(t.repeat_interleave(k, dim=0) for t in ts)  # noqa: E731
    return Sam3VisionEncoderOutput(last_hidden_state=vision.last_hidden_state,
                                   fpn_hidden_states=rep(vision.fpn_hidden_states),
                                   fpn_position_encoding=rep(vision.fpn_position_encoding))


class AsOf3056231:
    """A teacher run with the code of main at 3056231, pinned as the baseline of issue 65: transformers' SAM 3
    without :func:`pipeline.teachers.sam3.exact_savings`, every FPN level repeated per prompt (the DETR encoder's
    first self-attention once per image, as at 3056231)."""

    def __init__(self, teacher: Sam3Teacher):
        self.teacher = teacher

    def __getattr__(self, name):
        return getattr(self.teacher, name)

    def predict(self, items, prompts):
        none = lambda model: contextlib.nullcontext()  # noqa: E731
        with mock.patch.object(sam3_module, "exact_savings", none), \
                mock.patch.object(Sam3Teacher, "_repeat_vision", staticmethod(_repeat_vision_copies)):
            return self.teacher.predict(items, prompts)


def paths_dtype(paths, k) -> str:
    return paths[k].dtype_name


def batch_sweep(args, clock=time.perf_counter) -> dict:
    """The real-size teacher on a GPU (issue 58 item 4; reports/gpu/run.sh's ``teacher`` section): per batch size
    ``b`` of ``--batch-sweep``, one call of ``b`` images (one forward, six prompts) per path of ``--paths``
    (compiled = ``teacher.compile``, eager) untimed first -- its seconds are reported: they hold the compilation of
    that shape -- then ``--repeats`` round-robin rounds of one call per path: medians and minima in ms per image,
    and per path the peak memory (``torch.cuda.max_memory_allocated``, reset before each timed call) less the
    memory held before the call (both paths' weights) as ``activation_peak_bytes``.

    A batch that runs out of GPU memory stops the sweep; ``--deadline`` seconds from the start stop it before the
    next batch (``stopped`` says which).  The ``--json`` document is rewritten atomically after every batch, so
    a run killed from outside keeps what finished.  On a CPU there is no compile (Sam3Teacher turns it off, and
    ``compile_active`` says so) and no peak memory: there it is the logic's test, not a measurement."""
    import torch

    t_start = clock()
    cuda = torch.device(args.device).type == "cuda"
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    r = args.resolution
    batches = [int(b) for b in str(args.batch_sweep).split(",")]
    path_names = [p.strip() for p in str(args.paths or ("compiled" if args.compile else "eager")).split(",")]
    bad = [p for p in path_names if p not in ("compiled", "eager")]
    if bad or not path_names:
        raise SystemExit(f"bench_teacher: --paths {args.paths!r}: expected a comma-separated subset of compiled,eager")
    card = torch.cuda.get_device_name() if cuda else cpu()["model"]
    record = {"what": "real-size SAM 3 teacher (random weights: cost only, not answers), six prompts, "
                      f"{args.dtype}, Sam3Teacher.predict of b images per call at each batch b; medians and minima "
                      f"of {args.repeats} round-robin calls per path",
              "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "device": args.device, "card": card,
              "host": platform.node(), "torch": torch.__version__, "cuda": torch.version.cuda, "size": args.size,
              "dtype": args.dtype, "resolution": r, "repeats": args.repeats, "batches_asked": batches,
              "paths_asked": path_names, "prompts": list(PROMPTS), "batches": {}, "stopped": None, "finished": False}
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        tb = clock()
        ckpt = sam3_checkpoint(args, tmp)
        record["build_s"] = round(clock() - tb, 1)
        teachers, tl = {}, clock()
        for name in path_names:
            t = Sam3Teacher(ckpt, device=args.device, dtype=args.dtype, batch_size=1, resolution=(r, r),
                            score_threshold=0.0, compile=(name == "compiled"))
            model = t.load()
            t.text_features(PROMPTS)  # once per run, as in a run
            teachers[name] = t
            record.setdefault("compile_active", {})[name] = bool(t.compile)
            record["parameters"] = sum(q.numel() for q in model.parameters())
            record["weights_bytes"] = sum(q.numel() * q.element_size() for q in model.parameters())
        record["dtype_used"] = {name: t.dtype_name for name, t in teachers.items()}
        record["load_s"] = round(clock() - tl, 1)
        for b in batches:
            if clock() - t_start > args.deadline:
                record["stopped"] = f"deadline ({args.deadline:.0f} s) before batch {b}"
                break
            items = [TeacherInput(f"img{i}", f"sha{i}", rng.integers(0, 255, (r, r, 3), dtype=np.uint8))
                     for i in range(b)]
            row: dict = {"paths": {}}

            try:
                for name, t in teachers.items():
                    t.batch_size = b  # one forward of all b images
                    t0 = clock()
                    t.predict(items, PROMPTS)  # compiles this shape on the compiled path
                    sync()
                    row["paths"][name] = {"first_call_s": round(clock() - t0, 3), "peak_allocated_bytes": None,
                                          "activation_peak_bytes": None}
                times = round_robin({n: (lambda rep, n=n, items=items, row=row: timed_call(
                    teachers[n], items, row["paths"][n], cuda, clock)) for n in teachers}, args.repeats,
                    order="alternate")
            except torch.cuda.OutOfMemoryError as e:
                record["stopped"] = f"out of memory at batch {b}: {str(e).splitlines()[0][:160]}"
                torch.cuda.empty_cache()
                break
            for name, p in row["paths"].items():
                p["seconds"] = times[name]
                p["ms_per_image_median"] = statistics.median(times[name]) / b * 1e3
                p["ms_per_image_min"] = min(times[name]) / b * 1e3
            if {"compiled", "eager"} <= set(row["paths"]):
                row["eager_over_compiled_median"] = (row["paths"]["eager"]["ms_per_image_median"]
                                                     / row["paths"]["compiled"]["ms_per_image_median"])
            record["batches"][str(b)] = row
            print(f"  batch {b:3d}: " + "; ".join(
                f"{n} median {p['ms_per_image_median']:9.1f} ms/image, min {p['ms_per_image_min']:9.1f}, first call "
                f"{p['first_call_s']:8.2f} s, peak {fmt_gib(p['activation_peak_bytes'])}"
                for n, p in row["paths"].items()), flush=True)
            if args.json:
                write_json(args.json, record)
    record["finished"] = record["stopped"] is None
    done = sorted(int(b) for b in record["batches"])
    print(f"teacher batch sweep: SAM 3 {args.size} (random weights), {args.dtype}, paths {', '.join(path_names)} "
          f"(compile active: {record.get('compile_active')}), {len(PROMPTS)} prompts, {args.repeats} round-robin "
          f"repeats on {card}, {record['date_utc']}; batches {done}"
          + (f"; stopped: {record['stopped']}" if record["stopped"] else ""), flush=True)
    for name in path_names:
        if len(done) > 1:
            first, last = (record["batches"][str(b)]["paths"][name]["ms_per_image_median"] for b in (done[0], done[-1]))
            print(f"  {name}: batch {done[-1]} / batch {done[0]} time per image: {last / first:.2f} x")
    if args.json:
        write_json(args.json, record)
    return record


def timed_call(teacher, items, path: dict, cuda: bool, clock=time.perf_counter) -> float:
    """Seconds of one ``teacher.predict(items)``; on CUDA, ``path``'s peak memory (total, and above what was held
    before the call) raised to this call's."""
    import torch

    if cuda:
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
        before = torch.cuda.memory_allocated()
    t0 = clock()
    teacher.predict(items, PROMPTS)
    if cuda:
        torch.cuda.synchronize()
    seconds = clock() - t0
    if cuda:
        peak = torch.cuda.max_memory_allocated()
        path["peak_allocated_bytes"] = max(path["peak_allocated_bytes"] or 0, peak)
        path["activation_peak_bytes"] = max(path["activation_peak_bytes"] or 0, peak - before)
    return seconds


def fmt_gib(n: int | None) -> str:
    return "n/a (not CUDA)" if n is None else f"{n / 2 ** 30:.2f} GiB above the weights"


if __name__ == "__main__":
    main()
