"""Segmenting image files: discover the inputs, plan the outputs, write the mask/prob/overlay PNGs and
skipped.csv.

Decision (the paper is silent on deployment): images are read by
:func:`pipeline.datasets.loading.read_rgb` and resized to the working resolution exactly as the
training images were (:func:`~pipeline.datasets.loading.resize_image`, area interpolation, square);
the probability map is resized back to the original size (bilinear) and thresholded there
(eq:inference-mask, :func:`pipeline.thresholds.mask_from_probs`), which keeps boundaries smoother than
resizing a binary mask.
"""

from __future__ import annotations

import csv
import dataclasses
import os
import time
import uuid
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from pipeline.deploy.segmenter import Segmenter
from pipeline.errors import InputError
from pipeline.thresholds import mask_from_probs

OUTPUT_SUFFIXES = ("_mask.png", "_prob.png", "_overlay.png")


def discover_images(input_path: str | Path) -> tuple[Path, list[Path]]:
    """(root, image files): a single file (any suffix; the reader decides), or every file with a
    supported image suffix under a folder, recursively, sorted, hidden entries skipped."""
    from pipeline.datasets.loading import SUPPORTED_SUFFIXES

    p = Path(input_path)
    if not p.exists():
        raise InputError(f"--input {p}: not found")
    if p.is_file():
        return p.parent, [p]
    files = sorted(f for f in p.rglob("*") if f.is_file() and f.suffix.lower() in SUPPORTED_SUFFIXES
                   and not any(part.startswith(".") for part in f.relative_to(p).parts))
    return p, files


def _is_within(child: Path, parent: Path) -> bool:
    try:
        child.relative_to(parent)
        return True
    except ValueError:
        return False


def plan_outputs(root: Path, files: Sequence[Path], out_dir: str | Path, input_is_dir: bool) -> list[Path]:
    """Output stem per input (``out/<relative folder>/<stem>``; ``<stem>_<ext>`` where two inputs of a
    folder share a stem).  Refuses (InputError) an output folder equal to or inside an input folder,
    and any output file that would be one of the inputs."""
    out = Path(out_dir).resolve()
    root_r = root.resolve()
    if input_is_dir and (out == root_r or _is_within(out, root_r)):
        raise InputError(f"--output {out_dir}: inside the input folder {root}; outputs must not mix with inputs")
    rel = [f.resolve().relative_to(root_r) if input_is_dir else Path(f.name) for f in files]
    counts: dict[tuple[Path, str], int] = {}
    for r in rel:
        counts[(r.parent, r.stem)] = counts.get((r.parent, r.stem), 0) + 1
    stems = []
    for r in rel:
        name = r.stem if counts[(r.parent, r.stem)] == 1 else f"{r.stem}_{r.suffix.lstrip('.').lower()}"
        stems.append(out / r.parent / name)
    inputs = {f.resolve() for f in files}
    for s in stems:
        for suffix in OUTPUT_SUFFIXES:
            target = s.with_name(s.name + suffix)
            if target in inputs:
                raise InputError(f"--output {out_dir}: would overwrite the input {target}")
    return stems


def probs_to_size(probs: np.ndarray, height: int, width: int) -> np.ndarray:
    """Bilinear resize of a probability map [R,R] to the original [height, width] (values stay in [0,1])."""
    import cv2

    if probs.shape == (height, width):
        return probs
    return np.clip(cv2.resize(probs, (width, height), interpolation=cv2.INTER_LINEAR), 0.0, 1.0)


def overlay_image(image: np.ndarray, mask: np.ndarray, color=(255, 40, 40), alpha: float = 0.45) -> np.ndarray:
    """RGB uint8 overlay: mask tinted with ``color`` at ``alpha``, its inner contour drawn opaque."""
    import cv2

    out = image.astype(np.float32)
    col = np.asarray(color, np.float32)
    out[mask] = (1 - alpha) * out[mask] + alpha * col
    edge = mask & ~cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    out[edge] = col
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def write_png(path: Path, array: np.ndarray) -> None:
    """Write a PNG atomically (temp name, then rename); RGB arrays are converted to OpenCV's BGR."""
    import cv2

    arr = array[..., ::-1] if array.ndim == 3 else array
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(arr))
    if not ok:
        raise InputError(f"{path}: PNG encoding failed")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{uuid.uuid4().hex[:8]}")
    try:
        tmp.write_bytes(buf.tobytes())
        os.replace(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise InputError(f"{path}: cannot write ({e.strerror or e})") from None


@dataclasses.dataclass
class SegmentResult:
    written: list[Path]
    skipped: list[tuple[str, str]]  # (input path, reason)
    model_seconds: float = 0.0      # wall time inside the engine (Z = f(x) and sigmoid), all batches
    total_seconds: float = 0.0      # wall time of the whole loop (reading, resizing, PNG writing included)


def segment_files(segmenter: Segmenter, files: Sequence[Path], stems: Sequence[Path], *, tau: float,
                  resolution: int, batch_size: int = 8, save_prob: bool = False, overlay: bool = False,
                  on_skip: Callable[[str, str], None] | None = None) -> SegmentResult:
    """Segment image files in batches: read -> resize to R x R -> P = sigmoid(f(x)) -> resize P back
    to the original size -> M = [P >= tau] (eq:inference-mask) -> ``<stem>_mask.png`` (0/255), and
    optionally ``<stem>_prob.png`` (P as uint8, 255 = 1.0) and ``<stem>_overlay.png``.

    A file the reader rejects (InputError) is recorded in ``skipped`` and the rest go on.
    """
    from pipeline.datasets.loading import read_rgb, resize_image
    from pipeline.progress import progress

    written: list[Path] = []
    skipped: list[tuple[str, str]] = []
    model_s = 0.0
    t_start = time.perf_counter()
    bar = progress(total=len(files), desc="segment", unit="img")
    try:
        for s in range(0, len(files), batch_size):
            batch = []
            for f, stem in zip(files[s:s + batch_size], stems[s:s + batch_size]):
                try:
                    img = read_rgb(f)
                except InputError as e:
                    reason = str(e).splitlines()[0] if str(e) else type(e).__name__
                    reason = reason[len(f"{f}: "):] if reason.startswith(f"{f}: ") else reason
                    skipped.append((str(f), reason))
                    if on_skip is not None:
                        on_skip(str(f), reason)
                    bar.update(1)
                    continue
                batch.append((stem, img))
            if not batch:
                continue
            work = np.stack([resize_image(img, resolution) for _, img in batch])
            t0 = time.perf_counter()
            probs = segmenter.predict_probs(work, batch_size=batch_size)
            model_s += time.perf_counter() - t0
            for (stem, img), p in zip(batch, probs):
                h, w = img.shape[:2]
                p_full = probs_to_size(p, h, w)
                mask = mask_from_probs(p_full, tau)
                out = stem.with_name(stem.name + "_mask.png")
                write_png(out, mask.astype(np.uint8) * 255)
                written.append(out)
                if save_prob:
                    write_png(stem.with_name(stem.name + "_prob.png"),
                              np.round(p_full * 255).astype(np.uint8))
                if overlay:
                    write_png(stem.with_name(stem.name + "_overlay.png"), overlay_image(img, mask))
                bar.update(1)
    finally:
        bar.close()
    return SegmentResult(written, skipped, model_s, time.perf_counter() - t_start)


def write_skipped_csv(path: str | Path, skipped: Iterable[tuple[str, str]]) -> Path:
    """``skipped.csv`` (columns path, reason), written atomically; header only when nothing was skipped."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{uuid.uuid4().hex[:8]}")
    with open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["path", "reason"])
        w.writerows(skipped)
    os.replace(tmp, path)
    return path
