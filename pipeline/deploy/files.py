"""Segmenting image files: discover the inputs, plan the outputs, write the mask/prob/overlay PNGs and
skipped.csv.

Decision (the paper is silent on deployment): images are read by
:func:`pipeline.datasets.loading.read_rgb` and resized to the working resolution exactly as the
training images were (:func:`~pipeline.datasets.loading.resize_image`, area interpolation, square);
the probability map is resized back to the original size (bilinear) and thresholded there
(eq:inference-mask, :func:`pipeline.thresholds.mask_from_probs`), which keeps boundaries smoother than
resizing a binary mask.

Output names (decision): an input keeps its whole name, extension included, and its sub-folder
relative to the input folder; a fixed suffix is appended: ``sub/a.png`` -> ``<out>/sub/a.png.mask.png``
(and ``a.png.prob.png``, ``a.png.overlay.png``).  Distinct input paths therefore give distinct output
paths (``a.png``, ``a.jpg`` and ``a_png.png`` cannot meet).  Before anything is written
(:func:`plan_outputs`) the run is refused (InputError, one line) when two inputs' outputs differ only in
letter case (``b.png`` / ``b.PNG``: one would replace the other on a case-insensitive disk, and on
any disk the folder could not be copied to one), when an output would be a file where another output
needs a folder, when ``--output`` (or a folder on the way) is a file, when an output would replace an
input, and -- unless ``overwrite`` -- when an output file or skipped.csv already exists that no
``segment.json`` of an earlier run lists (:mod:`pipeline.ownership`: a rerun replaces its own outputs,
never a file it did not write).

Symbolic links inside an input folder (decision): a link to an image inside the input folder is
segmented under the link's own name; a link whose target lies outside the input folder, a broken link
and a link to a folder (never followed) are skipped and reported like unreadable files -- a stderr line
and a row of skipped.csv -- so the run neither escapes the folder nor drops anything silently.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import os
import time
import uuid
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from pipeline.datasets.loading import probs_to_size, read_rgb, resize_image
from pipeline.datasets.manifest import SKIPPED_COLUMNS
from pipeline.datasets.scan import Inputs, _is_within, scan_inputs  # noqa: F401  (the folder scan, re-exported)
from pipeline.deploy.segmenter import Segmenter
from pipeline.errors import InputError
from pipeline.ownership import owned_outputs, refuse_unowned
from pipeline.progress import progress
from pipeline.thresholds import mask_from_probs

MASK_SUFFIX, PROB_SUFFIX, OVERLAY_SUFFIX = ".mask.png", ".prob.png", ".overlay.png"
OUTPUT_SUFFIXES = (MASK_SUFFIX, PROB_SUFFIX, OVERLAY_SUFFIX)
SKIPPED_CSV = "skipped.csv"
#: segment's record (pipeline.ownership): the outputs a rerun may replace without --overwrite
RECORD = "segment.json"


def output_path(stem: Path, suffix: str) -> Path:
    """``<stem><suffix>``: the stem is the output folder joined with the input's relative path."""
    return stem.with_name(stem.name + suffix)


def output_suffixes(save_prob: bool = False, overlay: bool = False) -> tuple[str, ...]:
    """The output kinds one run writes: the mask, and the probability map / overlay when asked for."""
    return (MASK_SUFFIX,) + ((PROB_SUFFIX,) if save_prob else ()) + ((OVERLAY_SUFFIX,) if overlay else ())


def discover_images(input_path: str | Path) -> tuple[Path, list[Path]]:
    """(root, image files) of :func:`scan_inputs` (the skipped entries are dropped: use scan_inputs)."""
    found = scan_inputs(input_path)
    return found.root, found.files


def _relative(f: Path, root: Path, root_r: Path) -> Path:
    """``f`` relative to the input folder, by its own (link) name when it lies lexically under it."""
    try:
        return f.relative_to(root)
    except ValueError:
        return f.resolve().relative_to(root_r)


def _blocking_file(folder: Path, cache: dict[Path, Path | None]) -> Path | None:
    """The first existing non-folder among ``folder`` and its parents (mkdir would fail on it), else None."""
    for p in (folder, *folder.parents):
        if p in cache:
            found = cache[p]
            break
        if p.is_symlink() or p.exists():
            found = None if p.is_dir() else p
            break
    else:
        found = None
    cache[folder] = found
    return found


def plan_outputs(root: Path, files: Sequence[Path], out_dir: str | Path, input_is_dir: bool, *,
                 suffixes: Sequence[str] = (MASK_SUFFIX,), overwrite: bool = False) -> list[Path]:
    """Output stem per input, ``<out>/<relative folder>/<whole input name>`` (module docstring), after
    every check that can refuse the run, so that a refused run writes nothing.

    InputError (one line naming the path) when: ``out_dir`` or a folder on its way is a file; the
    output folder is, or is inside, the input folder; two inputs' outputs differ only in letter case,
    or one output file would be a folder another output needs; an output would be one of the inputs;
    an output is an existing folder; ``overwrite`` is False and an output file of the kinds
    ``suffixes``, ``skipped.csv`` or ``segment.json`` already exists that the ``segment.json`` of an
    earlier run does not list (the first one is named; :mod:`pipeline.ownership`).
    """
    out = Path(out_dir).absolute()
    cache: dict[Path, Path | None] = {}
    blocked = _blocking_file(out, cache)
    if blocked is not None:
        what = "is a file" if blocked == out else f"{blocked} is a file"
        raise InputError(f"--output {out_dir}: {what}, not a folder")
    out = out.resolve()
    root_r = root.resolve()
    if input_is_dir and (out == root_r or _is_within(out, root_r)):
        raise InputError(f"--output {out_dir}: inside the input folder {root}; outputs must not mix with inputs")
    rel = [_relative(f, root, root_r) if input_is_dir else Path(f.name) for f in files]

    # distinct input paths give distinct names; letter case and file/folder clashes are checked here
    by_key: dict[str, Path] = {}
    for f, r in zip(files, rel):
        key = r.as_posix().casefold()
        if key in by_key:
            raise InputError(f"--input: {by_key[key]} and {f} differ only in letter case, so their outputs "
                             f"would be one file on a case-insensitive disk (in {out}); rename one")
        by_key[key] = f
    folders: dict[str, Path] = {}
    for f, r in zip(files, rel):
        for parent in r.parents:
            if parent != Path("."):
                folders.setdefault(parent.as_posix().casefold(), f)
    for f, r in zip(files, rel):
        for suffix in OUTPUT_SUFFIXES:
            key = (r.as_posix() + suffix).casefold()
            if key in folders:
                raise InputError(f"--input: the output {out / r}{suffix} of {f} would be the folder holding "
                                 f"the output of {folders[key]}; rename one")

    stems = [out / r for r in rel]
    inputs = {f.resolve() for f in files}
    for s in stems:
        for suffix in OUTPUT_SUFFIXES:
            target = output_path(s, suffix)
            if target.resolve() in inputs:
                raise InputError(f"--output {out_dir}: would overwrite the input {target}")
    targets = [output_path(s, suffix) for s in stems for suffix in suffixes] + [out / SKIPPED_CSV, out / RECORD]
    for t in targets:
        blocked = _blocking_file(t.parent, cache)
        if blocked is not None:
            raise InputError(f"--output {out_dir}: {blocked} is a file where a folder is needed for {t.name}")
        if t.is_dir():
            raise InputError(f"--output {out_dir}: {t} is a folder; an output file must go there")
    own = [out / r for r in owned_outputs(out, RECORD, "segment")]
    refuse_unowned(targets, own, command="segment", option="--output", where=out_dir,
                   why=f"not listed in a {RECORD} there", overwrite=overwrite)
    return stems


def relative_outputs(out_dir: str | Path, stems: Sequence[Path], suffixes: Sequence[str]) -> list[str]:
    """The output files of ``stems`` (from :func:`plan_outputs`) and skipped.csv, relative to
    ``out_dir`` (posix): what ``segment.json`` lists."""
    out = Path(out_dir).absolute().resolve()
    return [output_path(s, x).relative_to(out).as_posix() for s in stems for x in suffixes] + [SKIPPED_CSV]


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
    tmp = path.with_name(f".{path.name}.tmp-{uuid.uuid4().hex[:8]}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_bytes(buf.tobytes())
        os.replace(tmp, path)
    except OSError as e:
        with contextlib.suppress(OSError):
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
                  on_skip: Callable[[str, str, InputError], None] | None = None,
                  max_pixels: int | None = None) -> SegmentResult:
    """Segment image files in batches: read -> resize to R x R -> P = sigmoid(f(x)) -> resize P back
    to the original size -> M = [P >= tau] (eq:inference-mask) -> ``<stem>.mask.png`` (0/255), and
    optionally ``<stem>.prob.png`` (P as uint8, 255 = 1.0) and ``<stem>.overlay.png`` (stems from
    :func:`plan_outputs`, which has already refused collisions and unwanted overwrites).

    A file the reader rejects (InputError; above ``max_pixels`` on its header, None = ``data.max_pixels``'s
    default, before decoding) is recorded in ``skipped``, handed to ``on_skip(path, reason, error)``, and
    the rest go on.
    """
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
                    img = read_rgb(f, max_pixels=max_pixels)
                except InputError as e:
                    reason = str(e).splitlines()[0] if str(e) else type(e).__name__
                    reason = reason[len(f"{f}: "):] if reason.startswith(f"{f}: ") else reason
                    skipped.append((str(f), reason))
                    if on_skip is not None:
                        on_skip(str(f), reason, e)
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
                out = output_path(stem, MASK_SUFFIX)
                write_png(out, mask.astype(np.uint8) * 255)
                written.append(out)
                if save_prob:
                    write_png(output_path(stem, PROB_SUFFIX),
                              np.round(p_full * 255).astype(np.uint8))
                if overlay:
                    write_png(output_path(stem, OVERLAY_SUFFIX), overlay_image(img, mask))
                bar.update(1)
    finally:
        bar.close()
    return SegmentResult(written, skipped, model_s, time.perf_counter() - t_start)


def write_skipped_csv(path: str | Path, skipped: Iterable[tuple[str, str, str]]) -> Path:
    """``skipped.csv`` (columns image_id, path, reason: those of skipped_files.parquet,
    :data:`pipeline.datasets.manifest.SKIPPED_COLUMNS`), written atomically; header only when nothing
    was skipped."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{uuid.uuid4().hex[:8]}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(list(SKIPPED_COLUMNS))
            w.writerows(skipped)
        os.replace(tmp, path)
    except OSError as e:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise InputError(f"{path}: cannot write ({e.strerror or e})") from None
    return path
