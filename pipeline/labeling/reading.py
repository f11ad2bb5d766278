"""What ``geodistill label`` reads and plans before writing.

The input folder (checked, then every file read once), the outputs it will own, the teacher's answers, and a
finished label folder (``distill --labels``).
"""

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
from pipeline.catalog import output_names
from pipeline.datasets.loading import (SUPPORTED_SUFFIXES, BadFileError, DecodeCache, load_mask, load_rgb,
                                       reset_frame_warnings)
from pipeline.datasets.manifest import BadInputPolicy, relative_id
from pipeline.datasets.scan import scan_inputs
from pipeline.labeling.formats import LABEL_FORMATS
from pipeline.params import section
from pipeline.runtime.errors import (BACKEND, CHECKPOINT, INPUT, LABELS, OUT, OVERWRITE, REFERENCE_MASKS, InputError,
                                     literal)
from pipeline.runtime.progress import progress
from pipeline.teacher_table import is_simulator
from pipeline.teachers import check_teacher_params
from pipeline.teachers.base import TeacherInput
from pipeline.teachers.jobs import in_view
from pipeline.teachers.runner import open_runner

__all__ = ["OUTPUTS", "SIMULATOR_NOTE", "find_images", "check_label_folder", "LabelJob", "open_folder"]

log = logging.getLogger("pipeline.labeling.run")  # label's one logger: callers listen to it

OUTPUTS = output_names("label")
#: written whatever the formats; the caches under .cache/ are not label's outputs
ALWAYS = tuple(OUTPUTS[k] for k in ("table", "csv", "sheet", "skipped"))
SIMULATOR_NOTE = ("teacher.backend=simulated is a SIMULATOR of foundation-model errors that reads the "
                  "reference masks given with --reference-masks; these are not a real teacher's labels")


def find_images(input_dir: str | Path):
    """Find the images under ``input_dir``, recursively.

    Parameters
    ----------
    input_dir : str or Path
        The input folder.

    Returns
    -------
    pipeline.datasets.scan.FolderScan
        The folder's images and the entries left out.

    Raises
    ------
    InputError
        ``input_dir`` does not exist, is not a folder, or holds no image.
    """
    root = Path(input_dir)
    if not root.is_dir():
        raise InputError(f"{root}: input folder not found" if not root.exists() else
                         f"{root}: not a folder (label and distill take a folder of images)")
    found = scan_inputs(root)
    if not found.files:
        raise InputError(f"{root}: no images ({', '.join(s.lstrip('.') for s in SUPPORTED_SUFFIXES)}) in this folder")
    return found


def image_ids(root: Path, files: Sequence[Path]) -> list[str]:
    """Return each file's label name (:func:`pipeline.datasets.manifest.relative_id`).

    Parameters
    ----------
    root : Path
        The input folder.
    files : sequence of Path
        Image files under it.

    Returns
    -------
    list of str
        The ids, in the files' order.

    Raises
    ------
    InputError
        Two ids are equal ignoring letter case.
    """
    ids = [relative_id(root, f) for f in files]
    seen: dict[str, Path] = {}
    for iid, f in zip(ids, files):
        other = seen.setdefault(iid.lower(), f)
        if other is not f:
            raise InputError(f"{f}: same label name {iid!r} as {other} (label files are named by the image "
                             f"path without its suffix; rename one of them)")
    return ids


def label_targets(root: Path, files: Sequence[Path], ids: Sequence[str], fmts: Sequence[str]) -> list[str]:
    """List the files a run writes under ``out``: what label.json lists (the record itself left out).

    The files always written, then each format's own in the order of ``fmts`` (``LabelFormat.files``).

    Parameters
    ----------
    root : Path
        The input folder.
    files : sequence of Path
        The image files.
    ids : sequence of str
        Their ids.
    fmts : sequence of str
        The formats written: names in :data:`pipeline.labeling.formats.LABEL_FORMATS`.

    Returns
    -------
    list of str
        Relative posix paths.
    """
    rels = [f.relative_to(root).as_posix() for f in files]
    return [*ALWAYS, *(p for name in fmts for p in LABEL_FORMATS[name].files(ids, rels))]


def find_reference_masks(mask_dir: str | Path, ids: Sequence[str]) -> list[Path]:
    """Find the reference mask ``<id>.<suffix>`` of every image id in ``mask_dir``.

    Parameters
    ----------
    mask_dir : str or Path
        The folder of reference masks (the simulated teacher's input).
    ids : sequence of str
        The image ids.

    Returns
    -------
    list of Path
        One mask per id, in order.

    Raises
    ------
    InputError
        The folder does not exist, or an image has no mask (naming the first).
    """
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
    """Take a relative cache folder inside the output folder, so a rerun there resumes."""
    if path is None:
        return None
    return str(path) if Path(path).is_absolute() else str(out / path)


def check_label_folder(label_dir: str | Path, input_dir: str | Path) -> dict:
    """Return the record (label.json) of an unmodified, complete ``label`` output of the images in ``input_dir``.

    Parameters
    ----------
    label_dir : str or Path
        The label output folder (``distill --labels``).
    input_dir : str or Path
        The images it must have labelled.

    Returns
    -------
    dict
        The record.

    Raises
    ------
    InputError
        One line naming ``--labels``: no record, an unfinished run, labels of other images, the SIMULATOR's
        labels, no checksums, a written file missing or changed (its sha256 differs), or an image added or gone
        since.
    """
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
    """One ``label`` run: its inputs, checked before anything is written, then read, then answered.

    Attributes
    ----------
    root : Path
        The input folder.
    out : Path
        The output folder.
    files : list of Path
        The readable image files.
    ids : list of str
        Their ids.
    policy : pipeline.datasets.manifest.BadInputPolicy
        What happens to bad files, and the list of those left out.
    data_cfg : dict
        The params ``data`` section.
    geo : dict
        The params ``geometry`` section.
    tcfg : dict
        The checked params ``teacher`` section (absolute cache folder).
    size : int
        The working resolution.
    simulated : bool
        Whether the teacher is the SIMULATOR.
    ref_files : list of Path or None
        The SIMULATOR's reference masks, one per file.
    cache : pipeline.datasets.loading.DecodeCache or None
        The decoded-image cache.
    copy_images : bool
        Formats that place the inputs beside the labels (yolo/images) copy them; False: relative links.
    shas : list of str
        sha256 of each file.
    sizes : list of tuple of int
        (height, width) of each image.
    previous : set of str
        Label's files of an earlier run (its label.json).
    targets : list of str
        The files this run writes (:func:`label_targets`).
    runner : pipeline.teachers.runner.TeacherRunner
        The teacher runner, every answer cached.
    fingerprint : str
        The teacher's fingerprint.
    stats : object
        The runner's RunStats.
    """

    root: Path
    out: Path
    files: list
    ids: list
    policy: BadInputPolicy
    data_cfg: dict
    geo: dict
    tcfg: dict
    size: int
    simulated: bool  # a SIMULATOR's labels (pipeline.teacher_table.is_simulator)
    ref_files: list | None
    cache: DecodeCache | None
    copy_images: bool = False  # formats that place the inputs beside the labels copy them (else: relative links)
    shas: list = dataclasses.field(default_factory=list)
    sizes: list = dataclasses.field(default_factory=list)
    previous: set = dataclasses.field(default_factory=set)  # label's files of an earlier run (its label.json)
    targets: list = dataclasses.field(default_factory=list)  # the files this run writes (label_targets)
    runner: object = None  # pipeline.teachers.runner.TeacherRunner, with every answer cached
    fingerprint: str = ""  # the teacher's
    stats: object = None   # the runner's RunStats


def plan_folder(input_dir, out, params: Mapping, reference_masks, overwrite: bool, fmts: Sequence[str]) -> LabelJob:
    """Plan a run before anything is written.

    Scans the folder, applies the bad-file policy to links and non-images, refuses outputs the user owns, and
    checks the teacher and reference-mask options.

    Parameters
    ----------
    input_dir : str or Path
        The input folder.
    out : str or Path
        The output folder; not the input folder or inside it.
    params : mapping
        Validated params.
    reference_masks : str or Path or None
        The SIMULATOR's reference masks (required for it, refused otherwise).
    overwrite : bool
        Write into a folder this command did not make, removing the labels of images no longer there.
    fmts : sequence of str
        The formats written.

    Returns
    -------
    LabelJob
        The planned job (nothing read yet).

    Raises
    ------
    InputError
        ``out`` is the input folder or inside it, it holds labels of images gone (without ``overwrite``), the
        reference-mask option does not fit the teacher, or as :func:`find_images`, :func:`image_ids` and
        :func:`find_reference_masks`.
    """
    found = find_images(input_dir)
    root, files = found.root, found.files
    out = Path(out)
    if out.resolve() == root.resolve() or root.resolve() in out.resolve().parents:
        raise InputError("{}: must not be the input folder or inside it", OUT(out))
    ids = image_ids(root, files)
    policy = BadInputPolicy(section(params, "data")["skip_bad"])
    # bad entries (links leaving the folder, broken links) are reported; non-images only listed
    policy.report_scan(found)
    planned, every_format = label_targets(root, files, ids, fmts), set(label_targets(root, files, ids, LABEL_FORMATS))
    check_outputs(out, planned, OUTPUTS["record"], "label", overwrite=overwrite)
    # adding images is fine; losing the labels of images no longer here is not, unless asked
    per_image = tuple(folder for f in LABEL_FORMATS.values() for folder in f.image_folders)
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
    simulated = is_simulator(tcfg["backend"])
    if simulated and reference_masks is None:
        raise InputError("{} is a SIMULATOR that reads reference masks: pass {} (masks named like the images); "
                         "use {} for real labels", BACKEND(tcfg["backend"]), REFERENCE_MASKS("DIR"),
                         CHECKPOINT("SAM3_DIR"))
    if not simulated and reference_masks is not None:
        raise InputError(f"{{}}: only the simulated teacher (a SIMULATOR) reads masks; teacher.backend="
                         f"{literal(tcfg['backend'])} never does", REFERENCE_MASKS)
    ref_files = find_reference_masks(reference_masks, ids) if simulated else None
    # absolute: Ray workers need not share this process's working directory
    cache = DecodeCache(os.path.abspath(_inside(data_cfg["cache_dir"], out))) if data_cfg["cache_dir"] else None
    return LabelJob(root, out, list(files), list(ids), policy, data_cfg, geo, tcfg, int(data_cfg["resolution"]),
                    simulated, ref_files, cache)


def read_images(job: LabelJob) -> None:
    """Read every file once: its sha256 (the teacher cache's key) and native size.

    Bad files, and files above ``data.max_pixels`` (refused on their header), go to the job's policy and leave
    its lists.

    Parameters
    ----------
    job : LabelJob
        A planned job, updated in place.

    Raises
    ------
    InputError
        A SIMULATOR reference mask's size differs from its image's, or no image could be read.
    """
    keep = []
    limit = job.data_cfg["max_pixels"]
    for i, f in enumerate(progress(job.files, desc="label: reading", unit="img")):
        try:
            loaded = load_rgb(f, job.size, job.cache, max_pixels=limit, bit_depth=job.data_cfg["bit_depth"])
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
    """The teacher's input reader: ``(row, view) -> TeacherInput`` of a job's images at the working resolution.

    For the SIMULATOR it also reads the reference masks.  Picklable: Ray's CPU workers decode with it.

    Parameters
    ----------
    job : LabelJob
        A job whose images were read (:func:`read_images`).
    """

    def __init__(self, job: LabelJob):
        absolute = lambda paths: None if paths is None else [Path(os.path.abspath(p)) for p in paths]  # noqa: E731
        # absolute paths: Ray workers need not share this process's working directory
        self.files, self.ref_files = absolute(job.files), absolute(job.ref_files)
        self.ids, self.shas, self.size = job.ids, job.shas, job.size
        self.max_pixels, self.bit_depth = job.data_cfg["max_pixels"], job.data_cfg["bit_depth"]
        self.cache = job.cache

    def __call__(self, row: int, view: str) -> TeacherInput:
        """Read image ``row`` in ``view``.

        Parameters
        ----------
        row : int
            The image's row in the job.
        view : str
            The view (e.g. a flip) the teacher sees it in.

        Returns
        -------
        pipeline.teachers.base.TeacherInput
            The image, its id and sha256, and for the SIMULATOR its reference mask.
        """
        image = load_rgb(self.files[row], self.size, self.cache, max_pixels=self.max_pixels,
                         bit_depth=self.bit_depth).array
        reference = None
        if self.ref_files is not None:
            mask = load_mask(self.ref_files[row], self.size, self.cache, max_pixels=self.max_pixels).array.astype(bool)
            reference = {"mask": in_view(mask, view)}
        return TeacherInput(image_id=self.ids[row], image_sha256=self.shas[row], image=in_view(image, view),
                            view=view, reference=reference)


def open_folder(input_dir, out, params: Mapping, reference_masks, overwrite: bool, fmts: Sequence[str],
                device: str = "auto", workers: int = 0, address: str | None = None, on_batch=None,
                on_teacher=None) -> LabelJob:
    """Plan, read and answer a label run.

    Plans the run, reads every image (a bad one stops it before any output folder stays), claims the outputs in
    label.json as an unfinished run, then fills the teacher cache with every answer through the teacher stage's
    runner.

    Parameters
    ----------
    input_dir : str or Path
        The input folder.
    out : str or Path
        The output folder.
    params : mapping
        Validated params.
    reference_masks : str or Path or None
        The SIMULATOR's reference masks.
    overwrite : bool
        As :func:`plan_folder`.
    fmts : sequence of str
        The formats written.
    device : str, optional
        ``auto`` (default), ``cpu`` or ``cuda``.
    workers : int, optional
        Teachers in a Ray Data pool; 0 (default): serial, the same answers.
    address : str, optional
        The Ray cluster to join with ``workers``.
    on_batch : callable, optional
        The runner's callback after each batch (:meth:`~pipeline.teachers.runner.TeacherRunner.fill`), e.g.
        :class:`~pipeline.labeling.run.TeacherClock`; None (default): none.
    on_teacher : callable, optional
        Called with the run's teacher once it is made, before the fill (``label`` names its path in the
        projection); None (default): none.

    Returns
    -------
    LabelJob
        The job, every teacher answer cached.

    Raises
    ------
    InputError
        As :func:`plan_folder` and :func:`read_images`.
    """
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
    if on_teacher is not None:
        on_teacher(job.runner.teacher)
    job.stats = job.runner.fill(range(len(job.files)), workers=workers, address=address, on_batch=on_batch)
    log.info("label: teacher computed %d answers on %d images; %d cached answers reused",
             job.stats.answers_computed, job.stats.images_computed, job.stats.cache_hits)
    return job
