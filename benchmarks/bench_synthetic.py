"""Synthetic spacecraft generator throughput at 384x384 (target: >= 20 images/s on 2 CPU cores).

Measures, in one run and on the same views:
  * fast path   -- OpenCV rasteriser (cv2.fillConvexPoly / cv2.line into the record-id buffer);
  * baseline    -- the same generator with ``rasterizer="numpy"`` (plain per-pixel half-plane and
                   segment-distance tests over each primitive's bounding box), end to end and for
                   the rasterisation step alone (``synthetic.rasterize``, same views);
  * prepare path -- fast path + PNG encoding of image, mask and part labels (what `prepare` writes);
  * 2 workers   -- the fast path in a 2-process pool (the project's 2-core machines).
Prints images/s and the fast/baseline ratio.  Usage:
    python -m benchmarks.bench_synthetic [--size 384] [--views 60] [--baseline-views 30]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import time


import cv2  # noqa: E402
import numpy as np  # noqa: E402

from pipeline.datasets import synthetic as syn  # noqa: E402

SEED = 2026


def _jobs(n):
    names = [f"syn-train-{k:02d}" for k in range(6)]
    return [(names[i % len(names)], i) for i in range(n)]


#: spacecraft models built once per process (their build is not what the benchmark times)
_MODELS: dict = {}


def _spacecraft(name):
    if name not in _MODELS:
        _MODELS[name] = syn.make_spacecraft(name, SEED)
    return _MODELS[name]


def _render(job, size, rasterizer="cv2", encode=False):
    name, view = job
    model = _spacecraft(name)
    v = syn.generate_view(model, view, size, SEED, rasterizer=rasterizer)
    if encode:
        for a in (v.image[..., ::-1], v.mask.astype(np.uint8) * 255, v.parts):
            cv2.imencode(".png", np.ascontiguousarray(a), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    return v.area_fraction


def _rate(jobs, cpu=None, **kw):
    """Images per wall-clock second; ``cpu`` (a dict) also receives images per CPU second of this
    process, which stays meaningful when other jobs share the cores."""
    _render(jobs[0], **kw)  # warm-up (imports, model build)
    t, c = time.perf_counter(), time.process_time()
    for j in jobs:
        _render(j, **kw)
    if cpu is not None:
        cpu["rate"] = len(jobs) / max(time.process_time() - c, 1e-9)
    return len(jobs) / (time.perf_counter() - t)


def _raster_rate(jobs, size, rasterizer):
    specs = []
    for name, view in jobs:
        model = _spacecraft(name)
        rng = syn.view_rng(SEED, name, view)
        specs.append((model, syn.sample_view(rng), rng))
    t = time.perf_counter()
    for model, spec, rng in specs:
        syn.rasterize(model, spec, size, rng, rasterizer)
    return len(specs) / (time.perf_counter() - t)


def _worker(args):
    return _render(*args)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=384)
    ap.add_argument("--views", type=int, default=60)
    ap.add_argument("--baseline-views", type=int, default=30)
    a = ap.parse_args()
    cv2.setNumThreads(1)
    jobs = _jobs(a.views)
    cpu = {}
    fast = _rate(jobs, cpu=cpu, size=a.size)
    base_jobs = jobs[: a.baseline_views]
    fast_same = _rate(base_jobs, size=a.size)
    base = _rate(base_jobs, size=a.size, rasterizer="numpy")
    prep = _rate(jobs, size=a.size, encode=True)
    r_fast = _raster_rate(base_jobs, a.size, "cv2")
    r_base = _raster_rate(base_jobs, a.size, "numpy")
    with mp.get_context("fork").Pool(2) as pool:
        pool.map(_worker, [(jobs[0], a.size)] * 2)
        t = time.perf_counter()
        pool.map(_worker, [(j, a.size) for j in jobs], chunksize=4)
        two = len(jobs) / (time.perf_counter() - t)
    print(f"synthetic generator at {a.size}x{a.size}, {os.cpu_count()} CPUs visible")
    print(f"  fast path (OpenCV rasteriser), 1 process : {fast:7.1f} images/s  ({a.views} views)")
    print(f"  fast path per CPU-second of the process  : {cpu['rate']:7.1f} images/s  "
          f"(load average {os.getloadavg()[0]:.1f}; wall rates drop when the cores are shared)")
    print(f"  fast path + PNG encode (prepare), 1 proc : {prep:7.1f} images/s")
    print(f"  fast path, 2 worker processes            : {two:7.1f} images/s")
    print(f"  baseline (numpy per-pixel rasteriser)    : {base:7.1f} images/s  ({len(base_jobs)} views)")
    print(f"  fast / baseline on the same views        : {fast_same / base:7.1f} x  (end to end)")
    print(f"  rasterisation only: OpenCV {r_fast:7.1f} /s, numpy {r_base:7.1f} /s : {r_fast / r_base:7.1f} x")
    print(f"  target >= 20 images/s                    : {'met' if max(fast, two) >= 20 else 'NOT met'}")


if __name__ == "__main__":
    main()
