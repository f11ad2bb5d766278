"""What ``geodistill label`` reads and plans before writing: the input folder (checked, then every file
read once), the outputs it will own, the teacher's answers, and a finished label folder (``distill --labels``)."""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import os
from pathlib import Path
from typing import Mapping, Sequence

import pandas as pd

from pipeline.artifacts.atomic import folders_gone_on_failure
from pipeline.artifacts.ownership import check_outputs, claim_outputs, owned_outputs, read_record
from pipeline.catalog import output_file, output_names
from pipeline.datasets.loading import (SUPPORTED_SUFFIXES, BadFileError, DecodeCache, load_mask, load_rgb,
                                       reset_frame_warnings)
from pipeline.datasets.manifest import BadInputPolicy, relative_id
from pipeline.datasets.scan import scan_inputs
from pipeline.params import section
from pipeline.runtime.errors import (BACKEND, CHECKPOINT, INPUT, LABELS, OUT, OVERWRITE, REFERENCE_MASKS, InputError,
                                     literal)
from pipeline.runtime.progress import progress
from pipeline.teachers import check_teacher_params
from pipeline.teachers.base import TeacherInput
from pipeline.teachers.jobs import in_view
from pipeline.teachers.runner import open_runner

log = logging.getLogger("pipeline.labeling.run")  # label's one logger: callers listen to it

FORMATS = ("png", "coco", "yolo")
OUTPUTS = output_names("label")
#: yolo/'s image lists: training, then validation
YOLO_LISTS = (output_file("label_yolo", "train"), output_file("label_yolo", "val"))
YOLO_DATA, YOLO_README = output_file("label_yolo", "data"), output_file("label_yolo", "readme")
#: written whatever the formats; the caches under .cache/ are not label's outputs
ALWAYS = tuple(OUTPUTS[k] for k in ("table", "csv", "sheet", "skipped"))
SIMULATOR_NOTE = ("teacher.backend=simulated is a SIMULATOR of foundation-model errors that reads the "
                  "reference masks given with --reference-masks; these are not a real teacher's labels")


def find_images(input_dir: str | Path):
    """The :class:`pipeline.datasets.scan.Inputs` of ``input_dir``, recursively; InputError when it is not
    a folder or holds no image."""
    root = Path(input_dir)
    if not root.is_dir():
        raise InputError(f"{root}: input folder not found" if not root.exists() else
                         f"{root}: not a folder (label and distill take a folder of images)")
    found = scan_inputs(root)
    if not found.files:
        raise InputError(f"{root}: no images ({', '.join(s.lstrip('.') for s in SUPPORTED_SUFFIXES)}) in this folder")
    return found


def image_ids(root: Path, files: Sequence[Path]) -> list[str]:
    """Each file's label name (:func:`~pipeline.datasets.manifest.relative_id`); InputError when two would be
    equal ignoring letter case."""
    ids = [relative_id(root, f) for f in files]
    seen: dict[str, Path] = {}
    for iid, f in zip(ids, files):
        other = seen.setdefault(iid.lower(), f)
        if other is not f:
            raise InputError(f"{f}: same label name {iid!r} as {other} (label files are named by the image "
                             f"path without its suffix; rename one of them)")
    return ids


def label_targets(root: Path, files: Sequence[Path], ids: Sequence[str], fmts: Sequence[str]) -> list[str]:
    """The files a run writes under ``out`` (relative, posix; the record left out): what label.json lists."""
    out = list(ALWAYS)
    if "png" in fmts:
        out += [f"{OUTPUTS['masks']}/{i}.png" for i in ids]
    if "coco" in fmts:
        out.append(OUTPUTS["coco"])
    if "yolo" in fmts:
        out += [f"{OUTPUTS['yolo']}/labels/{i}.txt" for i in ids]
        out += [f"{OUTPUTS['yolo']}/images/{f.relative_to(root).as_posix()}" for f in files]
        lists = YOLO_LISTS if len(ids) >= 2 else YOLO_LISTS[:1]  # no val.txt below 2 images (yolo_split)
        out += [f"{OUTPUTS['yolo']}/{name}" for name in (YOLO_DATA, *lists, YOLO_README)]
    return out


def find_reference_masks(mask_dir: str | Path, ids: Sequence[str]) -> list[Path]:
    """The reference mask ``<id>.<suffix>`` of every image id in ``mask_dir``; InputError naming the first
    image without one."""
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
    """A relative cache folder is taken inside the output folder, so a rerun there resumes."""
    if path is None:
        return None
    return str(path) if Path(path).is_absolute() else str(out / path)


def check_label_folder(label_dir: str | Path, input_dir: str | Path) -> dict:
    """The record (label.json) of an unmodified, complete ``label`` output folder of the images in
    ``input_dir`` (``distill --labels``); otherwise InputError, one line naming the option: no record,
    an unfinished run, other images, the SIMULATOR's labels, or a written file missing or changed (its
    sha256 differs from the record's)."""
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


@dataclasses.dataclass
class LabelJob:
    """One ``label`` run: its inputs, checked before anything is written, then read, then answered."""

    root: Path
    out: Path
    files: list
    ids: list
    policy: BadInputPolicy
    data_cfg: dict
    geo: dict
    tcfg: dict
    size: int
    simulated: bool
    ref_files: list | None
    cache: DecodeCache | None
    shas: list = dataclasses.field(default_factory=list)
    sizes: list = dataclasses.field(default_factory=list)
    previous: set = dataclasses.field(default_factory=set)  # label's files of an earlier run (its label.json)
    targets: list = dataclasses.field(default_factory=list)  # the files this run writes (label_targets)
    runner: object = None  # pipeline.teachers.runner.TeacherRunner, with every answer cached
    fingerprint: str = ""  # the teacher's
    stats: object = None   # the runner's RunStats


def plan_folder(input_dir, out, params: Mapping, reference_masks, overwrite: bool, fmts: Sequence[str]) -> LabelJob:
    """Scan the folder, apply the bad-file policy to links and non-images, refuse outputs the user owns
    and check the teacher and reference-mask options: all before anything is written."""
    found = find_images(input_dir)
    root, files = found.root, found.files
    out = Path(out)
    if out.resolve() == root.resolve() or root.resolve() in out.resolve().parents:
        raise InputError("{}: must not be the input folder or inside it", OUT(out))
    ids = image_ids(root, files)
    policy = BadInputPolicy(section(params, "data")["skip_bad"])
    # bad entries (links leaving the folder, broken links) are reported; non-images only listed
    policy.report_scan(found)
    planned, every_format = label_targets(root, files, ids, fmts), set(label_targets(root, files, ids, FORMATS))
    check_outputs(out, planned, OUTPUTS["record"], "label", overwrite=overwrite)
    # adding images is fine; losing the labels of images no longer here is not, unless asked
    per_image = (f"{OUTPUTS['masks']}/", f"{OUTPUTS['yolo']}/labels/", f"{OUTPUTS['yolo']}/images/")
    gone = sorted(p for p in owned_outputs(out, OUTPUTS["record"], "label") - every_format
                  if p.startswith(per_image) and ((out / p).is_symlink() or (out / p).is_file()))
    if gone and not overwrite:
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
    # absolute: Ray workers need not share this process's working directory
    cache = DecodeCache(os.path.abspath(_inside(data_cfg["cache_dir"], out))) if data_cfg["cache_dir"] else None
    return LabelJob(root, out, list(files), list(ids), policy, data_cfg, geo, tcfg, int(data_cfg["resolution"]),
                    simulated, ref_files, cache)


def read_images(job: LabelJob) -> None:
    """Read every file once (sha256 for the teacher cache, native size); bad files, and files above
    ``data.max_pixels`` (refused on their header), go to the policy and leave ``job``'s lists."""
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
        job.shas.append(loaded.content_sha256)  # the teacher cache keys on the pixels it sees
        job.sizes.append(loaded.native_hw)
    if not keep:
        first = job.policy.skipped[-1]
        raise InputError(f"{job.root}: none of the {len(job.files)} images could be read (first: {first['path']}: "
                         f"{first['reason']})")
    job.files = [job.files[i] for i in keep]
    job.ids = [job.ids[i] for i in keep]
    job.ref_files = [job.ref_files[i] for i in keep] if job.ref_files is not None else None


class FolderInputs:
    """``(row, view) -> TeacherInput`` of the job's image files at the working resolution (and for the
    SIMULATOR its reference masks).  Picklable: Ray's CPU workers decode with it."""

    def __init__(self, job: LabelJob):
        absolute = lambda paths: None if paths is None else [Path(os.path.abspath(p)) for p in paths]  # noqa: E731
        # absolute paths: Ray workers need not share this process's working directory
        self.files, self.ref_files = absolute(job.files), absolute(job.ref_files)
        self.ids, self.shas, self.size = job.ids, job.shas, job.size
        self.max_pixels, self.bit_depth = job.data_cfg["max_pixels"], job.data_cfg.get("bit_depth", "auto")
        self.cache = job.cache

    def __call__(self, row: int, view: str) -> TeacherInput:
        image = load_rgb(self.files[row], self.size, self.cache, max_pixels=self.max_pixels,
                         bit_depth=self.bit_depth).array
        reference = None
        if self.ref_files is not None:
            mask = load_mask(self.ref_files[row], self.size, self.cache, max_pixels=self.max_pixels).array.astype(bool)
            reference = {"mask": in_view(mask, view)}
        return TeacherInput(image_id=self.ids[row], image_sha256=self.shas[row], image=in_view(image, view),
                            view=view, reference=reference)


def open_folder(input_dir, out, params: Mapping, reference_masks, overwrite: bool, fmts: Sequence[str],
                device: str = "auto", workers: int = 0, address: str | None = None, on_batch=None) -> LabelJob:
    """Plan the run, read every image (a bad one stops it before any output folder stays), claim the
    outputs in label.json as an unfinished run, then fill the teacher cache with every answer through
    the teacher stage's runner (serial, or a Ray Data pool of ``workers``); ``on_batch``: the runner's
    callback after each batch (:meth:`~pipeline.teachers.runner.TeacherRunner.fill`)."""
    job = plan_folder(input_dir, out, params, reference_masks, overwrite, fmts)
    reset_frame_warnings()  # each run says once how it reads 16-bit frames
    made = [job.out, job.out / ".cache"] + ([job.cache.root] if job.cache is not None else [])
    with folders_gone_on_failure(*made):
        read_images(job)
    job.targets, inputs = label_targets(job.root, job.files, job.ids, fmts), FolderInputs(job)
    job.previous = owned_outputs(job.out, OUTPUTS["record"], "label")
    claim_outputs(job.out, job.targets, OUTPUTS["record"], "label",
                  {"input": str(job.root.resolve()), "complete": False})
    job.runner, job.fingerprint = open_runner(job.tcfg, (job.size, job.size), device, inputs, job.shas)
    if job.simulated:
        log.warning("label: %s", SIMULATOR_NOTE)
    job.stats = job.runner.fill(range(len(job.files)), workers=workers, address=address, on_batch=on_batch)
    log.info("label: teacher computed %d answers on %d images; %d cached answers reused",
             job.stats.answers_computed, job.stats.images_computed, job.stats.cache_hits)
    return job
