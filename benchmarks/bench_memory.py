"""Memory against N: peak RSS at N and 10N images (each figure from a fresh process) of one training epoch per
``--methods`` on artifact-shaped Zarr arrays, streaming (``LazyRows``) or loaded into memory (with both epochs'
seconds at 10N, interleaved), of ``label`` (simulated teacher), of ``prepare`` (every view count scaled) and of
``read_chunk_rows`` against zarr's orthogonal selection; the 10N / N ratios (target 1.3x) and the streaming
peak extrapolated to 100,000 images (target 8 GiB).

    python -m benchmarks.bench_memory [--n 27 --size 384 --methods plain,geodistill --max-batches 12 --check-batches 24]
"""

from __future__ import annotations

import argparse
import itertools
import json
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from pipeline import catalog
from pipeline.artifacts.lineage import make_meta
from pipeline.artifacts.store import read_chunk_rows
from benchmarks.bench_train import synthetic_set
from benchmarks.common import round_robin, seconds
from pipeline.datasets.params import check_data_params
from pipeline.methods import STAGE_ONE, get_method
from pipeline.params import load_params, section
from pipeline.training.streaming import LazyRows, row_means
from pipeline.training.checkpointing import NoCheckpointer

ROOT = Path(__file__).resolve().parents[1]


def peak_mb() -> float:
    """This process's peak resident set size in MB (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def rss_mb() -> float:
    """This process's current resident set size in MB (/proc/self/status VmRSS)."""
    m = re.search(r"^VmRSS:\s+(\d+)", Path("/proc/self/status").read_text(), re.MULTILINE)
    return int(m.group(1)) / 1024.0 if m else float("nan")


def write_zarr_set(folder: Path, n: int, size: int, seed: int = 0, geometry: bool = False) -> Path:
    """``folder/images.zarr`` uint8 [n,size,size,3] and ``mask.zarr`` bool, chunked as the artifacts; ``geometry``:
    also ``sdf.zarr`` float32 (+-0.5: the artifact's dtype, not an SDF) and ``skeleton.zarr`` bool (the mask)."""
    import zarr

    def create(name, shape, dtype):
        return zarr.create_array(str(folder / f"{name}.zarr"), shape=(n, *shape), dtype=dtype, chunks=(1, *shape),
                                 shards=(min(256, n), *shape), overwrite=True)

    img, msk = create("images", (size, size, 3), "uint8"), create("mask", (size, size), "bool")
    sdf = create("sdf", (size, size), "float32") if geometry else None
    skel = create("skeleton", (size, size), "bool") if geometry else None
    for s in range(0, n, 16):
        e = min(s + 16, n)
        images, masks = synthetic_set(e - s, size, seed + s)
        img[s:e], msk[s:e] = images, masks
        if geometry:
            sdf[s:e], skel[s:e] = np.where(masks, 0.5, -0.5).astype(np.float32), masks
    return folder


def child_train(folder: Path, mode: str, method_name: str, max_batches: int) -> dict:
    """One epoch (``max_batches`` at most, 0 = all) of ``method_name``, ``mode`` stream | memory: RSS, seconds."""
    import zarr

    from pipeline.training import loop as training
    method = get_method(method_name)
    arrays = {"images": None, "mask": bool, **({"sdf": np.float32, "skeleton": bool} if method.needs_geometry else {})}
    n = zarr.open_array(str(catalog.path("images", folder))).shape[0]
    lazy = {k: LazyRows(zarr.open_array(str(folder / f"{k}.zarr")), np.arange(n), dt) for k, dt in arrays.items()}
    if mode == "memory":
        lazy = {k: np.asarray(v) for k, v in lazy.items()}
    gate = np.random.default_rng(0).uniform(0.2, 1.0, n).astype(np.float32)
    data = training.TrainData(image_ids=[f"b{i}" for i in range(n)], area=row_means(lazy["mask"]), gate=gate,
                              stats={"confidence_pass_ratio": 1.0}, **lazy)  # r = 1: the anchored mode
    cfg = section(load_params(ROOT / "params.yaml"), "train")
    cfg.update({"epochs_stage1": 1, "epochs_stage2": 1, "num_threads": 0, "precision": "fp32", "average_last": 0,
                "precise_bn": False})
    init = (training.build_model(get_method(STAGE_ONE), cfg, 0).mask_path_state_dict()
            if method.init == "stage1" else None)
    if max_batches > 0:  # the epoch's first K batches (the loop itself is unchanged)
        in_order = training.epoch_batches_in_order
        training.epoch_batches_in_order = lambda run, epoch: itertools.islice(in_order(run, epoch), max_batches)
    before = rss_mb()
    t = seconds(lambda: training.train(method, cfg, data, None, 42, checkpointer=NoCheckpointer(),
                                       init_state=init, device="cpu", show_progress=False))
    steps = min(max_batches or n, -(-n // int(cfg["batch_size"])))
    return {"peak_mb": peak_mb(), "rss_before_mb": before, "seconds": t, "batches": steps}


def child_label(folder: Path, out: Path, size: int) -> dict:
    """``label`` on ``folder/images`` with the simulated teacher (reference masks ``folder/masks``)."""
    from pipeline.api import label

    t = seconds(lambda: label(folder / "images", out=out, formats=("png",), backend="simulated",
                              reference_masks=folder / "masks", overrides=[f"data.resolution={size}"], device="cpu"))
    return {"peak_mb": peak_mb(), "seconds": t}


def child_prepare(out: Path, factor: int, size: int) -> dict:
    """The prepare stage on the synthetic source, every view count times ``factor``, at ``size``^2."""
    import zarr

    from pipeline.datasets.prepare import prepare

    views = section(load_params(ROOT / "params.yaml"), "data")["synthetic"]
    sets = [f"data.synthetic.{k}={int(views[k]) * factor}" for k in ("train_views", "val_views", "test_views")]
    params = load_params(ROOT / "params.yaml", [f"data.resolution={size}", f"data.cache_dir={out / 'cache'}", *sets])
    t = seconds(lambda: prepare(check_data_params(section(params, "data")), out, lambda schema, params, **extra:
                                make_meta(schema, "prepare", "bench_memory", params, **extra)))
    return {"peak_mb": peak_mb(), "seconds": t, "n": zarr.open_group(str(catalog.path("images", out)))["image"].shape[0]}


def child_read(folder: Path, mode: str) -> dict:
    """200 rows of ``images.zarr``: ``slices`` (read_chunk_rows) or ``orthogonal`` (zarr's selection)."""
    import zarr

    arr = zarr.open_array(str(catalog.path("images", folder)))
    rows = np.arange(arr.shape[0])
    t = time.perf_counter()
    out = read_chunk_rows(arr, rows) if mode == "slices" else arr.get_orthogonal_selection((rows,))
    return {"peak_mb": peak_mb(), "seconds": time.perf_counter() - t, "checksum": int(out[:, ::7, ::7].sum())}


def image_folder(root: Path, n: int, size: int) -> Path:
    """``root/images`` and ``root/masks``: n synthetic PNGs and their 0/255 masks."""
    import cv2

    (root / "images").mkdir(parents=True)
    (root / "masks").mkdir()
    for s in range(0, n, 16):
        images, masks = synthetic_set(min(16, n - s), size, s)
        for j, (im, m) in enumerate(zip(images, masks)):
            cv2.imwrite(str(root / "images" / f"img{s + j:05d}.png"), im)
            cv2.imwrite(str(root / "masks" / f"img{s + j:05d}.png"), m.astype(np.uint8) * 255)
    return root


def run_child(*args: str) -> dict:
    """Run this module as ``--child ARGS`` in a fresh process; its JSON result."""
    proc = subprocess.run([sys.executable, "-m", "benchmarks.bench_memory", "--child", *args],
                          capture_output=True, text=True, cwd=ROOT)
    if proc.returncode != 0:
        raise RuntimeError(f"child {args} failed: {proc.stderr.strip().splitlines()[-1:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _train_part(tmp: Path, args, sizes: tuple[int, int], methods: list[str]) -> dict:
    """Peak RSS of every (method, N, mode) and the interleaved timings at 10N."""
    out: dict = {}
    geometry = any(m != STAGE_ONE for m in methods)
    folders = {n: str(write_zarr_set(tmp / f"train{n}", n, args.size, geometry=geometry)) for n in sizes}
    for method in methods:
        rows: dict = {}
        for n in sizes:  # interleaved A B A B at 10N: load hits both alike
            cmd = {m: ("train", folders[n], m, method, str(args.max_batches)) for m in ("stream", "memory")}
            reps = args.reps if n == sizes[1] else 1
            runs = round_robin({m: (lambda i, c=c: run_child(*c)) for m, c in cmd.items()}, reps)
            rows[n] = {m: {"peak_mb": max(r["peak_mb"] for r in rs), "rss_before_mb": rs[0]["rss_before_mb"],
                           "seconds": [r["seconds"] for r in rs], "batches": rs[0]["batches"]}
                       for m, rs in runs.items()}
        if args.check_batches:
            rows["check"] = run_child("train", folders[sizes[1]], "stream", method, str(args.check_batches))
        out[method] = rows
    return out


def _print_train(t: dict, args, sizes: tuple[int, int]) -> None:
    for method, rows in t.items():
        a, b = rows[sizes[0]], rows[sizes[1]]
        for m in ("stream", "memory"):
            ratio = b[m]["peak_mb"] / a[m]["peak_mb"]
            print(f"train {method} {args.size}^2, {m:6s}: {a[m]['peak_mb']:8.0f} {b[m]['peak_mb']:8.0f}  "
                  f"ratio {ratio:.2f}x  (RSS before training {a[m]['rss_before_mb']:.0f} / {b[m]['rss_before_mb']:.0f}; "
                  f"{b[m]['batches']} batches)" + ("  target <= 1.3x" if m == "stream" else ""))
        slope = (b["stream"]["peak_mb"] - a["stream"]["peak_mb"]) / (sizes[1] - sizes[0])
        extra = b["stream"]["peak_mb"] + slope * (args.extrapolate - sizes[1])
        print(f"  stream slope {slope * 1024:.1f} KB per image -> {args.extrapolate} images: {extra:.0f} MB "
              f"({extra / 1024:.2f} GiB; target 8 GiB)")
        if "check" in rows:
            c = rows["check"]
            print(f"  stream at {sizes[1]} with {c['batches']} batches: {c['peak_mb']:.0f} MB "
                  f"(vs {b['stream']['peak_mb']:.0f} MB with {b['stream']['batches']})")
        s, mem = b["stream"]["seconds"], b["memory"]["seconds"]
        print(f"  epoch seconds at {sizes[1]} ({b['stream']['batches']} batches): stream median {np.median(s):.1f} "
              f"(min {min(s):.1f}), in-memory median {np.median(mem):.1f} (min {min(mem):.1f}); throughput "
              f"stream / in-memory {np.median(mem) / np.median(s):.2f} (min-based {min(mem) / min(s):.2f})")


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=24, help="N images (and 10N)")
    ap.add_argument("--factor", type=int, default=10)
    ap.add_argument("--size", type=int, default=192, help="training image size")
    ap.add_argument("--methods", default=STAGE_ONE, help="comma list: plain, geodistill, geodistill_adaptive")
    ap.add_argument("--max-batches", type=int, default=0, help="batches per epoch (0 = the full epoch)")
    ap.add_argument("--check-batches", type=int, default=0,
                    help="one more streaming run at 10N with this many batches (peak reached early?)")
    ap.add_argument("--extrapolate", type=int, default=100_000, help="images for the slope's extrapolation")
    ap.add_argument("--label-size", type=int, default=64)
    ap.add_argument("--read-size", type=int, default=384)
    ap.add_argument("--reps", type=int, default=2, help="interleaved timing runs per training variant at 10N")
    ap.add_argument("--skip", default="", help="comma list of parts to skip: train,label,prepare,read")
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        kind, *rest = args.child
        res = {"train": lambda: child_train(Path(rest[0]), rest[1], rest[2], int(rest[3])),
               "label": lambda: child_label(Path(rest[0]), Path(rest[1]), int(rest[2])),
               "prepare": lambda: child_prepare(Path(rest[0]), int(rest[1]), int(rest[2])),
               "read": lambda: child_read(Path(rest[0]), rest[1])}[kind]()
        print(json.dumps(res))
        return res

    skip = set(filter(None, args.skip.split(",")))
    sizes = (args.n, args.n * args.factor)
    out: dict = {"n": sizes, "size": args.size, "label_size": args.label_size, "max_batches": args.max_batches}
    print(f"peak RSS (MB) at N = {sizes[0]} and {sizes[1]} images; each figure from a fresh process")
    with tempfile.TemporaryDirectory(prefix="bench_memory_") as tmp:  # each part printed as it finishes
        tmp = Path(tmp)
        if "train" not in skip:
            out["train"] = _train_part(tmp, args, sizes, args.methods.split(","))
            _print_train(out["train"], args, sizes)
        if "label" not in skip:
            out["label"] = {n: run_child("label", str(image_folder(tmp / f"label{n}", n, args.label_size)),
                                         str(tmp / f"label_out{n}"), str(args.label_size)) for n in sizes}
            a, b = out["label"][sizes[0]]["peak_mb"], out["label"][sizes[1]]["peak_mb"]
            print(f"label {args.label_size}^2:           {a:8.0f} {b:8.0f}  ratio {b / a:.2f}x  (target <= 1.3x)")
        if "prepare" not in skip:
            out["prepare"] = {f: run_child("prepare", str(tmp / f"prepare{f}"), str(f), str(args.label_size))
                              for f in (1, args.factor)}
            a, b = out["prepare"][1], out["prepare"][args.factor]
            print(f"prepare {args.label_size}^2 (N = {a['n']}, {b['n']}): {a['peak_mb']:8.0f} {b['peak_mb']:8.0f}  "
                  f"ratio {b['peak_mb'] / a['peak_mb']:.2f}x  (target <= 1.3x)")
        if "read" not in skip:
            folder = write_zarr_set(tmp / "read", 200, args.read_size)
            out["read"] = r = {m: run_child("read", str(folder), m) for m in ("slices", "orthogonal")}
            same = r["slices"]["checksum"] == r["orthogonal"]["checksum"]
            print(f"read 200 rows at {args.read_size}^2: slices {r['slices']['peak_mb']:.0f} MB "
                  f"{r['slices']['seconds']:.2f} s; orthogonal selection {r['orthogonal']['peak_mb']:.0f} MB "
                  f"{r['orthogonal']['seconds']:.2f} s; same data: {same}")
    print(json.dumps(out, default=str))
    return out


if __name__ == "__main__":
    main()
