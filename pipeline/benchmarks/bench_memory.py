"""Memory against N: peak RSS of a training epoch and of ``label`` at N and 10N images (issue 25).

    python -m pipeline.benchmarks.bench_memory                       # N = 24 at 192^2 (train), 64^2 (label)
    python -m pipeline.benchmarks.bench_memory --n 40 --size 256 --reps 3

Every measurement runs in a fresh Python process (its peak resident set, ``ru_maxrss``, is its own):

* ``train``: one epoch of the Stage-I ``plain`` method (:func:`pipeline.training.train`) on synthetic
  images and masks stored as Zarr arrays shaped like the artifacts (one image per chunk, sharded), read
  either streaming (:class:`pipeline.streaming.LazyRows`, what ``training_data`` returns) or loaded into
  memory first (the previous path).  Also: seconds per epoch (median and minimum of ``--reps``
  interleaved runs) -> streaming / in-memory throughput.
* ``label``: ``pipeline.api.label`` with the simulated teacher on a folder of synthetic PNGs.
* ``read``: ``read_chunk_rows`` of 200 rows at ``--read-size``^2 (plain slices) against zarr's orthogonal
  selection (what it used to do) -- peak RSS and seconds.

Prints a table, the 10N / N ratios (target: within 1.3x) and one JSON line.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from pipeline.artifacts import read_chunk_rows
from pipeline.benchmarks.bench_train import synthetic_set
from pipeline.methods import STAGE_ONE, get_method
from pipeline.params import load_params, section
from pipeline.streaming import LazyRows, row_means

ROOT = Path(__file__).resolve().parents[2]


def peak_mb() -> float:
    """This process's peak resident set size in MB (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def write_zarr_set(folder: Path, n: int, size: int, seed: int = 0) -> Path:
    """``folder/images.zarr`` uint8 [n,size,size,3] and ``folder/mask.zarr`` bool [n,size,size]: one image per
    chunk, 256 per shard (as the artifacts); written 16 images at a time."""
    import zarr

    img = zarr.create_array(str(folder / "images.zarr"), shape=(n, size, size, 3), dtype="uint8",
                            chunks=(1, size, size, 3), shards=(min(256, n), size, size, 3), overwrite=True)
    msk = zarr.create_array(str(folder / "mask.zarr"), shape=(n, size, size), dtype="bool",
                            chunks=(1, size, size), shards=(min(256, n), size, size), overwrite=True)
    for s in range(0, n, 16):
        e = min(s + 16, n)
        images, masks = synthetic_set(e - s, size, seed + s)
        img[s:e], msk[s:e] = images, masks
    return folder


def child_train(folder: Path, mode: str) -> dict:
    """One epoch of ``plain`` on the Zarr set, ``mode`` = stream | memory; peak RSS and seconds."""
    import zarr

    from pipeline import training

    img, msk = zarr.open_array(str(folder / "images.zarr")), zarr.open_array(str(folder / "mask.zarr"))
    n = img.shape[0]
    rows = np.arange(n)
    images, mask = LazyRows(img, rows), LazyRows(msk, rows, bool)
    if mode == "memory":
        images, mask = np.asarray(images), np.asarray(mask)
    data = training.TrainData(image_ids=[f"b{i}" for i in range(n)], images=images, mask=mask,
                              area=row_means(mask), gate=np.ones(n, np.float32))
    cfg = section(load_params(ROOT / "params.yaml"), "train")
    cfg.update({"epochs_stage1": 1, "num_threads": 0, "precision": "fp32"})
    t = time.perf_counter()
    training.train(get_method(STAGE_ONE), cfg, data, None, 42, checkpointer=training.NoCheckpointer(), device="cpu",
                   show_progress=False)
    return {"peak_mb": peak_mb(), "seconds": time.perf_counter() - t}


def child_label(folder: Path, out: Path, size: int) -> dict:
    """``label`` on ``folder/images`` with the simulated teacher (reference masks ``folder/masks``)."""
    from pipeline.api import label

    t = time.perf_counter()
    label(folder / "images", out=out, formats=("png",), backend="simulated", reference_masks=folder / "masks",
          overrides=[f"data.resolution={size}"], device="cpu")
    return {"peak_mb": peak_mb(), "seconds": time.perf_counter() - t}


def child_read(folder: Path, mode: str) -> dict:
    """200 rows of ``images.zarr``: ``slices`` (read_chunk_rows) or ``orthogonal`` (zarr's selection)."""
    import zarr

    arr = zarr.open_array(str(folder / "images.zarr"))
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
    proc = subprocess.run([sys.executable, "-m", "pipeline.benchmarks.bench_memory", "--child", *args],
                          capture_output=True, text=True, cwd=ROOT)
    if proc.returncode != 0:
        raise RuntimeError(f"child {args} failed: {proc.stderr.strip().splitlines()[-1:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=24, help="N images (and 10N)")
    ap.add_argument("--factor", type=int, default=10)
    ap.add_argument("--size", type=int, default=192, help="training image size")
    ap.add_argument("--label-size", type=int, default=64)
    ap.add_argument("--read-size", type=int, default=384)
    ap.add_argument("--reps", type=int, default=2, help="interleaved timing runs per training variant at 10N")
    ap.add_argument("--skip", default="", help="comma list of parts to skip: train,label,read")
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        kind, *rest = args.child
        res = {"train": lambda: child_train(Path(rest[0]), rest[1]),
               "label": lambda: child_label(Path(rest[0]), Path(rest[1]), int(rest[2])),
               "read": lambda: child_read(Path(rest[0]), rest[1])}[kind]()
        print(json.dumps(res))
        return res

    skip = set(filter(None, args.skip.split(",")))
    sizes = (args.n, args.n * args.factor)
    out: dict = {"n": sizes, "size": args.size, "label_size": args.label_size}
    with tempfile.TemporaryDirectory(prefix="bench_memory_") as tmp:
        tmp = Path(tmp)
        if "train" not in skip:
            rows = {}
            for n in sizes:
                folder = write_zarr_set(tmp / f"train{n}", n, args.size)
                runs: dict[str, list] = {"stream": [], "memory": []}
                for _ in range(args.reps if n == sizes[1] else 1):  # interleaved: load hits both alike
                    for m in runs:
                        runs[m].append(run_child("train", str(folder), m))
                rows[n] = {m: {"peak_mb": max(r["peak_mb"] for r in rs), "seconds": [r["seconds"] for r in rs]}
                           for m, rs in runs.items()}
            out["train"] = rows
        if "label" not in skip:
            out["label"] = {n: run_child("label", str(image_folder(tmp / f"label{n}", n, args.label_size)),
                                         str(tmp / f"label_out{n}"), str(args.label_size)) for n in sizes}
        if "read" not in skip:
            folder = write_zarr_set(tmp / "read", 200, args.read_size)
            out["read"] = {m: run_child("read", str(folder), m) for m in ("slices", "orthogonal")}

    print(f"peak RSS (MB) at N = {sizes[0]} and {sizes[1]} images; each figure from a fresh process")
    if "train" in out:
        t = out["train"]
        for m in ("stream", "memory"):
            a, b = t[sizes[0]][m]["peak_mb"], t[sizes[1]][m]["peak_mb"]
            print(f"train epoch {args.size}^2, {m:6s}: {a:8.0f} {b:8.0f}  ratio {b / a:.2f}x"
                  + ("  (target <= 1.3x)" if m == "stream" else ""))
        s, mem = t[sizes[1]]["stream"]["seconds"], t[sizes[1]]["memory"]["seconds"]
        print(f"epoch seconds at {sizes[1]}: stream median {np.median(s):.1f} (min {min(s):.1f}), "
              f"in-memory median {np.median(mem):.1f} (min {min(mem):.1f}); "
              f"throughput stream / in-memory {np.median(mem) / np.median(s):.2f} (min-based {min(mem) / min(s):.2f})")
    if "label" in out:
        a, b = out["label"][sizes[0]]["peak_mb"], out["label"][sizes[1]]["peak_mb"]
        print(f"label {args.label_size}^2:           {a:8.0f} {b:8.0f}  ratio {b / a:.2f}x  (target <= 1.3x)")
    if "read" in out:
        r = out["read"]
        print(f"read 200 rows at {args.read_size}^2: slices {r['slices']['peak_mb']:.0f} MB {r['slices']['seconds']:.2f} s; "
              f"orthogonal selection {r['orthogonal']['peak_mb']:.0f} MB {r['orthogonal']['seconds']:.2f} s; "
              f"same data: {r['slices']['checksum'] == r['orthogonal']['checksum']}")
    print(json.dumps(out, default=str))
    return out


if __name__ == "__main__":
    main()
