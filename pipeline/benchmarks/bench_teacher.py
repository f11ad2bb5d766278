"""Teacher speed: seconds per image and the encoder-reuse speed-up of the SAM 3 backend.

    python -m pipeline.benchmarks.bench_teacher                       # tiny random SAM 3 on CPU (no download)
    python -m pipeline.benchmarks.bench_teacher --size real --device cuda --dtype bf16 --images 8   # GPU, full-size random weights

Today's path beside the new one (issue 19 item 4), same run, same images: ``today`` = the former
params defaults (fp32, 2 images per forward, eager) against ``new`` = ``--dtype`` (default auto: bf16 on
CUDA, fp32 on a CPU), ``--batch-size`` (default 0 = from free GPU memory) and ``--compile``, with the
agreement of their answers (mean per-image mask IoU, max score difference; bf16 tolerance on CUDA).

    python -m pipeline.benchmarks.bench_teacher --size real --device cuda --images 16 --compile

Also measured in the same run: six separate calls per image (vision encoder + heads for each
prompt, :meth:`Sam3Teacher.predict_one_prompt_at_a_time`) against the backend's path (vision encoder
once per image batch, features repeated to the six prompts, text encoded once per run).  Also
prints the SIMULATOR's seconds per image for orientation.  Paper: 447.9 ms per image for six prompts
on an RTX 4090 (840.5 M parameters).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

PROMPTS = ["spacecraft", "satellite", "space probe", "space vehicle",
           "spacecraft with rigid body and appendages", "artificial object in space with panels and antennas"]


def _time(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", choices=["tiny", "real"], default="tiny")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--dtype", choices=["auto", "fp32", "bf16"], default="auto")
    ap.add_argument("--images", type=int, default=6)
    ap.add_argument("--resolution", type=int, default=128, help="working resolution of the input images")
    ap.add_argument("--batch-size", type=int, default=0, help="0 = from free GPU memory (2 on a CPU)")
    ap.add_argument("--compile", action="store_true", help="torch.compile the vision encoder (CUDA only)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--checkpoint", default=None, help="use this SAM 3 directory instead of building a random one")
    args = ap.parse_args()

    import torch

    from pipeline.teachers.base import TeacherInput
    from pipeline.teachers.sam3 import Sam3Teacher
    from pipeline.teachers.simulated import SimulatedFoundationTeacher
    from pipeline.teachers.tiny_sam3 import build_tiny_sam3

    rng = np.random.default_rng(0)
    r = args.resolution
    items = [TeacherInput(f"img{i}", f"sha{i}", rng.integers(0, 255, (r, r, 3), dtype=np.uint8))
             for i in range(args.images)]
    with tempfile.TemporaryDirectory() as tmp:
        ckpt = Path(args.checkpoint) if args.checkpoint else build_tiny_sam3(
            Path(tmp) / "sam3", size=args.size, words=tuple(w for p in PROMPTS for w in p.split()))
        teacher = Sam3Teacher(ckpt, device=args.device, dtype=args.dtype, batch_size=args.batch_size,
                              resolution=(r, r), score_threshold=0.0, compile=args.compile)
        today = Sam3Teacher(ckpt, device=args.device, dtype="fp32", batch_size=2, resolution=(r, r),
                            score_threshold=0.0)
        model = teacher.load()
        n_params = sum(p.numel() for p in model.parameters())
        teacher.predict(items[:1], PROMPTS)  # warm-up (text features cached here, as in a run)
        sync = torch.cuda.synchronize if teacher.device.type == "cuda" else (lambda: None)

        def batched():
            teacher.predict(items, PROMPTS)
            sync()

        def separate():
            teacher.predict_one_prompt_at_a_time(items, PROMPTS)
            sync()

        def todays():
            today.predict(items, PROMPTS)
            sync()

        batched()   # warm-up of every path: CPU kernels and CUDA graphs are built per tensor shape
        separate()
        todays()
        t_batched = _time(batched, args.repeats)
        t_separate = _time(separate, args.repeats)
        t_today = _time(todays, args.repeats)
        from pipeline.metrics import image_ious

        m_new, s_new = teacher.predict(items, PROMPTS)
        m_old, s_old = today.predict(items, PROMPTS)
        agree = float(np.mean(image_ious(m_new.reshape(-1, r, r), m_old.reshape(-1, r, r))))
        score_diff = float(np.max(np.abs(s_new - s_old))) if s_new.size else 0.0
        del today
    sim_items = []
    for it in items:
        m = np.zeros((r, r), bool)
        m[r // 4: r // 2, r // 4: 3 * r // 4] = True
        sim_items.append(TeacherInput(it.image_id, it.image_sha256, it.image, reference={"mask": m}))
    sim = SimulatedFoundationTeacher(resolution=(r, r))
    t_sim = _time(lambda: sim.predict(sim_items, PROMPTS), args.repeats)

    n = args.images
    print(f"SAM 3 ({args.size}, {n_params / 1e6:.2f} M parameters, random weights) on {teacher.device} "
          f"{teacher.dtype_name}{'+tf32' if teacher.tf32 else ''} (--dtype {args.dtype}), {n} images {r}x{r}, "
          f"6 prompts, batch {teacher.batch_size}, compile {teacher.compile}, best of {args.repeats}")
    print(f"  today's path (fp32, batch 2, eager):  {t_today / n * 1e3:9.1f} ms/image")
    print(f"  new path:                             {t_batched / n * 1e3:9.1f} ms/image")
    print(f"  new / today speed-up:                 {t_today / t_batched:9.2f} x  (target 25 ms/image on an H100)")
    print(f"  answers vs today: mean mask IoU {agree:.4f}, max |score difference| {score_diff:.3g}")
    print(f"  encoder reused (one pass, 6 prompts): {t_batched / n * 1e3:9.1f} ms/image")
    print(f"  six separate calls (baseline):        {t_separate / n * 1e3:9.1f} ms/image")
    print(f"  encoder-reuse speed-up:               {t_separate / t_batched:9.2f} x")
    print(f"  teacher seconds per image:            {t_batched / n:9.4f} s")
    print(f"SIMULATOR (simulated backend):          {t_sim / n * 1e3:9.2f} ms/image")
    print("paper: SAM 3 teacher 447.9 ms/image (six prompts, RTX 4090)")


if __name__ == "__main__":
    main()
