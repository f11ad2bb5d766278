"""``geodistill label``: a folder of images -> voted, gated pseudo-masks in standard formats.

The DAG's teacher, consensus and geometry steps, composed of the functions those stages call, on a
plain folder and without a DVC project:

1. every image (recursively, any size, grey / RGB / RGBA, 8/16-bit: :func:`pipeline.datasets.loading.
   load_rgb`) is resized to the working resolution ``data.resolution`` and sent to the teacher
   (``teacher.*``: SAM 3, imported masks, or the SIMULATOR) through the teacher stage's runner and
   content-addressed cache (:func:`pipeline.teachers.runner.open_runner`; serial, or with ``workers`` a
   Ray Data pool) -- a rerun, or a run killed half-way, recomputes nothing that is cached;
2. the K prompt masks are voted (:func:`pipeline.consensus.vote`, the consensus stage's vote:
   eq:agreement-map, eq:majority-vote);
3. the reliability gate of each pseudo-mask (the geometry stage's :func:`pipeline.geometry.image_gates`
   with eq:foreground-agreement and eq:pseudo-area), with a0 the median area of the non-empty
   pseudo-masks of the folder (every image is a training image here).

Outputs under ``out`` (formats ``png``, ``coco``, ``yolo``; the table, contact sheet and run record
always)::

    masks/<relative path without suffix>.png  voted pseudo-mask, 0/255, at the ORIGINAL image size
    coco.json                                 COCO instances, one RLE annotation per non-empty mask
    yolo/labels/<relative stem>.txt           YOLO segmentation lines per image
    yolo/images/<relative path>               a RELATIVE symbolic link to the input (a copy with --copy-images)
    yolo/data.yaml, yolo/train.txt, yolo/val.txt, yolo/README.txt
                                              the Ultralytics dataset: image lists relative to the folder, a
                                              seeded validation share (formats.yolo_split; no val.txt below
                                              2 images, the reason in README.txt)
    labels.parquet, labels.csv                one row per image: c, v, a, a0, g_conf, g_valid, g_area, g, and h
                                              (prompt disagreement: pipeline.consensus.agreement_entropy)
    contact_sheet.png                         sampled images with their pseudo-mask contours and g
    label.json                                backend (and whether it is a SIMULATOR), counts, params
    skipped.csv                               files left out by --skip-bad (columns image_id, path, reason)

Decisions: the vote happens at the working resolution (the pseudo-mask is exactly the DAG's training
target for the same image and params) and the voted mask is brought to the original size by
nearest-neighbour resizing; ``--set data.resolution=...`` gives finer masks for large images.
Relative cache folders (``teacher.cache_dir``, ``data.cache_dir``) are taken inside ``out``, so a
rerun into the same folder resumes; label.json records the teacher cache as an absolute path, and
``distill --labels OUT`` reads it after checking OUT against label.json's checksums
(:func:`check_label_folder`), so distill computes no answer again (the cache key is the image bytes'
sha256, the teacher's fingerprint, the prompt and the view -- the same keys the DAG's teacher stage uses).  Two inputs whose relative paths differ only in the suffix or
letter case would share a label file name (YOLO needs ``<image stem>.txt``): refused before anything
is computed.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
from contextlib import nullcontext
from pathlib import Path
from typing import Mapping, Sequence

import shutil

import numpy as np
import pandas as pd

from pipeline.artifacts import atomic_path, folders_gone_on_failure, write_json
from pipeline.consensus import vote
from pipeline.datasets.contact_sheet import contact_sheet, sample_for_sheet, tile
from pipeline.datasets.loading import (SUPPORTED_SUFFIXES, BadFileError, DecodeCache, load_mask, load_rgb,
                                       reset_frame_warnings)
from pipeline.datasets.manifest import BadInputPolicy
from pipeline.datasets.scan import scan_inputs
from pipeline.deploy.files import write_png, write_skipped_csv
from pipeline.errors import (BACKEND, CHECKPOINT, FORMAT, INPUT, LABELS, OUT, OVERWRITE, REFERENCE_MASKS, InputError,
                             caller, literal)
from pipeline.geometry import NoForeground, area_ratio, foreground_agreement, image_gates, median_area
from pipeline.labeling.formats import (coco_annotation, coco_document, yolo_data_yaml, yolo_image_list,
                                       yolo_lines, yolo_readme, yolo_split)
from pipeline.ownership import OUTPUTS as RECORD_OUTPUTS
from pipeline.ownership import (WRITTEN_BY, check_outputs, claim_outputs, owned_outputs, read_record,
                                remove_stale, signature)
from pipeline.params import section
from pipeline.progress import progress
from pipeline.consensus import agreement_entropy
from pipeline.teachers import check_teacher_params
from pipeline.teachers.base import TeacherInput
from pipeline.teachers.jobs import in_view
from pipeline.teachers.runner import open_runner

log = logging.getLogger(__name__)

FORMATS = ("png", "coco", "yolo")
#: the files and folders written under ``out`` (module docstring), named once
OUTPUTS = {"masks": "masks", "coco": "coco.json", "yolo": "yolo", "table": "labels.parquet", "csv": "labels.csv",
           "sheet": "contact_sheet.png", "record": "label.json", "skipped": "skipped.csv"}
#: yolo/'s image lists: training, then validation (pipeline.labeling.formats.yolo_split)
YOLO_LISTS = ("train.txt", "val.txt")
#: the outputs written whatever the formats (label.json lists them and the files of each format,
#: :func:`label_targets`; pipeline.ownership); the caches under .cache/ only add files
ALWAYS = tuple(OUTPUTS[k] for k in ("table", "csv", "sheet", "skipped"))
SIMULATOR_NOTE = ("teacher.backend=simulated is a SIMULATOR of foundation-model errors that reads the "
                  "reference masks given with --reference-masks; these are not a real teacher's labels")


@dataclasses.dataclass(repr=False)
class LabelResult:
    """What :func:`label_folder` (``pipeline.label``) wrote: the output folder ``out``, the per-image
    ``table`` (image_id, c, v, a, g, ...), the ``skipped`` files (path, reason), the ``formats`` written,
    the teacher ``backend``; :attr:`masks` maps each image id to its mask PNG.  Its repr is one line."""

    out: Path
    table: pd.DataFrame
    skipped: list[tuple[str, str]]
    formats: tuple[str, ...]
    backend: str
    skipped_line: str | None = None  # the bad-file summary line (BadInputPolicy.summary; None: no bad file)

    @property
    def simulator(self) -> bool:
        return self.backend == "simulated"

    @property
    def masks(self) -> dict[str, Path]:
        """image id -> its voted mask ``out/masks/<image id>.png`` (at the image's own size); empty when
        ``png`` was not among the formats."""
        if "png" not in self.formats:
            return {}
        return {str(i): Path(self.out) / OUTPUTS["masks"] / f"{i}.png" for i in self.table["image_id"]}

    def __repr__(self) -> str:
        return (f"LabelResult(out={str(self.out)!r}, images={len(self.table)}, formats={list(self.formats)}, "
                f"skipped={len(self.skipped)}, backend={self.backend!r})")


def parse_formats(formats: str | Sequence[str]) -> tuple[str, ...]:
    """``"png,coco"`` or ``["png", "coco"]`` -> ("png", "coco") in the canonical order; InputError on an
    unknown or empty list (naming ``--format`` / ``formats=``)."""
    items = [f.strip().lower() for f in (formats.split(",") if isinstance(formats, str) else formats)]
    items = [f for f in items if f]
    bad = [f for f in items if f not in FORMATS]
    if bad or not items:
        raise InputError(f"{{}}: expected a comma-separated subset of {','.join(FORMATS)}",
                         FORMAT(','.join(items) or repr(formats)))
    return tuple(f for f in FORMATS if f in items)


def find_images(input_dir: str | Path):
    """The :class:`pipeline.datasets.scan.Inputs` of ``input_dir`` (images sorted, bad entries, files
    that are not images), recursively (:func:`pipeline.datasets.scan.scan_inputs`, the one scan of
    label, distill and segment); InputError when it is not a folder or has no image."""
    root = Path(input_dir)
    if not root.is_dir():
        raise InputError(f"{root}: input folder not found" if not root.exists() else
                         f"{root}: not a folder (label and distill take a folder of images)")
    found = scan_inputs(root)
    if not found.files:
        raise InputError(f"{root}: no images ({', '.join(s.lstrip('.') for s in SUPPORTED_SUFFIXES)}) in this folder")
    return found


def _id_of(root: Path, path: str | Path) -> str:
    """The label name of ``path`` (relative to ``root`` without the suffix), or its stem outside ``root``."""
    try:
        return Path(path).relative_to(root).with_suffix("").as_posix()
    except ValueError:
        return Path(path).stem


def image_ids(root: Path, files: Sequence[Path]) -> list[str]:
    """Each file's path relative to ``root`` without its suffix (posix): the label files' names.
    InputError when two inputs would get the same name (ignoring letter case)."""
    ids = [f.relative_to(root).with_suffix("").as_posix() for f in files]
    seen: dict[str, Path] = {}
    for iid, f in zip(ids, files):
        other = seen.setdefault(iid.lower(), f)
        if other is not f:
            raise InputError(f"{f}: same label name {iid!r} as {other} (label files are named by the image "
                             f"path without its suffix; rename one of them)")
    return ids


def find_reference_masks(mask_dir: str | Path, ids: Sequence[str]) -> list[Path]:
    """The reference mask of every image id in ``mask_dir`` (``<id>.<png|jpg|tif|bmp>``); InputError
    naming the first image without one (the simulated teacher needs all of them)."""
    d = Path(mask_dir)
    if not d.is_dir():
        raise InputError("{}: folder not found", REFERENCE_MASKS(d))
    out = []
    for iid in ids:
        hits = [d / f"{iid}{s}" for s in SUPPORTED_SUFFIXES if (d / f"{iid}{s}").is_file()]
        if not hits:
            raise InputError(f"{{}}: no mask for image {literal(repr(iid))} (expected {literal(iid)}.png)",
                             REFERENCE_MASKS(d))
        out.append(hits[0])
    return out


def _inside(path: str | None, out: Path) -> str | None:
    """A relative cache folder is taken inside the output folder (so a rerun there resumes)."""
    if path is None:
        return None
    return str(path) if Path(path).is_absolute() else str(out / path)


def _write_table(out: Path, table: pd.DataFrame) -> None:
    with atomic_path(out / OUTPUTS["table"]) as tmp:
        table.to_parquet(tmp, index=False)
    with atomic_path(out / OUTPUTS["csv"]) as tmp:
        table.to_csv(tmp, index=False, float_format="%.6g")


def label_targets(root: Path, files: Sequence[Path], ids: Sequence[str], fmts: Sequence[str]) -> list[str]:
    """The files a run writes under ``out`` for ``files`` (ids ``ids``) in formats ``fmts``, relative
    (posix), the record left out: what label.json lists (module docstring)."""
    out = list(ALWAYS)
    if "png" in fmts:
        out += [f"{OUTPUTS['masks']}/{i}.png" for i in ids]
    if "coco" in fmts:
        out.append(OUTPUTS["coco"])
    if "yolo" in fmts:
        out += [f"{OUTPUTS['yolo']}/labels/{i}.txt" for i in ids]
        out += [f"{OUTPUTS['yolo']}/images/{f.relative_to(root).as_posix()}" for f in files]
        lists = YOLO_LISTS if len(ids) >= 2 else YOLO_LISTS[:1]  # no val.txt below 2 images (yolo_split)
        out += [f"{OUTPUTS['yolo']}/{name}" for name in ("data.yaml", *lists, "README.txt")]
    return out


def file_checksums(out: Path, rels: Sequence[str]) -> dict[str, str]:
    """sha256 of each regular file of ``rels`` under ``out`` (links to the inputs left out): label.json
    records them, so a reader (``distill --labels``) can tell an unmodified label folder."""
    sums = {}
    for rel in rels:
        p = out / rel
        if p.is_file() and not p.is_symlink():
            sums[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
    return sums


def labels_of_gone_images(out: Path, root: Path, files: Sequence[Path], ids: Sequence[str]) -> list[str]:
    """The per-image files (masks, YOLO labels and images) an earlier label run in ``out`` wrote for
    images that are not among ``files`` now: what a rerun would remove (relative, sorted)."""
    per_image = (f"{OUTPUTS['masks']}/", f"{OUTPUTS['yolo']}/labels/", f"{OUTPUTS['yolo']}/images/")
    previous = owned_outputs(out, OUTPUTS["record"], "label")
    now = set(label_targets(root, files, ids, FORMATS))
    return sorted(p for p in previous - now if p.startswith(per_image)
                  and ((out / p).is_symlink() or (out / p).is_file()))


def check_label_folder(label_dir: str | Path, input_dir: str | Path) -> dict:
    """The record (label.json) of an UNMODIFIED, complete ``label`` output folder of the images in
    ``input_dir``, for ``distill --labels`` / ``distill(labels=...)``; InputError, one line naming the
    option, when it is not one: no label.json of label's, a run that did not finish, other images (a
    labelled image gone, an image added since, neither labelled nor listed in skipped.csv), the
    SIMULATOR's labels, or a file label wrote (masks, tables, COCO, YOLO) missing or changed since --
    its sha256 differs from the one label.json records.  Corrected masks enter only through review
    import, where they are marked as corrections, never by editing a label folder."""
    d, root = Path(label_dir), Path(input_dir).resolve()
    record = read_record(d / OUTPUTS["record"], "label")
    if record is None:
        raise InputError(f"{{}}: {'folder not found' if not d.is_dir() else 'not an output folder of label'} "
                         f"(no {literal(OUTPUTS['record'])} of label there)", LABELS(d))
    if record.get("complete") is not True:
        raise InputError("{}: that label run did not finish; rerun label into it (it resumes from its cache)",
                         LABELS(d))
    if Path(str(record.get("input"))) != root:
        raise InputError(f"{{}}: these are the labels of {literal(record.get('input'))}, not of {{}}", LABELS(d),
                         INPUT(input_dir))
    if record.get("simulator"):
        raise InputError("{}: labelled by the SIMULATOR (it reads reference masks), which distill cannot train "
                         "from; label with a real teacher", LABELS(d))
    sums = record.get("checksums")
    if not isinstance(sums, dict) or not isinstance(record.get("teacher"), dict):
        raise InputError("{}: its label.json records no checksums (an older label); rerun label into it",
                         LABELS(d))
    for rel, digest in sorted(sums.items()):
        p = d / rel
        if not p.is_file():
            raise InputError(f"{{}}: {literal(rel)} is missing, the folder is incomplete; rerun label into it",
                             LABELS(d))
        if hashlib.sha256(p.read_bytes()).hexdigest() != digest:
            raise InputError(f"{{}}: {literal(rel)} changed after label wrote it; distill trains only on an "
                             "unmodified label folder -- corrected masks enter only through `geodistill review "
                             "import`, where they are marked as corrections", LABELS(d))
    labelled = set(pd.read_parquet(d / OUTPUTS["table"], columns=["image_id"])["image_id"].astype(str))
    skipped = set(pd.read_csv(d / OUTPUTS["skipped"], dtype=str, keep_default_na=False)["image_id"])
    found = find_images(root)
    now = set(image_ids(found.root, found.files))
    for what, ids in (("was labelled but is gone from", labelled - now), ("was added to", now - labelled - skipped)):
        if ids:
            raise InputError(f"{{}}: image {literal(repr(sorted(ids)[0]))} {what} {{}} since label ran "
                             f"({len(ids)} such); rerun label", LABELS(d), INPUT(input_dir))
    return record


def _link_or_copy(src: Path, dst: Path, copy: bool = False) -> None:
    """yolo/images/<rel>: a RELATIVE symbolic link to the input (it survives moving the input and output
    folders together), or with ``copy`` -- or where links are not allowed -- a copy (it goes anywhere).
    An earlier run's link or copy there (label.json lists it) is replaced, never written through."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    if dst.is_symlink() or dst.is_file():
        dst.unlink()
    if not copy:
        try:  # real paths on both sides: a link inside a linked folder still points at the file
            os.symlink(os.path.relpath(os.path.realpath(src), os.path.realpath(dst.parent)), dst)
            return
        except OSError:
            pass
    with atomic_path(dst) as tmp:
        shutil.copy2(src, tmp)


def _write_yolo_dataset(yolo_dir: Path, rels: Sequence[str], ids: Sequence[str], seed: int, copies: bool) -> None:
    """data.yaml, train.txt, val.txt (when there is a split) and README.txt of ``yolo/``
    (:mod:`pipeline.labeling.formats`: the seeded split and the texts)."""
    train, val = yolo_split(ids, seed)
    copies = copies or not (yolo_dir / "images" / rels[0]).is_symlink()  # links refused by the file system
    for name, rows in zip(YOLO_LISTS, (train, val)):
        if rows:
            with atomic_path(yolo_dir / name) as tmp:
                tmp.write_text(yolo_image_list([rels[i] for i in rows]))
    for name, text in (("data.yaml", yolo_data_yaml(len(train), len(val), seed)),
                       ("README.txt", yolo_readme(len(train), len(val), seed, copies))):
        with atomic_path(yolo_dir / name) as tmp:
            tmp.write_text(text)


def folder_gates(c: np.ndarray, n_valid: np.ndarray, a: np.ndarray, geo: Mapping):
    """(v, a0, :class:`pipeline.geometry.GateFactors`) of a labelled folder: every image is a training
    image, so a0 = the median area of its non-empty pseudo-masks (:func:`pipeline.geometry.median_area`);
    without any, a0 = 0 (every c is 0 then, so every g is 0 whatever a0 is) and label warns with the
    words distill fails with on the same images (:class:`pipeline.geometry.NoForeground`, spelled for
    the caller).  ``geo``: params ``geometry`` (eq:valid-prompt-ratio .. eq:reliability-gate constants)."""
    a = np.asarray(a, np.float64)
    try:
        a0 = median_area(a, np.ones(a.shape, bool))
    except NoForeground as e:
        log.warning("label: %s (every gate g is 0)", e.render(caller()))
        a0 = 0.0
    v, gf = image_gates(c, n_valid, a, a0, geo)
    return v, a0, gf


@dataclasses.dataclass
class _Job:
    """One ``label`` run, checked before anything is written (:func:`_plan`)."""

    root: Path
    out: Path
    files: list
    ids: list
    policy: object          # pipeline.datasets.manifest.BadInputPolicy
    data_cfg: dict
    geo: dict
    tcfg: dict
    size: int
    simulated: bool
    ref_files: list | None
    cache: object           # pipeline.datasets.loading.DecodeCache | None
    shas: list = dataclasses.field(default_factory=list)
    sizes: list = dataclasses.field(default_factory=list)


def _plan(input_dir, out, params: Mapping, reference_masks, overwrite: bool, fmts: Sequence[str] = FORMATS) -> _Job:
    """Scan the folder, apply the bad-file policy to links and non-images, refuse outputs the user owns
    and check the teacher and reference-mask options -- all before anything is written."""
    found = find_images(input_dir)
    root, files = found.root, found.files
    out = Path(out)
    if out.resolve() == root.resolve() or root.resolve() in out.resolve().parents:
        raise InputError("{}: must not be the input folder or inside it", OUT(out))
    ids = image_ids(root, files)
    policy = BadInputPolicy(section(params, "data")["skip_bad"])
    for path, reason in found.skipped:  # links leaving the folder, broken links: before anything is written
        policy.report(_id_of(root, path), path, reason)
    for path, reason in found.unused:  # not images (hidden files, other types): listed, not an error
        policy.record(_id_of(root, path), path, reason)
    check_outputs(out, label_targets(root, files, ids, fmts), OUTPUTS["record"], "label", overwrite=overwrite)
    gone = labels_of_gone_images(out, root, files, ids)
    if gone and not overwrite:  # adding images is fine; losing the labels of images no longer here is not
        raise InputError(f"{{}}: holds the labels of {len(gone)} image(s) no longer in {literal(root)} (first: "
                         f"{literal(gone[0])}), which this run would remove; pass {{}} to remove them, or choose "
                         "another {}", OUT(out), OVERWRITE, OUT)
    data_cfg, geo = section(params, "data"), section(params, "geometry")
    tcfg = section(params, "teacher")
    tcfg["cache_dir"] = _inside(tcfg["cache_dir"], out.resolve())  # absolute: label.json names it to distill
    tcfg = check_teacher_params(tcfg)
    simulated = tcfg["backend"] == "simulated"
    if simulated and reference_masks is None:
        raise InputError("{} is a SIMULATOR that reads reference masks: pass {} (masks named like the images); "
                         "use {} for real labels", BACKEND("simulated"), REFERENCE_MASKS("DIR"),
                         CHECKPOINT("SAM3_DIR"))
    if not simulated and reference_masks is not None:
        raise InputError(f"{{}}: only the simulated teacher reads masks; teacher.backend="
                         f"{literal(tcfg['backend'])} never does", REFERENCE_MASKS)
    ref_files = find_reference_masks(reference_masks, ids) if simulated else None
    cache = DecodeCache(_inside(data_cfg["cache_dir"], out)) if data_cfg["cache_dir"] else None
    return _Job(root, out, list(files), list(ids), policy, data_cfg, geo, tcfg, int(data_cfg["resolution"]),
                simulated, ref_files, cache)


def _read_images(job: _Job) -> None:
    """Pass 1: read every file once (sha256 for the teacher cache, native size); bad files -- and files
    above ``data.max_pixels``, refused on their header before decoding -- go to the policy and leave
    ``job``'s lists."""
    keep = []
    limit = job.data_cfg["max_pixels"]
    for i, f in enumerate(progress(job.files, desc="label: reading", unit="img")):
        try:
            loaded = load_rgb(f, job.size, job.cache, max_pixels=limit, bit_depth=job.data_cfg.get("bit_depth", "auto"))
            if job.ref_files is not None:
                ref = load_mask(job.ref_files[i], job.size, job.cache, max_pixels=limit)
                if ref.native_hw != loaded.native_hw:
                    raise InputError(f"{job.ref_files[i]}: mask size {ref.native_hw[1]}x{ref.native_hw[0]} differs "
                                     f"from image {f} size {loaded.native_hw[1]}x{loaded.native_hw[0]}")
        except BadFileError as e:
            job.policy.report_error(job.ids[i] if e.path == str(f) else Path(e.path).stem, e)
            continue
        keep.append(i)
        job.shas.append(loaded.sha256)
        job.sizes.append(loaded.native_hw)
    if not keep:
        first = job.policy.skipped[-1]
        raise InputError(f"{job.root}: none of the {len(job.files)} images could be read (first: {first['path']}: "
                         f"{first['reason']})")
    job.files = [job.files[i] for i in keep]
    job.ids = [job.ids[i] for i in keep]
    job.ref_files = [job.ref_files[i] for i in keep] if job.ref_files is not None else None


class FolderInputs:
    """``(row, view) -> TeacherInput`` of a labelled folder's image files, decoded and resized to the
    working resolution (:func:`pipeline.datasets.loading.load_rgb`, through the decode cache); for the
    SIMULATOR also the reference masks.  Picklable: Ray's CPU workers decode with it."""

    def __init__(self, job: _Job):
        absolute = lambda paths: None if paths is None else [Path(os.path.abspath(p)) for p in paths]  # noqa: E731
        # absolute paths: Ray workers need not share this process's working directory
        self.files, self.ref_files = absolute(job.files), absolute(job.ref_files)
        self.ids, self.shas, self.size = job.ids, job.shas, job.size
        self.max_pixels = job.data_cfg["max_pixels"]
        self.bit_depth = job.data_cfg.get("bit_depth", "auto")
        self.cache = DecodeCache(os.path.abspath(job.cache.root)) if job.cache is not None else None

    def __call__(self, row: int, view: str) -> TeacherInput:
        image = load_rgb(self.files[row], self.size, self.cache, max_pixels=self.max_pixels,
                         bit_depth=self.bit_depth).array
        reference = None
        if self.ref_files is not None:
            mask = load_mask(self.ref_files[row], self.size, self.cache, max_pixels=self.max_pixels).array.astype(bool)
            reference = {"mask": in_view(mask, view)}
        return TeacherInput(image_id=self.ids[row], image_sha256=self.shas[row], image=in_view(image, view),
                            view=view, reference=reference)


def _run_teacher(job: _Job, device: str, workers: int = 0, address: str | None = None):
    """The prompts on every image through the teacher stage's runner and cache (serial, or a Ray Data
    pool of ``workers`` teachers); (runner, fingerprint, stats)."""
    runner, t_fp = open_runner(job.tcfg, (job.size, job.size), device, FolderInputs(job), job.shas)
    if job.simulated:
        log.warning("label: %s", SIMULATOR_NOTE)
    stats = runner.fill(range(len(job.files)), workers=workers, address=address)
    log.info("label: teacher computed %d answers on %d images; %d cached answers reused",
             stats.answers_computed, stats.images_computed, stats.cache_hits)
    return runner, t_fp, stats


@dataclasses.dataclass
class _Votes:
    """Per-image results of pass 2 (:func:`_vote_and_export`)."""

    c: np.ndarray
    a: np.ndarray
    n_valid: np.ndarray
    pixels: np.ndarray
    annotations: list
    sheet: dict
    h: np.ndarray  # prompt disagreement (pipeline.consensus.agreement_entropy: mean entropy of A over the union)


def _vote_and_export(job: _Job, runner, fmts: tuple[str, ...], vote_threshold: float,
                     copy_images: bool = False) -> _Votes:
    """Pass 2: vote (eq:majority-vote), write the PNG and YOLO outputs at each image's own size (YOLO's
    images as relative links, or copies with ``copy_images``), collect the gate inputs
    (eq:foreground-agreement, eq:pseudo-area) and the COCO annotations."""
    import cv2  # opencv: heavy, imported where used

    n, out = len(job.files), job.out
    rng = np.random.default_rng(int(job.data_cfg["seed"]))
    sheet_rows = set(sample_for_sheet(pd.DataFrame({"split": ["train"] * n, "group": ["label"] * n}),
                                      int(job.data_cfg["contact_sheet_images"]), int(rng.integers(2**31))).tolist())
    v = _Votes(np.zeros(n), np.zeros(n), np.zeros(n, np.int64), np.zeros(n, np.int64), [], {}, np.zeros(n))
    # file by file, never a folder swapped in whole: what label did not write there stays (pipeline.ownership)
    with nullcontext(out / OUTPUTS["masks"]) as masks_dir, nullcontext(out / OUTPUTS["yolo"]) as yolo_dir:
        for row in progress(range(n), desc="label: vote + export", unit="img"):
            masks, scores, _, _ = runner.answers(row)
            cons = vote(masks, scores, vote_threshold)
            v.c[row] = foreground_agreement(cons.agreement, cons.voted)
            v.a[row] = area_ratio(cons.voted)
            v.n_valid[row] = cons.n_valid
            v.h[row] = agreement_entropy(cons.agreement)
            h, w = job.sizes[row]
            full = cv2.resize(cons.voted.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
            v.pixels[row] = int(np.count_nonzero(full))
            if "png" in fmts:
                write_png(masks_dir / f"{job.ids[row]}.png", full.astype(np.uint8) * 255)
            if "coco" in fmts:
                v.annotations.append(coco_annotation(full, row + 1, row + 1))
            if "yolo" in fmts:
                with atomic_path(yolo_dir / "labels" / f"{job.ids[row]}.txt") as dst:
                    dst.write_text("".join(line + "\n" for line in yolo_lines(full)))
                _link_or_copy(job.files[row], yolo_dir / "images" / job.files[row].relative_to(job.root),
                              copy_images)
            if row in sheet_rows:
                v.sheet[row] = (load_rgb(job.files[row], job.size, job.cache, max_pixels=job.data_cfg["max_pixels"],
                                         bit_depth=job.data_cfg.get("bit_depth", "auto")).array, cons.voted)
        if "yolo" in fmts:
            _write_yolo_dataset(yolo_dir, [f.relative_to(job.root).as_posix() for f in job.files], job.ids,
                                int(job.data_cfg["seed"]), copy_images)
    return v


def _write_coco(job: _Job, table: pd.DataFrame, v: _Votes, g: np.ndarray) -> None:
    """``coco.json``: one image and (where the vote is non-empty) one instance with its RLE per image."""
    images = [{"id": i + 1, "file_name": table["file"].iloc[i], "width": int(job.sizes[i][1]),
               "height": int(job.sizes[i][0])} for i in range(len(job.files))]
    for i, ann in enumerate(v.annotations):
        if ann is not None:
            ann.update(gate=round(float(g[i]), 6), agreement=round(float(v.c[i]), 6))
    desc = "geodistill label: voted multi-prompt pseudo-masks" + (f" -- {SIMULATOR_NOTE}" if job.simulated else "")
    doc = coco_document(images, [x for x in v.annotations if x is not None], description=desc,
                        teacher_backend=job.tcfg["backend"], simulator=job.simulated)
    with atomic_path(job.out / OUTPUTS["coco"]) as tmp:
        tmp.write_text(json.dumps(doc, separators=(",", ":")))


def label_folder(input_dir: str | Path, out: str | Path, params: Mapping, *, device: str = "auto",
                 formats: str | Sequence[str] = FORMATS, reference_masks: str | Path | None = None,
                 overwrite: bool = False, workers: int = 0, address: str | None = None,
                 copy_images: bool = False) -> LabelResult:
    """Label every image under ``input_dir`` into ``out`` (module docstring); ``params`` are validated
    params (schema defaults or a params file): data.resolution / cache_dir / contact_sheet_images /
    seed, teacher.*, consensus.vote_threshold, geometry.*.  ``reference_masks``: the folder of masks the
    simulated teacher (a SIMULATOR) reads; refused for real teachers (they never see masks).
    ``workers`` / ``address``: the teacher's Ray Data executor, as the teacher stage's ``--workers``
    (0: the serial loop; same answers either way).  ``copy_images``: ``yolo/images`` holds copies of the
    inputs instead of relative links (``--copy-images``).

    Ownership (:mod:`pipeline.ownership`): ``label.json`` lists the files written; a user's file where
    one goes (``coco.json``, ``masks/a.png``) is refused before anything is written, ``overwrite`` or
    not; a user's folder (``masks/``) is refused unless ``overwrite``, and the files in it stay; label's
    own files of an earlier run that this run does not write are removed.  Steps: :func:`_plan` (checks), :func:`_read_images`,
    :func:`_run_teacher`, :func:`_vote_and_export`, then the gates (eq:reliability-gate), the tables, COCO,
    the contact sheet, skipped.csv and the record."""
    fmts = parse_formats(formats)
    job = _plan(input_dir, out, params, reference_masks, overwrite, fmts)
    reset_frame_warnings()  # each run says once how it reads 16-bit frames
    made = [job.out, job.out / ".cache"] + ([job.cache.root] if job.cache is not None else [])
    with folders_gone_on_failure(*made):  # a bad image stops the run before any output: no folder of it stays
        _read_images(job)
    out, policy, tcfg, n = job.out, job.policy, job.tcfg, len(job.files)
    previous = owned_outputs(out, OUTPUTS["record"], "label")
    current = label_targets(job.root, job.files, job.ids, fmts)
    claim_outputs(out, current, OUTPUTS["record"], "label", {"input": str(job.root.resolve()), "complete": False})
    runner, t_fp, stats = _run_teacher(job, device, workers, address)
    vote_threshold = float(section(params, "consensus")["vote_threshold"])
    v = _vote_and_export(job, runner, fmts, vote_threshold, copy_images)

    valid, a0, gf = folder_gates(v.c, v.n_valid, v.a, job.geo)
    table = pd.DataFrame({
        "image_id": job.ids, "file": [f.relative_to(job.root).as_posix() for f in job.files],
        "width": [s[1] for s in job.sizes], "height": [s[0] for s in job.sizes],
        "n_valid": v.n_valid.astype(np.int16), "c": v.c, "v": valid, "a": v.a, "a0": np.full(n, a0),
        "g_conf": gf.conf, "g_valid": gf.valid, "g_area": gf.area, "g": gf.g, "h": v.h, "mask_pixels": v.pixels})
    table["teacher_backend"] = tcfg["backend"]
    table["simulator"] = job.simulated
    _write_table(out, table)
    if "coco" in fmts:
        _write_coco(job, table, v, gf.g)

    tsize = max(job.size, 192)
    tiles = [tile(img, voted, f"{job.ids[r]} g={gf.g[r]:.2f}", tsize)
             for r, (img, voted) in sorted(v.sheet.items())]
    write_png(out / OUTPUTS["sheet"], contact_sheet(tiles, columns=4))

    write_skipped_csv(out / OUTPUTS["skipped"], policy.rows())  # header only when nothing was skipped
    # label's own files of another run (formats not asked for now, images no longer there) go
    removed = remove_stale(out, previous - {OUTPUTS["record"]}, current)
    if removed:
        log.info("label: removed %d file(s) an earlier label run wrote that this run does not (first: %s)",
                 len(removed), removed[0])
    write_json(out / OUTPUTS["record"], {
        "input": str(job.root.resolve()), "images": n, "skipped": policy.bad_count(), "formats": list(fmts),
        "teacher_backend": tcfg["backend"], "simulator": job.simulated,
        "note": SIMULATOR_NOTE if job.simulated else None, "teacher_fingerprint": t_fp,
        "prompts": list(tcfg["prompts"]), "resolution": job.size, "vote_threshold": vote_threshold, "a0": a0,
        "geometry": job.geo, "teacher_answers_computed": stats.answers_computed,
        "teacher_cache_hits": stats.cache_hits, "complete": True, "teacher": tcfg,
        "checksums": file_checksums(out, current),
        WRITTEN_BY: signature("label"), RECORD_OUTPUTS: sorted({*current, OUTPUTS["record"]})})
    # the summary is the caller's one line (stages/label.py), not also a log line
    log.debug("label: %d images -> %s (%s); %d skipped", n, out, ", ".join(fmts), policy.bad_count())
    return LabelResult(out, table, [(r["path"], r["reason"]) for r in policy.skipped], fmts, tcfg["backend"],
                       policy.summary("label", out / OUTPUTS["skipped"]))
