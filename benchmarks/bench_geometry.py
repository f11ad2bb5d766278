"""SDF + skeleton + area targets (eq:sdf-target, Skel, eq:pseudo-area) per second for 384x384 masks (target:
>= 300 masks/s on 2 CPU cores), OpenCV against a plain scipy baseline in the same run, after checking that both
give the same targets on every mask.

    python -m benchmarks.bench_geometry [--n 200] [--size 384] [--repeats 3] [--workers 2]
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from benchmarks.common import best_of, parser
from pipeline.geometry import pseudo_targets


def spacecraft_like_masks(n: int, size: int, seed: int = 0) -> np.ndarray:
    """Random bus + solar panels + boom silhouettes (some empty, some tiny), like voted pseudo-masks."""
    import cv2

    rng = np.random.default_rng(seed)
    out = np.zeros((n, size, size), np.uint8)
    for i in range(n):
        if rng.random() < 0.03:
            continue  # an image whose vote is empty
        m = out[i]
        cx, cy = rng.uniform(0.3, 0.7, 2) * size
        scale = rng.uniform(0.03, 0.25) * size
        ang = rng.uniform(0, 180)
        box = cv2.boxPoints(((cx, cy), (scale, scale * rng.uniform(0.6, 1.4)), ang)).astype(np.int32)
        cv2.fillPoly(m, [box], 1)
        for side in (-1, 1):  # panels
            rad = np.deg2rad(ang)
            off = side * scale * rng.uniform(0.9, 1.6)
            px, py = cx + off * np.cos(rad), cy + off * np.sin(rad)
            panel = cv2.boxPoints(((px, py), (scale * rng.uniform(0.8, 1.5), scale * 0.4), ang)).astype(np.int32)
            cv2.fillPoly(m, [panel], 1)
        end = (int(cx + rng.uniform(-1, 1) * scale * 2), int(cy + rng.uniform(-1, 1) * scale * 2))
        cv2.line(m, (int(cx), int(cy)), end, 1, thickness=int(rng.integers(1, 3)))  # boom
    return out.astype(bool)


def scipy_targets(mask: np.ndarray, q: float = 0.95, min_distance: float = 1.0):
    """The baseline: the same three targets with scipy's exact EDT, np.quantile and a maximum filter."""
    from scipy import ndimage

    area = mask.mean()
    if not mask.any():
        return np.zeros(mask.shape, np.float32), np.zeros(mask.shape, bool), area
    if mask.all():
        return np.ones(mask.shape, np.float32), mask.copy(), area
    d_in = ndimage.distance_transform_edt(mask)
    d_out = ndimage.distance_transform_edt(~mask)
    raw = d_in - d_out
    s = np.quantile(np.abs(raw), q)
    sdf = np.clip(raw / (s if s >= 1e-6 else 1.0), -1, 1).astype(np.float32)
    skel = (d_in > min_distance) & (d_in >= ndimage.maximum_filter(d_in, size=3, mode="constant", cval=-np.inf))
    return sdf, (skel if skel.any() else mask.copy()), area


def main() -> None:
    ap = parser(__doc__, repeats=3)
    ap.add_argument("--n", type=int, default=200)
    ap.add_argument("--size", type=int, default=384)
    ap.add_argument("--workers", type=int, default=2, help="threads for the parallel OpenCV run (cores)")
    args = ap.parse_args()
    import cv2

    masks = spacecraft_like_masks(args.n, args.size)
    print(f"{args.n} masks {args.size}x{args.size}, mean area {masks.mean():.4f}; cpu count {os.cpu_count()}, "
          f"OpenCV {cv2.__version__} threads {cv2.getNumThreads()}")

    # same targets first (SDF to float32 rounding, skeleton and area exactly)
    sdf, skel, area = pseudo_targets(masks)
    for i, m in enumerate(masks):
        r_sdf, r_skel, r_area = scipy_targets(m)
        assert np.allclose(sdf[i], r_sdf, atol=1e-5), f"SDF differs on mask {i}"
        assert np.array_equal(skel[i], r_skel), f"skeleton differs on mask {i}"
        assert area[i] == r_area
    print("check: OpenCV and scipy targets agree on every mask")

    t_cv = best_of(lambda: pseudo_targets(masks), args.repeats)
    t_sp = best_of(lambda: [scipy_targets(m) for m in masks], max(1, args.repeats - 1))
    chunks = np.array_split(masks, args.workers * 4)
    cv2.setNumThreads(1)  # one OpenCV thread per worker: parallel over images instead
    with ThreadPoolExecutor(args.workers) as ex:
        t_cv_par = best_of(lambda: list(ex.map(pseudo_targets, chunks)), args.repeats)
        t_sp_par = best_of(lambda: list(ex.map(lambda c: [scipy_targets(m) for m in c], chunks)), 1)
    cv2.setNumThreads(-1)

    print(f"{'implementation':<48}{'masks/s':>10}{'ms/mask':>10}")
    rows = [("scipy EDT + quantile + maximum_filter (serial)", t_sp),
            (f"scipy, {args.workers} threads over images", t_sp_par),
            ("OpenCV pseudo_targets (serial, OpenCV threads)", t_cv),
            (f"OpenCV pseudo_targets, {args.workers} threads over images", t_cv_par)]
    for name, t in rows:
        print(f"{name:<48}{args.n / t:>10.1f}{1e3 * t / args.n:>10.2f}")
    best_cv = min(t_cv, t_cv_par)
    rate = args.n / best_cv
    print(f"ratio OpenCV/scipy (serial): {t_sp / t_cv:.2f}x;  best OpenCV vs best scipy: {min(t_sp, t_sp_par) / best_cv:.2f}x")
    print(f"target >= 300 masks/s: best OpenCV {rate:.1f} masks/s -> {'MET' if rate >= 300 else 'NOT MET'}")


if __name__ == "__main__":
    main()
