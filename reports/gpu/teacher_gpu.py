#!/usr/bin/env python3
"""The real-size SAM 3 teacher on a GPU (issue 58 item 4): peak memory and time per image in bf16 at each
batch, compiled (``teacher.compile``) and eager, round-robin, medians and minima.  Random weights
(``build_tiny_sam3(size="real")``): the figures measure the architecture's cost, not its answers.

    python reports/gpu/teacher_gpu.py --device cuda --size real --batches 1 2 4 8 16 32 --out teacher_gpu.json

Per batch ``b``: one warm-up call per path (its seconds are reported: they hold the compile of that shape),
then ``--repeats`` rounds of one call per path, each call ``b`` images and the six paper prompts
(:meth:`Sam3Teacher.predict`, the vision encoder once per image).  Peak memory is
``torch.cuda.max_memory_allocated`` over a path's timed calls (reset before each), with the memory held before
the call (both paths' weights) subtracted as ``activation_peak_bytes``.  A batch that runs out of memory stops
the sweep; ``--deadline`` seconds stops it before the next batch.  The JSON is rewritten after every batch, so
a run killed from outside keeps what finished.  On a CPU there is no compile (Sam3Teacher turns it off) and no
peak memory: the CPU run is a smoke test of this script's logic, not a measurement.
"""

from __future__ import annotations

import argparse
import inspect
import platform
import statistics
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

#: what this script calls: (module, name) -> attributes it needs; checked before any work
NEEDS = {("pipeline.teachers.sam3", "Sam3Teacher"): ("predict", "load"),
         ("pipeline.teachers.tiny_sam3", "build_tiny_sam3"): ()}


def require_api() -> dict:
    """The project's objects this script uses, or one clear line and exit 2 when one is absent."""
    import importlib

    found = {}
    for (mod, name), attrs in NEEDS.items():
        try:
            obj = getattr(importlib.import_module(mod), name)
        except (ImportError, AttributeError) as e:
            sys.exit(f"teacher_gpu.py: {mod}.{name} is absent ({type(e).__name__}: {e}); this script needs it")
        missing = [a for a in attrs if not hasattr(obj, a)]
        if missing:
            sys.exit(f"teacher_gpu.py: {mod}.{name} lacks {', '.join(missing)}; this script needs it")
        found[name] = obj
    if "size" not in inspect.signature(found["build_tiny_sam3"]).parameters:
        sys.exit("teacher_gpu.py: build_tiny_sam3 has no size= parameter (size='real' is needed)")
    return found


def write_json(path: Path, obj) -> None:
    from pipeline.artifacts.atomic import write_json as atomic_write_json

    atomic_write_json(path, obj)


def measure(teachers: dict, batches: list[int], resolution: int, repeats: int, deadline_s: float,
            out: Path, record: dict, prompts) -> dict:
    """Fill ``record["batches"]`` per batch (see the module docstring); rewrite ``out`` after each batch.

    Parameters
    ----------
    teachers : {path name: Sam3Teacher}, loaded; their ``batch_size`` is set to each batch in turn.
    batches : images per call, in the order tried.
    resolution : side of the random uint8 input images (the teacher resizes them to its input size).
    repeats : timed rounds per batch (round-robin over the paths).
    deadline_s : seconds from now after which no new batch starts.
    out : the JSON written after every batch.
    record : the document written (``batches``, ``stopped``, ``finished`` are set here).
    prompts : the text prompts of each call.

    Returns
    -------
    dict
        ``record``.
    """
    import torch

    from pipeline.teachers.base import TeacherInput

    t_start = time.perf_counter()
    cuda = all(t.device.type == "cuda" for t in teachers.values())
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    rng = np.random.default_rng(0)
    record.setdefault("batches", {})
    record["stopped"] = None
    for b in batches:
        if time.perf_counter() - t_start > deadline_s:
            record["stopped"] = f"deadline ({deadline_s:.0f} s) before batch {b}"
            break
        items = [TeacherInput(f"img{i}", f"sha{i}", rng.integers(0, 255, (resolution, resolution, 3), dtype=np.uint8))
                 for i in range(b)]
        row: dict = {"paths": {}}
        try:
            for name, t in teachers.items():
                t.batch_size = b  # one forward of all b images
                t0 = time.perf_counter()
                t.predict(items, prompts)
                sync()
                row["paths"][name] = {"first_call_s": round(time.perf_counter() - t0, 3), "seconds": [],
                                      "peak_allocated_bytes": None, "activation_peak_bytes": None}
            for _ in range(repeats):
                for name, t in teachers.items():
                    p = row["paths"][name]
                    if cuda:
                        sync()
                        torch.cuda.reset_peak_memory_stats()
                        before = torch.cuda.memory_allocated()
                    t0 = time.perf_counter()
                    t.predict(items, prompts)
                    sync()
                    p["seconds"].append(time.perf_counter() - t0)
                    if cuda:
                        peak = torch.cuda.max_memory_allocated()
                        p["peak_allocated_bytes"] = max(p["peak_allocated_bytes"] or 0, peak)
                        p["activation_peak_bytes"] = max(p["activation_peak_bytes"] or 0, peak - before)
        except torch.cuda.OutOfMemoryError as e:
            record["stopped"] = f"out of memory at batch {b}: {str(e).splitlines()[0][:160]}"
            torch.cuda.empty_cache()
            break
        for p in row["paths"].values():
            s = p["seconds"]
            p["ms_per_image_median"] = statistics.median(s) / b * 1e3
            p["ms_per_image_min"] = min(s) / b * 1e3
        if len(row["paths"]) == 2 and "eager" in row["paths"] and "compiled" in row["paths"]:
            row["eager_over_compiled_median"] = (row["paths"]["eager"]["ms_per_image_median"]
                                                 / row["paths"]["compiled"]["ms_per_image_median"])
        record["batches"][str(b)] = row
        print(f"batch {b:3d}: " + "; ".join(
            f"{n} {p['ms_per_image_median']:.1f} ms/image (min {p['ms_per_image_min']:.1f}, first call "
            f"{p['first_call_s']:.1f} s, peak {fmt_bytes(p['peak_allocated_bytes'])})"
            for n, p in row["paths"].items()), flush=True)
        write_json(out, record)
    record["finished"] = record["stopped"] is None
    write_json(out, record)
    return record


def fmt_bytes(n: int | None) -> str:
    return "n/a" if n is None else f"{n / 2**30:.2f} GiB"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--size", choices=["tiny", "real"], default="real")
    ap.add_argument("--checkpoint", default=None, help="a SAM 3 directory instead of building a random one")
    ap.add_argument("--dtype", choices=["bf16", "fp32"], default="bf16")
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 2, 4, 8, 16, 32])
    ap.add_argument("--paths", nargs="+", choices=["compiled", "eager"], default=["compiled", "eager"])
    ap.add_argument("--resolution", type=int, default=384, help="side of the input images (resized by SAM 3)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--deadline", type=float, default=1e9, help="seconds after which no new batch starts")
    ap.add_argument("--out", default="teacher_gpu.json")
    a = ap.parse_args(argv)
    api = require_api()
    import torch

    from pipeline.params import PAPER_PROMPTS

    t0 = time.perf_counter()
    out = Path(a.out)
    record = {"what": "real-size SAM 3 teacher (random weights: cost only, not answers), six prompts, "
                      f"{a.dtype}, Sam3Teacher.predict at each batch; medians and minima of {a.repeats} "
                      "round-robin calls per path", "date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
              "device": a.device, "size": a.size, "dtype": a.dtype, "resolution": a.resolution,
              "repeats": a.repeats, "batches_asked": a.batches, "torch": torch.__version__, "cuda": torch.version.cuda,
              "card": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
              "host": platform.node(), "prompts": list(PAPER_PROMPTS)}
    with tempfile.TemporaryDirectory() as tmp:
        if a.checkpoint:
            ckpt = Path(a.checkpoint)
        else:
            tb = time.perf_counter()
            ckpt = api["build_tiny_sam3"](Path(tmp) / "sam3", size=a.size,
                                          words=tuple(dict.fromkeys(w for p in PAPER_PROMPTS for w in p.split())))
            record["build_s"] = round(time.perf_counter() - tb, 1)
        teachers = {}
        tl = time.perf_counter()
        for path in a.paths:
            t = api["Sam3Teacher"](ckpt, device=a.device, dtype=a.dtype, batch_size=1, resolution=(a.resolution,) * 2,
                                   score_threshold=0.0, compile=(path == "compiled"))
            model = t.load()
            teachers[path] = t
            record.setdefault("compile_active", {})[path] = bool(getattr(t, "compile", False))
            record["parameters"] = sum(p.numel() for p in model.parameters())
            record["weights_bytes"] = sum(p.numel() * p.element_size() for p in model.parameters())
        record["load_s"] = round(time.perf_counter() - tl, 1)
        left = a.deadline - (time.perf_counter() - t0)
        measure(teachers, a.batches, a.resolution, a.repeats, left, out, record, PAPER_PROMPTS)
    print(f"wrote {out}: batches {sorted(int(b) for b in record['batches'])}"
          + (f"; stopped: {record['stopped']}" if record["stopped"] else ""), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
