"""What the benchmark stage costs a ``geodistill distill`` run: the same distill with the distill profile's
benchmark plan and with one variant (:data:`pipeline.deploy.benchmark.BASELINE_VARIANT`), each into a fresh
project, round-robin; medians, minima and their ratio against the 1.5x target.

    python -m benchmarks.bench_distill IMAGES --checkpoint SAM3_DIR --reps 3 --set train.epochs_stage1=1
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Callable, Sequence

from benchmarks.common import medians, minima, parser, round_robin, seconds
from pipeline.deploy.benchmark import BASELINE_VARIANT

TARGET = 1.5  # default distill wall time / the one-variant run's
#: the cases: name -> the extra --set items of the distill command
CASES = {"one variant": [f"deploy.benchmark_variants=[{BASELINE_VARIANT}]"], "default": []}


def distill_argv(images: str, out: Path, teacher: Sequence[str], sets: Sequence[str]) -> list[str]:
    return [sys.executable, "-m", "pipeline.cli", "distill", images, "--out", str(out), *teacher,
            *[a for kv in sets for a in ("--set", kv)]]


def run_command(argv: list[str]) -> float:
    """Wall seconds of ``argv``; a failed run is an error (it times nothing)."""
    def call():
        r = subprocess.run(argv, capture_output=True, text=True)
        if r.returncode != 0:
            raise SystemExit(f"geodistill {' '.join(argv[3:7])} ... failed:\n{r.stderr[-2000:]}")
    return seconds(call)


def summary(times: dict[str, list[float]]) -> str:
    med, low = medians(times), minima(times)
    lines = [f"{n:12s} median {med[n]:7.1f} s  min {low[n]:7.1f} s  ({len(t)} runs)" for n, t in times.items()]
    ratio, ratio_min = med["default"] / med["one variant"], low["default"] / low["one variant"]
    lines.append(f"default / one variant: {ratio:.2f}x (medians), {ratio_min:.2f}x (minima); target <= {TARGET:g}x: "
                 + ("met" if ratio <= TARGET else "NOT met"))
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None, run: Callable[[list[str]], float] = run_command) -> dict[str, list[float]]:
    ap = parser(__doc__, set=[])
    ap.add_argument("images", help="the input folder of `geodistill distill`")
    ap.add_argument("--checkpoint", help="SAM 3 folder (or give --labels / --backend imported --imported-dir)")
    ap.add_argument("--labels", help="a `geodistill label` output of the same images")
    ap.add_argument("--backend")
    ap.add_argument("--imported-dir")
    ap.add_argument("--reps", type=int, default=3, help="round-robin rounds")
    ap.add_argument("--workdir", default=None, help="where the projects go (default: a temporary folder)")
    args = ap.parse_args(argv)
    teacher = [a for flag in ("checkpoint", "labels", "backend", "imported_dir") if getattr(args, flag)
               for a in ("--" + flag.replace("_", "-"), getattr(args, flag))] + ["--device", "cpu", "--quiet"]
    with tempfile.TemporaryDirectory() as td:
        work = Path(args.workdir or td)
        cases = {name: (lambda i, name=name, extra=extra: run(distill_argv(
            args.images, work / f"{name.replace(' ', '_')}_{i}", teacher, [*args.sets, *extra])))
            for name, extra in CASES.items()}
        times = round_robin(cases, args.reps, order="alternate")
    print(f"bench_distill: {args.images}, {args.reps} round(s), round-robin; settings: "
          + (", ".join(args.sets) or "the distill profile's"))
    print(summary(times))
    return times


if __name__ == "__main__":
    main()
