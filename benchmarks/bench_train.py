"""Training speed of Stage-I ``plain`` at ``distill``'s settings: images per second of fp32 eager NCHW against
``distill``'s resolved settings (its ``train.precision`` autocast on this host and ``train.channels_last``), at each
``--sizes`` side and ``distill``'s batch size, each epoch timed round-robin (medians and minima, absolute seconds),
each variant's run in a spawned process of its own (``--in-process``: all in this one) with the heap reused between
steps as ``train()`` has it (:func:`pipeline.runtime.device.reuse_freed_memory`);
then a profile of one step at ``--profile-size``: FLOPs per step against the host's measured matmul peak
(:func:`benchmarks.common.host_limits`) and where the step's time goes (data, augmentation, normalisation, forward,
loss, backward, optimizer).  Both variants train the loop's own epochs (:func:`pipeline.training.loop.train_epoch`)
on an in-memory synthetic set (ellipse + bar on noise), with ``distill``'s augmentation; only the precision and the
memory format differ.  ``--compile`` adds ``distill``'s settings with ``torch.compile`` of the model's training
forward (and so its backward), and reports its final loss beside eager's; ``--batches N ...`` adds ``distill``'s
settings at each other batch size to the same round-robin (does a larger batch feed the matrix units faster? images
per second; the learning rate that batch needs is a training question, not timed here); ``--epochs N`` trains each
variant N epochs and scores held-out images (validation Image IoU / Boundary F1).

    python -m benchmarks.bench_train [--sizes 64 128 384] [--threads 2] [--reps 3] [--compile] [--batches 16 32]
        [--in-process] [--out FILE]
"""

from __future__ import annotations

import copy
import json
import math
import multiprocessing as mp
import statistics
import time
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from benchmarks.common import host_limits, parser, round_robin
from pipeline.methods import STAGE_ONE, get_method
from pipeline.runtime.device import resolve_device, reuse_freed_memory
from pipeline.training.inputs import TrainData, ValData
from pipeline.training.checkpointing import NoCheckpointer
from pipeline.artifacts.atomic import write_json
from pipeline.augment import augment_batch
from pipeline.methods import resolve_plan
from pipeline.params import PAPER
from pipeline.profiles import load_profile
from pipeline.runtime.device import autocast

PAPER_IMAGES = 270
#: the profile whose settings are timed against fp32 eager NCHW
PROFILE = "distill"
BASELINE = "fp32 eager NCHW"
#: the phases of one training step, in order (:func:`step_profile`)
PHASES = ("data", "augmentation", "normalisation", "forward", "loss", "backward", "optimizer")


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


def train_data(images: np.ndarray, masks: np.ndarray) -> TrainData:
    """Stage-I rows of ``images`` with ``masks`` as their targets (every gate 1)."""
    n = len(images)
    return TrainData(image_ids=[f"b{i}" for i in range(n)], images=images, mask=masks,
                     area=masks.reshape(n, -1).mean(1).astype(np.float32), gate=np.ones(n, np.float32))


def batch_variant(batch: int) -> str:
    """The name of :data:`PROFILE`'s settings at another batch size (``--batches``)."""
    return f"{PROFILE} @ batch {batch}"


def variants(overrides: list[str] = (), batches: list[int] = ()) -> dict[str, dict]:
    """``{name: train section}``: fp32 eager NCHW and :data:`PROFILE`'s own settings, both with the rest of
    :data:`PROFILE`'s train section; every epoch at the timed side (no half-side epochs), no stopping rule.
    Each of ``batches`` other than the profile's own adds :data:`PROFILE`'s settings at that batch size
    (:func:`batch_variant`)."""

    train = load_profile(PROFILE, overrides)["train"]
    train.update({"num_threads": 0, "low_res_fraction": 0.0, "until": "epochs", "epochs_stage1": 10_000})
    out = {BASELINE: {**train, "precision": "fp32", "channels_last": False}, PROFILE: train}
    out.update({batch_variant(b): {**train, "batch_size": int(b)} for b in batches if b != train["batch_size"]})
    return out


def open_run(cfg: Mapping[str, Any], data: TrainData, device, seed: int, compiled: bool = False):
    """A training run of ``plain`` set up as :func:`pipeline.training.loop.train` sets it up (``compiled``: its
    model's ``forward_train`` through ``torch.compile``), ready for :func:`pipeline.training.loop.train_epoch`."""
    import torch

    from pipeline.training import loop
    from pipeline.training.settings import Settings

    method = get_method(STAGE_ONE)
    s = Settings.from_params(method, cfg, PAPER.calibrate.fixed_tau)
    run = loop.setup_run(method, cfg, s, resolve_plan(method, cfg, None), data, seed, None, torch.device(device))
    if compiled:
        run.model.forward_train = torch.compile(run.model.forward_train)
    return run


def epoch_timer(run) -> Callable[[int], float]:
    """A round-robin case: train ``run``'s next epoch (the loop's own) and return its wall seconds.

    Its ``state`` holds the run's ``autocast`` and the last epoch's ``loss``; ``close()`` does nothing (as
    :func:`process_timer`'s, which ends its process)."""
    from pipeline.training import loop

    state = {"epoch": 0, "autocast": run.run_key["autocast"]}

    def one(_round: int) -> float:
        state["epoch"] += 1
        t0 = time.perf_counter()
        row = loop.train_epoch(run, state["epoch"], None, None)
        state["loss"] = row["loss"]
        return time.perf_counter() - t0

    one.state, one.close = state, lambda: None
    return one


def _serve_epochs(conn, cfg: Mapping[str, Any], size: int, n_images: int, seed: int, device: str, threads: int,
                  compiled: bool) -> None:
    """A spawned process's loop: open the run, then train one epoch per ``"epoch"`` received, until ``"stop"``."""
    import torch

    try:
        if threads:
            torch.set_num_threads(threads)
        reuse_freed_memory(device)  # as train() does
        one = epoch_timer(open_run(cfg, train_data(*synthetic_set(n_images, size, seed)), device, seed, compiled))
        conn.send(("ready", one.state["autocast"]))
        while conn.recv() == "epoch":
            seconds = one(0)
            conn.send(("epoch", (seconds, one.state["loss"])))
    except Exception as e:  # handed to the parent, which raises it
        conn.send(("error", f"{type(e).__name__}: {e}"))


def process_timer(cfg: Mapping[str, Any], size: int, n_images: int, seed: int, device: str, threads: int,
                  compiled: bool = False) -> Callable[[int], float]:
    """A round-robin case whose run lives in a spawned process of its own: one epoch per call, its wall seconds.

    Timed in-process, one variant's freed memory, allocator thresholds and caches shaped the next variant's epoch
    (glibc raises its mmap threshold when a large block is freed, so the fp32 variant's frees spared ``distill``'s
    epochs page faults that a ``distill`` process alone pays).  Each process times what a training process of its
    own gets.  ``state`` as :func:`epoch_timer`'s; ``close()`` ends the process.
    """
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_serve_epochs, args=(child, dict(cfg), size, n_images, seed, device, threads, compiled),
                       daemon=True)
    proc.start()

    def reply():
        kind, value = parent.recv()
        if kind == "error":
            proc.join()
            raise RuntimeError(f"bench_train worker ({size}², {cfg['precision']}): {value}")
        return value

    state: dict[str, Any] = {}

    def one(_round: int) -> float:
        if "autocast" not in state:  # the processes start side by side; each is waited for at its first epoch
            state["autocast"] = reply()
        parent.send("epoch")
        seconds, state["loss"] = reply()
        return seconds

    def close() -> None:
        if proc.is_alive():
            parent.send("stop")
        proc.join()

    one.state, one.close = state, close
    return one


def speed_rows(times: Mapping[str, list[float]], n_images: int, batches: Mapping[str, int]) -> dict[str, dict]:
    """Per variant: its epoch seconds, their median and minimum, images per second of each and seconds a step
    (``batches``: each variant's batch size)."""
    return {name: {"epoch_seconds": list(t), "median_seconds": statistics.median(t), "min_seconds": min(t),
                   "images_per_second": n_images / statistics.median(t), "images_per_second_best": n_images / min(t),
                   "batch_size": batches[name], "seconds_per_step": statistics.median(t) / -(-n_images // batches[name])}
            for name, t in times.items()}


def step_flops(run, size: int) -> int:
    """FLOPs of one training step's forward and backward (``torch.utils.flop_counter``) at ``run``'s batch size
    and side ``size``, under ``run``'s autocast and memory format; the optimizer's elementwise work is not counted."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    from pipeline import losses

    model = copy.deepcopy(run.model)
    fmt = torch.channels_last if run.settings.channels_last else torch.contiguous_format
    x = torch.rand(run.settings.batch_size, 3, size, size).contiguous(memory_format=fmt)
    y = (torch.rand(run.settings.batch_size, 1, size, size) > 0.5).float()
    b = {"x": x, "mask": y, "gate": torch.ones(len(x)), "area": y.mean((1, 2, 3))}
    with FlopCounterMode(display=False) as counter:
        with autocast(run.device, run.amp):
            out = model.forward_train(x)
        losses.refine_loss(out, b, b["gate"], run.plan.weights, run.settings.constants)["loss"].backward()
    return int(counter.get_total_flops())


def step_profile(run, steps: int) -> dict[str, list[float]]:
    """Wall seconds of each of :data:`PHASES` in each of ``steps`` training steps of ``run``, composed of the
    loop's own pieces in the loop's order (the batch is checked against the loop's :func:`augmented_batch` /
    :func:`make_batch` so the profile cannot drift from it); ``step``: the phases' sum."""
    import torch

    from pipeline import losses
    from pipeline.training import loop

    s, n = run.settings, run.n_train
    order = np.random.default_rng([run.seed, 0]).permutation(n)
    spans: dict[str, list[float]] = {p: [] for p in (*PHASES, "step")}

    def now() -> float:  # a phase ends when its device work does
        if run.device.type == "cuda":
            torch.cuda.synchronize(run.device)
        return time.perf_counter()

    for k in range(steps):
        idx = order[(k * s.batch_size) % n:][:s.batch_size]
        t = [now()]
        idx_dev = torch.from_numpy(idx).to(run.device)
        rows = {key: loop.take_rows(v, idx_dev).cpu().numpy() for key, v in run.tensors.items()}
        t.append(now())
        if s.augment is not None:
            images = rows.pop("image")
            images, targets = augment_batch(images, rows, [[run.seed, 0, int(i)] for i in idx], s.augment,
                                            run.geometry)
            rows = {"image": images, **targets}
        t.append(now())
        dev = {key: torch.from_numpy(np.ascontiguousarray(v)).to(run.device) for key, v in rows.items()}
        b = loop.make_batch(dev, torch.arange(len(idx), device=run.device), None, s.channels_last)
        t.append(now())
        with autocast(run.device, run.amp):
            out = run.model.forward_train(b["x"])
        t.append(now())
        terms = losses.refine_loss(out, b, b["gate"], run.plan.weights, s.constants)
        float(terms["loss"].detach())  # the loop's finiteness check reads it every step
        t.append(now())
        terms["loss"].backward()
        t.append(now())
        run.opt.step()
        run.sched.step()
        run.opt.zero_grad(set_to_none=True)
        t.append(now())
        if k == 0 and s.augment is not None:  # the same batch as the loop builds
            ref = loop.augmented_batch(run, idx, 0)
            assert all(torch.equal(ref[key], b[key]) for key in ref), "step_profile's batch is not the loop's"
        for p, a, z in zip(PHASES, t, t[1:]):
            spans[p].append(z - a)
        spans["step"].append(t[-1] - t[0])
    return spans


def accuracy(cfg: Mapping, data: TrainData, val: ValData, device, seed: int, epochs: int) -> dict:
    """Train ``plain`` ``epochs`` epochs with ``cfg`` through :func:`pipeline.training.loop.train`; val metrics."""
    from pipeline.training import loop

    res = loop.train(get_method(STAGE_ONE), {**cfg, "epochs_stage1": epochs}, data, None, seed,
                     checkpointer=NoCheckpointer(), device=device, show_progress=False)
    iou, bf1 = loop.validate(res.model, val, device, precision=cfg["precision"], channels_last=cfg["channels_last"],
                             tolerance=cfg["val_bf1_tolerance"])
    return {"val_iou": iou, "val_bf1": bf1, "final_loss": float(res.log["loss"].iloc[-1])}


def load_average() -> str:
    """``/proc/loadavg`` (the host's load beside each measurement), or ``n/a``."""
    try:
        return Path("/proc/loadavg").read_text().strip()
    except OSError:
        return "n/a"


def main(argv=None) -> dict:
    ap = parser(__doc__, device="cpu", threads=2, out=None)
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 384])
    ap.add_argument("--images", type=int, default=64, help="images per timed epoch")
    ap.add_argument("--reps", type=int, default=3, help="round-robin rounds (after one warm-up round)")
    ap.add_argument("--profile-size", type=int, default=128, help="side of the one-step profile (0 = none)")
    ap.add_argument("--profile-steps", type=int, default=5)
    ap.add_argument("--compile", action="store_true", help="also time distill's settings under torch.compile")
    ap.add_argument("--batches", type=int, nargs="+", default=[],
                    help=f"also time {PROFILE}'s settings at these batch sizes (images per second)")
    ap.add_argument("--epochs", type=int, default=0, help="accuracy runs of this many epochs (0 = none)")
    ap.add_argument("--val-images", type=int, default=16)
    ap.add_argument("--seed", type=int, default=42)
    ap.add_argument("--in-process", action="store_true",
                    help="time every variant in this process (default: each in a spawned process of its own)")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                    help=f"an override of the {PROFILE} profile's params (repeatable)")
    args = ap.parse_args(argv)

    import torch

    device = resolve_device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    # as train() does, process-wide: both variants run with it (GLIBC_TUNABLES=glibc.malloc.tcache_count=7 in the
    # environment times both with glibc's defaults; reuse_freed_memory)
    heap_reuse = reuse_freed_memory(device)
    cfgs = variants(args.sets, args.batches)
    batch = int(cfgs[PROFILE]["batch_size"])
    out: dict[str, Any] = {"device": str(device), "threads": torch.get_num_threads(), "torch": torch.__version__,
                           "heap_reuse": heap_reuse, "timed_in": "this process" if args.in_process else
                           "a process per variant",
                           "images": args.images, "batch_size": batch, "reps": args.reps, "sizes": {},
                           "settings": {name: {"precision": c["precision"], "channels_last": c["channels_last"]}
                                        for name, c in cfgs.items()}}
    names = list(cfgs) + ([f"{PROFILE} + torch.compile"] if args.compile else [])
    batches = {name: int(cfgs[name.split(" + ")[0]]["batch_size"]) for name in names}
    for size in args.sizes:
        if args.in_process:
            data = train_data(*synthetic_set(args.images, size, args.seed))
            cases = {name: epoch_timer(open_run(cfgs[name.split(" + ")[0]], data, device, args.seed,
                                                compiled="compile" in name)) for name in names}
        else:
            cases = {name: process_timer(cfgs[name.split(" + ")[0]], size, args.images, args.seed, str(device),
                                         args.threads, compiled="compile" in name) for name in names}
        load_before = load_average()
        t0 = time.perf_counter()
        round_robin(cases, 1)  # warm-up: oneDNN primitives, the allocator, torch.compile's compilation
        warm = time.perf_counter() - t0
        times = round_robin(cases, max(args.reps, 1), order="rotate")
        rows = speed_rows(times, args.images, batches)
        for name, case in cases.items():
            rows[name].update(autocast=case.state["autocast"], loss_after=case.state["loss"])
            case.close()
        out["sizes"][str(size)] = {"variants": rows, "warmup_seconds": warm, "load_before": load_before,
                                   "load_after": load_average(),
                                   "speedup_median": rows[BASELINE]["median_seconds"] / rows[PROFILE]["median_seconds"],
                                   "speedup_min": rows[BASELINE]["min_seconds"] / rows[PROFILE]["min_seconds"],
                                   # each round's pair ran back to back: its ratio sees the same load
                                   "speedup_rounds": [b / f for b, f in zip(times[BASELINE], times[PROFILE])]}
        out["sizes"][str(size)]["batch_speedup_median"] = {
            name: rows[BASELINE]["median_seconds"] / rows[name]["median_seconds"] for name in cfgs if name != BASELINE}
        if args.compile:
            c = rows[names[-1]]
            out["sizes"][str(size)]["compile_speedup_median"] = rows[PROFILE]["median_seconds"] / c["median_seconds"]

    if args.profile_size:
        limits = host_limits() if device.type == "cpu" else None  # the CPU's matmul peaks; none on a GPU
        images, masks = synthetic_set(max(args.images, batch), args.profile_size, args.seed)
        data = train_data(images, masks)
        prof, runs = {}, {name: open_run(cfgs[name], data, device, args.seed) for name in (BASELINE, PROFILE)}
        # one step of each variant a round, so that the host's load hits both alike
        spans = round_robin({name: (lambda i, run=run: step_profile(run, 1)) for name, run in runs.items()},
                            1 + args.profile_steps, order="rotate")
        for name, run in runs.items():
            phases = {p: statistics.median(r[p][0] for r in spans[name][1:]) for p in spans[name][0]}
            flops = step_flops(run, args.profile_size)
            peak = (limits["bf16_gflops"] if run.amp is not None else limits["fp32_gflops"]) if limits else None
            compute = phases["forward"] + phases["backward"]
            prof[name] = {"phases": phases, "gflop_per_step": flops / 1e9, "peak_gflops": peak,
                          "compute_gflops": flops / 1e9 / compute,
                          "limit_seconds": flops / 1e9 / peak if peak else None,
                          "limit_share": flops / 1e9 / peak / phases["step"] if peak else None}
        out["profile"] = {"size": args.profile_size, "host_limits": limits, "load": load_average(), "variants": prof}

    if args.epochs:
        images, masks = synthetic_set(args.images + args.val_images, args.sizes[0], args.seed)
        data = train_data(images[:args.images], masks[:args.images])
        val = ValData(image_ids=[f"v{i}" for i in range(args.val_images)], images=images[args.images:],
                      masks=masks[args.images:])
        out["accuracy"] = {"size": args.sizes[0], "epochs": args.epochs,
                           "variants": {name: accuracy(cfg, data, val, device, args.seed, args.epochs)
                                        for name, cfg in cfgs.items() if name in (BASELINE, PROFILE)}}
    print_summary(out)
    if args.out:

        write_json(args.out, out)
    print(json.dumps(out))
    return out


def print_summary(out: Mapping) -> None:
    """The tables of :func:`main`'s result."""
    print(f"device {out['device']} ({out['threads']} threads), torch {out['torch']}; {out['images']} images an "
          f"epoch, batch {out['batch_size']} ({PROFILE}'s); {out['reps']} round-robin epochs after a warm-up; "
          f"settings {out['settings']}; the heap reused between steps: {out.get('heap_reuse', False)}; timed in "
          f"{out.get('timed_in', 'this process')}")
    print(f"{'size':>5s} {'variant':34s} {'autocast':>9s} {'s/epoch':>8s} {'min':>7s} {'img/s':>7s} {'best':>7s} "
          f"{'s/step':>7s}  load before / after")
    for size, r in out["sizes"].items():
        for name, v in r["variants"].items():
            print(f"{size:>5s} {name:34s} {v['autocast']:>9s} {v['median_seconds']:8.3f} {v['min_seconds']:7.3f} "
                  f"{v['images_per_second']:7.1f} {v['images_per_second_best']:7.1f} {v['seconds_per_step']:7.3f}  "
                  f"{r['load_before']} / {r['load_after']}")
        print(f"{size:>5s} speed-up {PROFILE} / {BASELINE}: {r['speedup_median']:.2f}x median, "
              f"{r['speedup_min']:.2f}x of the minima, per round "
              f"{', '.join(f'{x:.2f}' for x in r['speedup_rounds'])}"
              + (f"; torch.compile / eager: {r['compile_speedup_median']:.2f}x" if "compile_speedup_median" in r else ""))
        for name, x in r.get("batch_speedup_median", {}).items():
            if name != PROFILE:
                print(f"{size:>5s} speed-up {name} / {BASELINE} (batch {out['batch_size']}): {x:.2f}x median")
    if "profile" in out:
        p = out["profile"]
        lim = p["host_limits"] or {}
        print(f"one step at {p['size']}^2 (medians), CPU matmul peak fp32 {lim.get('fp32_gflops') or math.nan:.0f} / "
              f"bf16 {lim.get('bf16_gflops') or math.nan:.0f} GFLOP/s; load {p['load']}")
        for name, v in p["variants"].items():
            ph = v["phases"]
            parts = ", ".join(f"{k} {1e3 * ph[k]:.1f}" for k in PHASES)
            print(f"  {name}: step {1e3 * ph['step']:.1f} ms ({parts} ms); {v['gflop_per_step']:.2f} GFLOP, "
                  f"forward+backward at {v['compute_gflops']:.0f} GFLOP/s of {v['peak_gflops'] or math.nan:.0f}; "
                  f"the peak's step {1e3 * (v['limit_seconds'] or math.nan):.1f} ms = "
                  f"{100 * (v['limit_share'] or math.nan):.0f} % of the measured step")
    if "accuracy" in out:
        a = out["accuracy"]
        for name, v in a["variants"].items():
            print(f"accuracy {a['epochs']} epochs at {a['size']}^2, {name}: val IoU {v['val_iou']:.4f}, "
                  f"val BF1 {v['val_bf1']:.4f}, final loss {v['final_loss']:.4f}")


if __name__ == "__main__":
    main()
