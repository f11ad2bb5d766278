"""Synthetic spacecraft generator throughput (target: >= 20 images/s at 384x384 on 2 CPU cores): the OpenCV
rasteriser against the numpy per-pixel baseline (``rasterizer="numpy"``) on the same views, end to end and
the rasterisation alone, plus the fast path with PNG encoding (what ``prepare`` writes) and in 2 processes.

    python -m benchmarks.bench_synthetic [--size 384] [--views 60] [--baseline-views 30]
"""

from __future__ import annotations

import functools
import multiprocessing as mp
import os
import time

import cv2
import numpy as np

from benchmarks.common import parser, seconds
from pipeline.datasets import synthetic as syn

SEED = 2026


@functools.cache
def _spacecraft(name):
    """A spacecraft model, built once per process (its build is not what the benchmark times)."""
    return syn.make_spacecraft(name, SEED)


def _render(job, size, rasterizer="cv2", encode=False):
    name, view = job
    v = syn.generate_view(_spacecraft(name), view, size, SEED, rasterizer=rasterizer)
    if encode:
        for a in (v.image[..., ::-1], v.mask.astype(np.uint8) * 255, v.parts):
            cv2.imencode(".png", np.ascontiguousarray(a), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    return v.area_fraction


def _rate(jobs, **kw):
    """(images per wall second, images per CPU second of this process: meaningful on shared cores)."""
    _render(jobs[0], **kw)  # warm-up (imports, model build)
    c = time.process_time()
    wall = seconds(lambda: [_render(j, **kw) for j in jobs])
    return len(jobs) / wall, len(jobs) / max(time.process_time() - c, 1e-9)


def _raster_rate(jobs, size, rasterizer):
    rngs = [(name, syn.view_rng(SEED, name, view)) for name, view in jobs]
    specs = [(_spacecraft(name), syn.sample_view(rng), rng) for name, rng in rngs]
    return len(specs) / seconds(lambda: [syn.rasterize(m, spec, size, rng, rasterizer) for m, spec, rng in specs])


def main():
    ap = parser(__doc__)
    ap.add_argument("--size", type=int, default=384)
    ap.add_argument("--views", type=int, default=60)
    ap.add_argument("--baseline-views", type=int, default=30)
    a = ap.parse_args()
    cv2.setNumThreads(1)
    names = [f"syn-train-{k:02d}" for k in range(6)]
    jobs = [(names[i % len(names)], i) for i in range(a.views)]
    fast, cpu_rate = _rate(jobs, size=a.size)
    base_jobs = jobs[: a.baseline_views]
    fast_same = _rate(base_jobs, size=a.size)[0]
    base = _rate(base_jobs, size=a.size, rasterizer="numpy")[0]
    prep = _rate(jobs, size=a.size, encode=True)[0]
    r_fast = _raster_rate(base_jobs, a.size, "cv2")
    r_base = _raster_rate(base_jobs, a.size, "numpy")
    with mp.get_context("fork").Pool(2) as pool:
        pool.starmap(_render, [(jobs[0], a.size)] * 2)
        two = len(jobs) / seconds(lambda: pool.starmap(_render, [(j, a.size) for j in jobs], chunksize=4))
    print(f"synthetic generator at {a.size}x{a.size}, {os.cpu_count()} CPUs visible")
    print(f"  fast path (OpenCV rasteriser), 1 process : {fast:7.1f} images/s  ({a.views} views)")
    print(f"  fast path per CPU-second of the process  : {cpu_rate:7.1f} images/s  "
          f"(load average {os.getloadavg()[0]:.1f}; wall rates drop when the cores are shared)")
    print(f"  fast path + PNG encode (prepare), 1 proc : {prep:7.1f} images/s")
    print(f"  fast path, 2 worker processes            : {two:7.1f} images/s")
    print(f"  baseline (numpy per-pixel rasteriser)    : {base:7.1f} images/s  ({len(base_jobs)} views)")
    print(f"  fast / baseline on the same views        : {fast_same / base:7.1f} x  (end to end)")
    print(f"  rasterisation only: OpenCV {r_fast:7.1f} /s, numpy {r_base:7.1f} /s : {r_fast / r_base:7.1f} x")
    print(f"  target >= 20 images/s                    : {'met' if max(fast, two) >= 20 else 'NOT met'}")


if __name__ == "__main__":
    main()
