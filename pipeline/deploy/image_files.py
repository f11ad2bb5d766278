"""``geodistill segment``'s logic (``pipeline/cli/segment.py`` is its wiring): image files in, mask files out.

The masks are M = [P >= tau] (eq:inference-mask) at each frame's own size, with a checkpoint or a deploy bundle
loaded as a :class:`pipeline.deploy.segmenter.Segmenter`.  Every output is planned (and refused) before anything
is written; reading and writing overlap the inference.  Output names and refusals: docs/real-data.md.
"""

from __future__ import annotations

import collections
import contextvars
import dataclasses
import functools
import queue
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Mapping, Sequence

import numpy as np

from pipeline.artifacts.atomic import write_csv, write_png
from pipeline.artifacts.ownership import claim_outputs, owned_outputs, refuse_unowned
from pipeline.catalog import output_file, output_names
from pipeline.datasets.loading import (BadFileError, check_bit_depth, pixel_limit, probs_to_size, read_rgb,
                                       reset_frame_warnings, resize_image)
from pipeline.datasets.manifest import BadInputPolicy, write_skipped_csv
from pipeline.datasets.scan import scan_inputs
from pipeline.deploy.confidence import frame_confidence
from pipeline.engine_table import AUTO
from pipeline.params import PAPER
from pipeline.runtime.device import resolve_device
from pipeline.runtime.errors import CHECKPOINT, InputError
from pipeline.runtime.progress import progress
from pipeline.thresholds import MIN_RESOLUTION, RESOLUTION_LABELS, mask_from_probs, resolve_resolution

if TYPE_CHECKING:  # torch: loaded by segment_images once the options are checked
    from pipeline.deploy.segmenter import Segmenter

__all__ = ["MASK_SUFFIX", "PROB_SUFFIX", "OVERLAY_SUFFIX", "OUTPUT_SUFFIXES", "SKIPPED_CSV", "CONFIDENCE_CSV", "RECORD",
           "output_path", "output_suffixes", "plan_outputs", "SegmentResult", "IO_WORKERS", "segment_files",
           "check_options", "segment_images", "model_resolution"]

#: the output files' suffixes (pipeline.catalog): the mask, the probabilities and the overlay of one input
MASK_SUFFIX, PROB_SUFFIX, OVERLAY_SUFFIX = output_names("segment", "mask", "prob", "overlay").values()
OUTPUT_SUFFIXES = (MASK_SUFFIX, PROB_SUFFIX, OVERLAY_SUFFIX)
#: the run's own files in the output folder: skipped inputs, frame confidences, and the record of its outputs
SKIPPED_CSV, CONFIDENCE_CSV, RECORD = (output_file("segment", k) for k in ("skipped", "confidence", "record"))


def output_path(stem: Path, suffix: str) -> Path:
    """Name one output file: ``<stem><suffix>``.

    Parameters
    ----------
    stem : Path
        The output folder joined with the input's relative path (:func:`plan_outputs`).
    suffix : str
        One of :data:`OUTPUT_SUFFIXES`.

    Returns
    -------
    Path
        The output file.
    """
    return stem.with_name(stem.name + suffix)


def output_suffixes(save_prob: bool = False, overlay: bool = False) -> tuple[str, ...]:
    """List the output kinds one run writes.

    Parameters
    ----------
    save_prob : bool
        The probabilities are written too (``--save-prob``).
    overlay : bool
        The overlays are written too (``--overlay``).

    Returns
    -------
    tuple of str
        :data:`MASK_SUFFIX`, then the others asked for.
    """
    return (MASK_SUFFIX,) + ((PROB_SUFFIX,) if save_prob else ()) + ((OVERLAY_SUFFIX,) if overlay else ())


def _relative(f: Path, root: Path, root_r: Path) -> Path:
    """Place ``f`` relative to the input folder, by its own (link) name when it lies lexically under it."""
    try:
        return f.relative_to(root)
    except ValueError:
        return f.resolve().relative_to(root_r)


def _blocking_file(folder: Path, cache: dict[Path, Path | None]) -> Path | None:
    """Find the first existing non-folder among ``folder`` and its parents (mkdir would fail on it), else None."""
    found = None
    for p in (folder, *folder.parents):
        if p in cache or p.is_symlink() or p.exists():
            found = cache[p] if p in cache else None if p.is_dir() else p
            break
    cache[folder] = found
    return found


def plan_outputs(root: Path, files: Sequence[Path], out_dir: str | Path, input_is_dir: bool, *,
                 suffixes: Sequence[str] = (MASK_SUFFIX,), overwrite: bool = False) -> list[Path]:
    """Plan the output stem of each input, after every check that can refuse the run.

    Parameters
    ----------
    root : Path
        The input folder (or the input file's folder).
    files : Sequence of Path
        The input image files.
    out_dir : str or Path
        The output folder (``--output``).
    input_is_dir : bool
        The input is a folder (outputs keep its relative layout), not one file.
    suffixes : Sequence of str
        The output kinds written (:func:`output_suffixes`).
    overwrite : bool
        Replace files no earlier run's record lists (``--overwrite``).

    Returns
    -------
    list of Path
        ``<out>/<relative folder>/<whole input name>`` per input, in the order of ``files``.

    Raises
    ------
    InputError
        One line on the first refusal: a file in the way, outputs inside the input folder, two inputs
        differing only in letter case, an output replacing an input or a folder, or (unless ``overwrite``)
        files no earlier run's record lists (:mod:`pipeline.artifacts.ownership`).
    """
    out = Path(out_dir).absolute()
    cache: dict[Path, Path | None] = {}
    blocked = _blocking_file(out, cache)
    if blocked is not None:
        what = "is a file" if blocked == out else f"{blocked} is a file"
        raise InputError(f"--output {out_dir}: {what}, not a folder")
    out = out.resolve()
    root_r = root.resolve()
    if input_is_dir and out.is_relative_to(root_r):
        raise InputError(f"--output {out_dir}: inside the input folder {root}; outputs must not mix with inputs")
    rel = [_relative(f, root, root_r) if input_is_dir else Path(f.name) for f in files]

    by_key: dict[str, Path] = {}
    folders: dict[str, Path] = {}
    for f, r in zip(files, rel):
        key = r.as_posix().casefold()
        if key in by_key:
            raise InputError(f"--input: {by_key[key]} and {f} differ only in letter case, so their outputs "
                             f"would be one file on a case-insensitive disk (in {out}); rename one")
        by_key[key] = f
        for parent in r.parents[:-1]:  # not "."
            folders.setdefault(parent.as_posix().casefold(), f)
    for f, r in zip(files, rel):
        for suffix in OUTPUT_SUFFIXES:
            if (key := (r.as_posix() + suffix).casefold()) in folders:
                raise InputError(f"--input: the output {out / r}{suffix} of {f} would be the folder holding "
                                 f"the output of {folders[key]}; rename one")

    stems = [out / r for r in rel]
    inputs = {f.resolve() for f in files}
    for target in (output_path(s, suffix) for s in stems for suffix in OUTPUT_SUFFIXES):
        if target.resolve() in inputs:
            raise InputError(f"--output {out_dir}: would overwrite the input {target}")
    targets = [*(output_path(s, x) for s in stems for x in suffixes), out / SKIPPED_CSV, out / CONFIDENCE_CSV,
               out / RECORD]
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
    """List what the run's record holds: the output files, skipped.csv and confidence.csv, relative to ``out_dir``."""
    out = Path(out_dir).absolute().resolve()
    return ([output_path(s, x).relative_to(out).as_posix() for s in stems for x in suffixes]
            + [SKIPPED_CSV, CONFIDENCE_CSV])


def overlay_image(image: np.ndarray, mask: np.ndarray, color=(255, 40, 40), alpha: float = 0.45) -> np.ndarray:
    """Draw an RGB uint8 overlay: the mask tinted with ``color`` at ``alpha``, its inner contour drawn opaque."""
    import cv2

    out = image.astype(np.float32)
    col = np.asarray(color, np.float32)
    out[mask] = (1 - alpha) * out[mask] + alpha * col
    edge = mask & ~cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    out[edge] = col
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


@dataclasses.dataclass
class SegmentResult:
    """What a segment run did.

    Attributes
    ----------
    written : list of Path
        The mask files written, in input order.
    skipped : list of tuple
        ``(input path, reason)`` of each input the reader rejected.
    model_seconds : float
        Seconds inside the engine.
    total_seconds : float
        Seconds of the whole loop (reading, inference, writing).
    scores : list of float
        The frame confidence of each written mask (:func:`pipeline.deploy.confidence.frame_confidence`).
    """

    written: list[Path]
    skipped: list[tuple[str, str]]  # (input path, reason)
    model_seconds: float = 0.0      # inside the engine
    total_seconds: float = 0.0      # the whole loop
    scores: list[float] = dataclasses.field(default_factory=list)  # frame confidence of each written mask


#: segment_files' reader threads (decode + resize) beside the inference; 0 = the serial loop
IO_WORKERS = 1


def _load(f: Path, resolution: int, max_pixels: int | None, keep_image: bool,
          bit_depth: str | int = PAPER.data.bit_depth, letterbox: bool = PAPER.data.letterbox):
    """Read one frame: (the R x R working image, the original (h, w), the original image when ``keep_image``)."""
    img = read_rgb(f, max_pixels=max_pixels, bit_depth=bit_depth)
    return resize_image(img, resolution, letterbox), img.shape[:2], img if keep_image else None


def _save(stem: Path, p: np.ndarray, shape: tuple[int, int], img: np.ndarray | None, tau: float,
          save_prob: bool, overlay: bool, letterbox: bool) -> tuple[Path, float]:
    """Write the PNGs of one image: P back to the original size, M = [P >= tau] (eq:inference-mask).

    Returns (its mask path, the frame's confidence from the working-resolution P).
    """
    h, w = shape
    p_full = probs_to_size(p, h, w, letterbox)
    mask = mask_from_probs(p_full, tau)
    out = output_path(stem, MASK_SUFFIX)
    write_png(out, mask.astype(np.uint8) * 255)
    if save_prob:
        write_png(output_path(stem, PROB_SUFFIX), np.round(p_full * 255).astype(np.uint8))
    if overlay:
        write_png(output_path(stem, OVERLAY_SUFFIX), overlay_image(img, mask))
    return out, frame_confidence(p, tau)


class _Writer:
    """Run :func:`_save` on jobs in order.

    In the caller's thread (``depth`` 0), else in a thread through a queue of ``depth`` (memory stays flat),
    where the first error drops later jobs and :meth:`flush` raises it in the caller's thread.
    """

    def __init__(self, depth: int, done: Callable[[], None]):
        self.written: list[tuple[Path, float]] = []  # (mask path, frame confidence) per written image
        self.error: BaseException | None = None
        self.abort = False
        self._done = done
        self._q: queue.Queue = queue.Queue(maxsize=depth)
        self._thread = threading.Thread(target=self._run, name="segment-write", daemon=True) if depth else None
        if self._thread is not None:
            self._thread.start()

    def _write(self, job) -> None:
        self.written.append(_save(*job))
        self._done()

    def _run(self) -> None:
        while True:
            job = self._q.get()
            try:
                if job is None:
                    return
                if self.error is None and not self.abort:
                    self._write(job)
            except BaseException as e:  # noqa: BLE001 -- handed to the caller's thread by flush/close
                self.error = e
            finally:
                self._q.task_done()

    def put(self, job) -> None:
        if self.error is not None:
            raise self.error
        if self._thread is None:
            self._write(job)
        else:
            self._q.put(job)

    def flush(self) -> None:
        """Wait until every job put so far is written; raise the writer's error."""
        self._q.join()
        if self.error is not None:
            raise self.error

    def close(self) -> None:
        """Stop the thread after the jobs put so far (dropped after :attr:`abort`)."""
        if self._thread is not None:
            self._q.put(None)
            self._thread.join()


def segment_files(segmenter: Segmenter, files: Sequence[Path], stems: Sequence[Path], *, tau: float,
                  resolution: int, batch_size: int = 8, save_prob: bool = False, overlay: bool = False,
                  on_skip: Callable[[str, str, InputError], None] | None = None,
                  max_pixels: int | None = None, workers: int = IO_WORKERS) -> SegmentResult:
    """Segment image files in batches into ``<stem>.mask.png`` (and ``.prob.png``, ``.overlay.png``).

    A file the reader rejects is skipped and handed to ``on_skip``.  ``workers`` >= 1 threads read ahead and one
    writes behind; ``workers=0``, the serial loop, leaves the same bytes, even after an error.  Frames are read
    as ``segmenter`` says (its ``bit_depth`` and ``letterbox``).

    Parameters
    ----------
    segmenter : Segmenter
        The loaded model and engine.
    files : Sequence of Path
        The input image files.
    stems : Sequence of Path
        Their output stems (:func:`plan_outputs`).
    tau : float
        The mask threshold (eq:inference-mask).
    resolution : int
        The working resolution R.
    batch_size : int
        Images per engine call.
    save_prob : bool
        Write the probabilities too.
    overlay : bool
        Write the overlays too.
    on_skip : Callable or None
        ``on_skip(path, reason, error)`` per rejected file (it may raise to stop the run).
    max_pixels : int or None
        Refuse image files above this many pixels, read from their header (None: ``data.max_pixels``).
    workers : int
        Reader threads beside the inference (:data:`IO_WORKERS`); 0: the serial loop.

    Returns
    -------
    SegmentResult
        The masks written, the files skipped, the timings and the frame confidences.

    Raises
    ------
    InputError
        ``workers`` is negative.
    """
    if workers < 0:
        raise InputError(f"workers={workers}: must be >= 0 (0 = the serial loop)")
    bar = progress(total=len(files), desc="segment", unit="img")
    t_start = time.perf_counter()
    skipped: list[tuple[str, str]] = []
    model_s = 0.0
    lock = threading.Lock()

    def done() -> None:
        with lock:
            bar.update(1)

    options = (resolution, max_pixels, overlay, segmenter.bit_depth, segmenter.letterbox)
    ahead = 2 * batch_size  # reads in flight: the next two batches
    jobs = iter(zip(files, stems))
    pending: collections.deque = collections.deque()  # (file, stem, read() -> _load's result)
    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="segment-read") if workers else None
    writer = _Writer(depth=batch_size if workers else 0, done=done)

    def fill() -> None:
        while len(pending) < ahead and (job := next(jobs, None)) is not None:
            # in this context: a reader's warning names options in the caller's terms
            read = (functools.partial(_load, job[0], *options) if pool is None
                    else pool.submit(contextvars.copy_context().run, _load, job[0], *options).result)
            pending.append((*job, read))

    try:
        fill()
        while pending:
            batch = []
            while pending and len(batch) < batch_size:
                f, stem, read = pending.popleft()
                fill()
                try:
                    batch.append((stem, read()))
                except InputError as e:  # skipped with the error's first line, without the leading path
                    writer.flush()  # the serial loop has written everything before this file
                    reason = (str(e).splitlines()[0] if str(e) else type(e).__name__).removeprefix(f"{f}: ")
                    skipped.append((str(f), reason))
                    if on_skip is not None:
                        on_skip(str(f), reason, e)
                    done()
            if not batch:
                continue
            t0 = time.perf_counter()
            probs = segmenter.predict_probs(np.stack([item[0] for _, item in batch]), batch_size=batch_size)
            model_s += time.perf_counter() - t0
            for (stem, (_, shape, img)), p in zip(batch, probs):
                writer.put((stem, p, shape, img, tau, save_prob, overlay, segmenter.letterbox))
        writer.flush()
    except Exception as e:
        try:
            writer.flush()  # what the serial loop had written before the error
        except Exception as first:  # noqa: BLE001 -- a write failed on an earlier file: the serial loop stopped there
            if first is not e:
                raise first from None
        raise
    except BaseException:  # KeyboardInterrupt: stop now
        writer.abort = True
        raise
    finally:
        writer.close()
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
        bar.close()
    return SegmentResult([w for w, _ in writer.written], skipped, model_s, time.perf_counter() - t_start,
                         [c for _, c in writer.written])


def write_confidence_csv(path: str | Path, out_dir: str | Path, written: Sequence[Path],
                         scores: Sequence[float]) -> Path:
    """Write ``confidence.csv``: each written mask (relative to ``out_dir``) and its frame confidence."""
    out = Path(out_dir)
    return write_csv(path, ["mask", "confidence"],
                     [(Path(m).relative_to(out).as_posix(), f"{c:.6f}") for m, c in zip(written, scores)])


def _stderr(line: str) -> None:
    print(line, file=sys.stderr)


def check_options(checkpoint, input_path, output, batch_size: int, resolution: int | None) -> None:
    """Check segment's options before anything is read.

    Parameters
    ----------
    checkpoint : str or Path or None
        ``--checkpoint``: a checkpoint folder or a deploy bundle.
    input_path : str or Path or None
        ``--input``: an image file or a folder.
    output : str or Path or None
        ``--output``: the masks' folder.
    batch_size : int
        ``--batch-size``.
    resolution : int or None
        ``--resolution``, when given.

    Raises
    ------
    InputError
        Naming the first missing or invalid option.
    """
    if not checkpoint:
        raise InputError("{} missing: a checkpoint directory or a deploy bundle (geodistill export)", CHECKPOINT)
    if not input_path:
        raise InputError("--input missing: an image file or a folder of images")
    if not output:
        raise InputError("--output missing: a folder for the masks")
    if batch_size < 1:
        raise InputError(f"--batch-size {batch_size}: must be >= 1")
    if resolution is not None and resolution < MIN_RESOLUTION:
        raise InputError(f"--resolution {resolution}: must be >= {MIN_RESOLUTION}")


def segment_images(checkpoint, input_path, output, *, tau: float | None = None, resolution: int | None = None,
                   thresholds=None, engine: str = AUTO, batch_size: int = 8, save_prob: bool = False,
                   overlay: bool = False, device="auto", params: Mapping | None = None, overwrite: bool = False,
                   skip_bad: bool = PAPER.data.skip_bad, max_pixels: int | None = None,
                   echo: Callable[[str], None] = _stderr, workers: int | None = None,
                   bit_depth: str | int | None = None, quiet: bool = False):
    """Segment one image file or a folder.

    The inputs are found and every output planned before anything is written; tau as
    :func:`pipeline.thresholds.resolve_tau`; the resolution given or recorded, never guessed.

    Parameters
    ----------
    checkpoint : str or Path
        A checkpoint folder or a deploy bundle.
    input_path : str or Path
        An image file or a folder of images.
    output : str or Path
        The folder the masks go to.
    tau : float or None
        A threshold overriding the model's.
    resolution : int or None
        A working resolution overriding the recorded one.
    thresholds : str or Path or None
        A checkpoint's thresholds table (a tau candidate).
    engine : str
        An engine name, or ``auto`` (:func:`pipeline.deploy.segmenter.resolve_engine`).
    batch_size : int
        Images per engine call.
    save_prob : bool
        Write the probabilities too.
    overlay : bool
        Write the overlays too.
    device : str
        Where torch engines run (``auto``: :func:`pipeline.runtime.device.resolve_device`).
    params : Mapping or None
        Params whose ``calibrate.fixed_tau`` is the last tau candidate.
    overwrite : bool
        Replace files no earlier run's record lists.
    skip_bad : bool
        Leave unreadable files out (listed in skipped.csv) instead of stopping; ``data.skip_bad`` unless given.
    max_pixels : int or None
        Refuse image files above this many pixels (None: ``data.max_pixels``).
    echo : Callable
        Where the lines go (stderr).
    workers : int or None
        Reader threads (0: the serial loop, the same bytes); None: :data:`IO_WORKERS`.
    bit_depth : str or int or None
        The bits a 16-bit frame's sensor fills; None: what the bundle records.
    quiet : bool
        Only warnings, errors and the summary line on ``echo``.

    Returns
    -------
    SegmentResult
        :func:`segment_files`' result.

    Raises
    ------
    InputError
        An option is missing or invalid, the input has no image files, an output is refused
        (:func:`plan_outputs`), a bad file without ``skip_bad``, or no file could be read.
    """
    from pipeline.deploy.segmenter import load_segmenter  # torch

    check_options(checkpoint, input_path, output, batch_size, resolution)
    if workers is not None and workers < 0:
        raise InputError(f"workers={workers}: must be >= 0 (0 = the serial loop)")
    found = scan_inputs(input_path)
    if not found.files:
        extra = f"; skipped {found.skipped[0][0]}: {found.skipped[0][1]}" if found.skipped else ""
        raise InputError(f"--input {input_path}: no image files (png, jpg, jpeg, tif, tiff, bmp){extra}")
    files = found.files
    suffixes = output_suffixes(save_prob, overlay)
    stems = plan_outputs(found.root, files, output, found.is_dir, suffixes=suffixes, overwrite=overwrite)
    policy = BadInputPolicy(skip_bad, hint="pass --skip-bad to leave it out")
    root = found.root if found.is_dir else None

    def image_id(path) -> str:
        """Name the file as label does: its path relative to the input folder, without the suffix."""
        p = Path(path)
        try:
            return (p.relative_to(root) if root is not None else Path(p.name)).with_suffix("").as_posix()
        except ValueError:
            return p.stem

    max_pixels = pixel_limit(max_pixels)
    for path, reason in found.skipped:  # links and special files: before anything is written
        policy.report(image_id(path), path, reason)
    for path, reason in found.unused:  # not images (hidden files, other types): listed, not an error
        policy.record(image_id(path), path, reason)

    seg = load_segmenter(checkpoint, engine, resolve_device(device), thresholds, params=params)
    if bit_depth is not None:
        seg.bit_depth = check_bit_depth(bit_depth)
    reset_frame_warnings()  # once per run
    tau, source = seg.resolve_tau(option=tau)
    resolution, res_source = model_resolution(seg.resolution, resolution, checkpoint, echo)

    def report(path, reason, error):  # raises without --skip-bad, naming the option in the caller's terms
        if isinstance(error, BadFileError):
            policy.report_error(image_id(path), error)
        else:
            policy.report(image_id(path), path, reason)

    info = (lambda line: None) if quiet else echo
    info(f"segment: engine {seg.engine}" + (" (auto)" if engine == AUTO else "")
         + f", {len(files)} image(s), {resolution}px ({res_source}), tau={tau:.4g} ({source})")
    claim_outputs(output, relative_outputs(output, stems, suffixes), RECORD, "segment",
                  {"input": str(Path(input_path).absolute()), "checkpoint": str(Path(checkpoint).absolute())})
    result = segment_files(seg, files, stems, tau=tau, resolution=resolution, batch_size=batch_size,
                             save_prob=save_prob, overlay=overlay, on_skip=report, max_pixels=max_pixels,
                             **({} if workers is None else {"workers": workers}))
    listing = Path(output) / SKIPPED_CSV
    write_skipped_csv(listing, policy.rows())
    write_confidence_csv(Path(output) / CONFIDENCE_CSV, Path(output).absolute().resolve(), result.written,
                           result.scores)
    lowest = (f" (lowest {min(result.scores):.3f}: {result.written[result.scores.index(min(result.scores))].name})"
              if result.scores else "")
    echo(f"segment: wrote {len(result.written)} mask(s) to {output}; per-frame confidence in "
         f"{CONFIDENCE_CSV}{lowest}")
    if (line := policy.summary("segment", listing)) is not None:
        echo(line)
    if not result.written:
        raise InputError(f"--input {input_path}: none of the {len(files)} file(s) could be read")
    n = len(result.written)
    info(f"segment: timing: engine {seg.engine}, {1e3 * result.model_seconds / n:.2f} ms/image in the model, "
         f"{1e3 * result.total_seconds / n:.2f} ms/image end to end ({n} images, batch {batch_size}, "
         f"{resolution}px)")
    return result


def model_resolution(trained: int | None, option: int | None, checkpoint,
                     echo: Callable[[str], None] = _stderr) -> tuple[int, str]:
    """Pick the working resolution: ``option`` (with a warning when it differs) over the recorded one.

    Parameters
    ----------
    trained : int or None
        The resolution recorded with the model.
    option : int or None
        ``--resolution``, when given.
    checkpoint : str or Path
        The checkpoint or bundle (named in messages).
    echo : Callable
        Where the warning goes.

    Returns
    -------
    tuple
        ``(resolution, source)``: the value and where it came from (:data:`pipeline.thresholds.RESOLUTION_LABELS`).
    """
    from pipeline.deploy.bundle import DEPLOY_JSON, is_deploy_bundle  # torch

    recorded_in = f"{Path(checkpoint) / DEPLOY_JSON}" if is_deploy_bundle(checkpoint) else f"checkpoint {checkpoint}"
    if trained is not None:  # a recorded resolution is checked even when --resolution overrides it
        resolve_resolution(recorded=(trained, recorded_in))
    resolution, res_source = resolve_resolution(
        option=option, recorded=(trained, recorded_in),
        missing=f"--checkpoint {checkpoint}: records no training resolution; pass --resolution N "
                "(the image size the model was trained at)")
    if res_source == RESOLUTION_LABELS["option"] and trained is not None and resolution != trained:
        echo(f"segment: warning: --resolution {resolution} differs from the {trained}px the model was "
             f"trained at ({recorded_in})")
    return resolution, res_source
