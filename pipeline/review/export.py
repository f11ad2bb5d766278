"""``geodistill review export LABEL_DIR --out DIR`` and the DAG stage ``review_export``.

Both write the images that most need a person, ranked, as a Label Studio import, a CVAT import and a CSV, with
``review.json`` (the export id, a hash of the teacher, options and rows, and each image's voted mask) that
``review import`` checks against.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import urllib.parse
from pathlib import Path
from typing import Callable

import numpy as np

from pipeline.artifacts.atomic import atomic_path, write_json
from pipeline.artifacts.lineage import canonical_json
from pipeline.catalog import output_names
from pipeline.params import PAPER
from pipeline.datasets.loading import probs_to_size, read_mask
from pipeline.runtime.errors import OUT, InputError, Option, literal
from pipeline.labeling.formats import SPACECRAFT_CATEGORY, rle_encode
from pipeline.labeling.run import OUTPUTS as LABEL_OUTPUTS
from pipeline.labeling.run import mask_file
from pipeline.artifacts.ownership import (check_outputs, claim_outputs, read_record, record_fields,
                                refuse_foreign_files, signature)
from pipeline.review.formats import coco_review_annotation, ls_label_config, ls_results
from pipeline.review.ranking import DEFAULT_RANKING, STUDENT_COLUMN, rank, student_disagreement

__all__ = ["COMMAND", "COCO_SHAPES", "LS_SHAPES", "OUTPUTS", "EXPORT_FIELD", "LS_RECORD_KEY", "server_env",
           "export_review", "write_export", "export_run"]

COMMAND = "review export"
LABEL_DIR = Option("LABEL_DIR", "label_dir")
TOP = Option("--top", "top")
LS_SHAPE = Option("--ls-shape", "ls_shape")
COCO_SHAPE = Option("--coco-shape", "coco_shape")
LS_SHAPES, COCO_SHAPES = ("brush", "polygon"), ("rle", "polygon")
OUTPUTS = output_names("review", "record", "csv", "labelstudio", "cvat")
OWN_OUTPUTS = tuple(v for k, v in OUTPUTS.items() if k != "record")
LS_TASKS, LS_CONFIG, CVAT_COCO = output_names("review", "ls_tasks", "ls_config", "cvat_coco").values()
#: the files the export writes in each folder it replaces whole
FOLDER_FILES = {OUTPUTS["labelstudio"]: (LS_TASKS, LS_CONFIG), OUTPUTS["cvat"]: (CVAT_COCO,)}
EXPORT_FIELD = "geodistill_export"   # the task data field naming the export (review import checks it)
MODEL_VERSION = "geodistill-vote"    # the predictions' model_version in Label Studio
LOCAL_FILES_URL = "/data/local-files/?d="
ENV_SERVING, ENV_ROOT = "LABEL_STUDIO_LOCAL_FILES_SERVING_ENABLED", "LABEL_STUDIO_LOCAL_FILES_DOCUMENT_ROOT"
LS_RECORD_KEY = "label_studio"   # review.json: {"document_root", "storage_path"} of the local-files URLs


@dataclasses.dataclass
class ReviewExport:
    """What an export wrote.

    Attributes
    ----------
    out : Path
        The export folder.
    table : pandas.DataFrame
        The exported rows, ranked (:func:`pipeline.review.ranking.rank`).
    export_id : str
        The export's id: a hash of the teacher's identity, the options and the rows.
    ranking : str
        The ranking used.
    """

    out: Path
    table: object
    export_id: str
    ranking: str


def read_label_folder(label_dir: str | Path):
    """Read (record, table) of a complete ``geodistill label`` output folder with PNG masks; InputError otherwise."""
    import pandas as pd

    d = Path(label_dir)
    record = read_record(d / LABEL_OUTPUTS["record"], "label")
    if record is None:
        raise InputError(f"{{}}: not an output folder of geodistill label (no {literal(LABEL_OUTPUTS['record'])} "
                         f"of it there)", LABEL_DIR(d))
    if not record.get("complete"):
        raise InputError("{}: that label run did not finish; rerun it (it resumes from its cache)", LABEL_DIR(d))
    if mask_file(record.get("formats", [])) is None:
        raise InputError(f"{{}}: label wrote no {literal(LABEL_OUTPUTS['masks'])}/ PNGs there; rerun geodistill "
                         f"label with --format png (plus any other format)", LABEL_DIR(d))
    table = pd.read_parquet(d / LABEL_OUTPUTS["table"])
    return record, table


def voted_mask(path: Path, width: int, height: int) -> np.ndarray:
    """Read the voted mask label wrote at ``path`` (:func:`pipeline.labeling.run.mask_file`).

    An InputError names the file when its size is not the image's.
    """
    mask = read_mask(path)
    if mask.shape != (height, width):
        raise InputError(f"{path}: mask size {mask.shape[1]}x{mask.shape[0]} is not the image's {width}x{height}")
    return mask


def mask_digest(mask: np.ndarray) -> str:
    """Hash a bool mask's shape and packed bits with sha256 (the content, not a file encoding)."""
    m = np.asarray(mask, bool)
    return hashlib.sha256(f"{m.shape[0]}x{m.shape[1]}:".encode() + np.packbits(m).tobytes()).hexdigest()


# Label Studio (1.23.2) serves /data/local-files/?d=PATH only with both ENV_* variables set, PATH relative to
# the document root, under a Local files storage whose path (a strict sub-folder of that root) holds the file
def local_files_layout(image_paths: list[Path], image_root: Path | None = None) -> dict:
    """Lay out the Local files storage serving ``image_paths``: ``{"document_root", "storage_path"}``.

    The storage path is ``image_root`` (default: the folder they share; relative paths stay relative), the
    document root its parent.  An InputError says so when the images share no folder below the root.
    """
    if image_root is not None:
        storage = Path(image_root)
    else:
        dirs = [str(Path(p).parent) for p in image_paths] or ["."]
        try:
            storage = Path(os.path.commonpath(dirs))
        except ValueError:   # absolute and relative paths mixed
            storage = Path(os.path.commonpath([str(Path(d).resolve()) for d in dirs]))
    if storage.parent == storage:   # "." has no parent written out
        storage = storage.resolve()
    if storage.parent == storage:
        raise InputError(f"{storage}: the images share no folder below the file-system root, so Label Studio's "
                         f"Local files storage cannot serve them; give the tasks URLs of your own "
                         f"(review export's --image-url)")
    return {"document_root": str(storage.parent), "storage_path": str(storage)}


def local_files_url(path: Path, layout: dict) -> str:
    """Make the task URL of ``path``: its path from the document root, percent-encoded (``+&#`` alter the query)."""
    rel = Path(path).resolve().relative_to(Path(layout["document_root"]).resolve()).as_posix()
    return LOCAL_FILES_URL + urllib.parse.quote(rel, safe="/")


def server_env(layout: dict) -> dict:
    """Name the environment variables Label Studio must start with to serve ``layout``'s images.

    Parameters
    ----------
    layout : dict
        The export's Local files layout (``review.json`` :data:`LS_RECORD_KEY`): ``document_root``,
        ``storage_path``.

    Returns
    -------
    dict
        Variable name -> value: local-files serving on, and the document root (absolute).
    """
    return {ENV_SERVING: "true", ENV_ROOT: str(Path(layout["document_root"]).resolve())}


def _check_options(top, ls_shape: str, coco_shape: str) -> None:
    """Refuse a ``--top`` below 1 or an unknown shape, naming the option."""
    if top is not None and int(top) < 1:
        raise InputError("{}: must be at least 1 (leave it out to export every image)", TOP(top))
    for option, value, allowed in ((LS_SHAPE, ls_shape, LS_SHAPES), (COCO_SHAPE, coco_shape, COCO_SHAPES)):
        if value not in allowed:
            raise InputError(f"{{}}: expected one of {', '.join(allowed)}", option(value))


def check_export_outputs(out: Path, overwrite: bool) -> None:
    """Refuse before anything is written: first a user's file inside a folder the export replaces whole.

    Such a file is refused with ``overwrite`` or not; then whatever else is in the way (without ``overwrite``).
    """
    for folder, files in FOLDER_FILES.items():  # first: --overwrite would not save such a file either
        refuse_foreign_files(out / folder, files, command=COMMAND, option=OUT, where=out,
                             why=f"not a file {signature(COMMAND)} writes in {folder}/, which it replaces whole")
    check_outputs(out, OWN_OUTPUTS, OUTPUTS["record"], COMMAND, overwrite=overwrite, option=OUT)


def export_review(label_dir: str | Path, out: str | Path, *, top: int | None = None, ranking: str = DEFAULT_RANKING,
                  ls_shape: str = "brush", coco_shape: str = "rle", image_url: str | None = None,
                  predict: Callable[[Path], np.ndarray] | None = None, overwrite: bool = False) -> ReviewExport:
    """Rank the images of a ``geodistill label`` folder and write the top ones for a person (``review export``).

    Parameters
    ----------
    label_dir : str or Path
        A complete ``geodistill label`` output folder with PNG masks.
    out : str or Path
        The export folder.
    top : int, optional
        Export the first ``top`` images; None exports all.
    ranking : str
        A ranking of :data:`pipeline.review.ranking.RANKINGS`.
    ls_shape : str
        How the Label Studio predictions draw the voted mask: one of :data:`LS_SHAPES` (``brush``, ``polygon``).
    coco_shape : str
        How the CVAT COCO annotations draw it: one of :data:`COCO_SHAPES` (``rle``, ``polygon``).
    image_url : str or None
        The tasks' image URL prefix (``<image_url><file>``); None: Label Studio's local-files URLs, served by a
        Local files storage (:func:`server_env`).
    predict : callable, optional
        ``predict(image path) -> bool [H,W]``: a student whose disagreement with the vote the table gains
        (:func:`pipeline.review.ranking.student_disagreement`); None: no student.
    overwrite : bool
        Replace the export's output paths even where no review.json of this command owns them (never a user's
        file inside a folder it replaces whole).

    Returns
    -------
    ReviewExport
        The folder, the ranked table written, the export id and the ranking.

    Raises
    ------
    pipeline.runtime.errors.InputError
        From the checks it calls: a bad option, an unfinished or foreign label folder, a mask of the wrong size,
        or an output in the way.
    """
    _check_options(top, ls_shape, coco_shape)
    label_dir, out = Path(label_dir), Path(out)
    record, table = read_label_folder(label_dir)
    check_export_outputs(out, overwrite)
    sizes = dict(zip(table["image_id"], zip(table["width"].astype(int), table["height"].astype(int))))
    where = mask_file(record["formats"])
    voted = lambda i: voted_mask(label_dir / where(i), *sizes[i])  # noqa: E731
    if predict is not None:
        root = Path(record["input"])
        table[STUDENT_COLUMN] = [student_disagreement(predict(root / f), voted(i))
                                 for i, f in zip(table["image_id"], table["file"])]
    return write_export(out, table, voted, top=top, ranking=ranking,
                        ls_shape=ls_shape, coco_shape=coco_shape, image_url=image_url,
                        image_root=Path(record["input"]), identity={"teacher": record.get("teacher_fingerprint")},
                        options={"student": predict is not None},
                        record={"label_dir": str(label_dir.resolve()), "input": record["input"],
                                "simulator": bool(record.get("simulator"))})


def write_export(out: Path, table, mask_of: Callable[[str], np.ndarray], *, top: int | None, ranking: str,
                 ls_shape: str, coco_shape: str, image_url: str | None, identity: dict, options: dict | None = None,
                 record: dict | None = None, image_root: Path | None = None) -> ReviewExport:
    """Write an export: the part ``review export`` and the DAG stage share.

    It ranks ``table``, takes each voted mask from ``mask_of`` and writes review.json, ranked.csv, the Label
    Studio tasks and the CVAT COCO file under ``out`` (its outputs claimed first; review.json complete last).

    Parameters
    ----------
    out : Path
        The export folder.
    table : pandas.DataFrame
        The label table: ``image_id``, ``file``, ``width``, ``height``, ``g``, ``h`` and what ``ranking`` reads.
    mask_of : callable
        Image id -> its voted mask (eq:majority-vote), bool [H,W] at the image's own size.
    top : int or None
        Export the first ``top`` ranked images; None exports all.
    ranking : str
        A ranking of :data:`pipeline.review.ranking.RANKINGS`.
    ls_shape : str
        How the Label Studio predictions draw the voted mask: one of :data:`LS_SHAPES` (``brush``, ``polygon``).
    coco_shape : str
        How the CVAT COCO annotations draw it: one of :data:`COCO_SHAPES` (``rle``, ``polygon``).
    image_url : str or None
        The tasks' image URL prefix (``<image_url><file>``); None: Label Studio's local-files URLs, served by a
        Local files storage (:func:`server_env`).
    identity : dict
        What identifies the source (the teacher's fingerprint); with the options and rows it makes the export id.
    options : dict, optional
        Options recorded beside the shapes, ranking and top (``student``: whether a student ranked).
    record : dict, optional
        The record's fields about the source (``label_dir``, ``input``, ``simulator``).
    image_root : Path, optional
        The folder ``file`` is relative to; None: the working directory.

    Returns
    -------
    ReviewExport
        The folder, the ranked table written, the export id and the ranking.
    """
    ranked = rank(table, ranking, top)
    masks = {i: mask_of(i) for i in ranked["image_id"]}
    rows = [{"image_id": str(r.image_id), "file": str(r.file), "width": int(r.width), "height": int(r.height),
             "rank": int(r.rank), "score": round(float(r.score), 6), "mask_sha256": mask_digest(masks[r.image_id])}
            for r in ranked.itertuples(index=False)]
    options = {"ranking": ranking, "top": top, "ls_shape": ls_shape, "coco_shape": coco_shape, "image_url": image_url,
               "student": False, **(options or {})}
    export_id = hashlib.sha256(canonical_json({**identity, "options": options, "rows": rows}).encode()).hexdigest()[:16]
    paths = {r.image_id: Path(image_root or "") / str(r.file) for r in ranked.itertuples(index=False)}
    layout = local_files_layout(list(paths.values()), image_root) if image_url is None else None
    claim_outputs(out, OWN_OUTPUTS, OUTPUTS["record"], COMMAND, {"export_id": export_id, "complete": False})

    with atomic_path(out / OUTPUTS["csv"]) as tmp:
        ranked.to_csv(tmp, index=False, float_format="%.6g")
    tasks, images, annotations = [], [], []
    for k, r in enumerate(ranked.itertuples(index=False)):
        mask = masks[r.image_id]
        url = local_files_url(paths[r.image_id], layout) if layout is not None else f"{image_url}{r.file}"
        data = {"image": url, "image_id": str(r.image_id), EXPORT_FIELD: export_id,
                "rank": int(r.rank), "score": round(float(r.score), 6), "g": round(float(r.g), 6),
                "h": round(float(r.h), 6)}
        result = ls_results(mask, ls_shape, result_id=f"vote{k + 1}")
        tasks.append({"data": data, "predictions": [{"model_version": MODEL_VERSION, "score": data["g"],
                                                     "result": result}] if result else []})
        images.append({"id": k + 1, "file_name": str(r.file), "width": int(r.width), "height": int(r.height)})
        ann = coco_review_annotation(mask, len(annotations) + 1, k + 1, coco_shape)
        if ann is not None:
            annotations.append(ann)
    with atomic_path(out / OUTPUTS["labelstudio"], is_dir=True) as tmp:
        (tmp / LS_TASKS).write_text(json.dumps(tasks, separators=(",", ":")))
        (tmp / LS_CONFIG).write_text(ls_label_config(ls_shape))
    coco = {"info": {"version": "1.0", "description": f"geodistill review export {export_id}: voted pseudo-masks "
                                                      f"ranked by {ranking}"},
            "licenses": [], "categories": [dict(SPACECRAFT_CATEGORY)], "images": images, "annotations": annotations}
    with atomic_path(out / OUTPUTS["cvat"], is_dir=True) as tmp:
        (tmp / CVAT_COCO).write_text(json.dumps(coco, separators=(",", ":")))
    for row in rows:
        row["voted_rle"] = rle_encode(masks[row["image_id"]])
    write_json(out / OUTPUTS["record"], {
        "export_id": export_id, **(record or {}), **options, LS_RECORD_KEY: layout, "images": rows, "complete": True,
        **record_fields(out, OUTPUTS["record"], COMMAND, OWN_OUTPUTS)})
    return ReviewExport(out, ranked, export_id, ranking)


#: the split the DAG stage exports: corrections are accepted for training images only
RUN_SPLIT = "train"


def run_table(manifest_df, gates_df, h: np.ndarray):
    """Build the label-table view of a run's training images (image_id, file, width, height, gate columns, h)."""
    ids = manifest_df["image_id"].astype(str).to_numpy()
    if list(gates_df["image_id"].astype(str)) != list(ids) or len(h) != len(ids):
        raise InputError("gates and consensus do not follow the manifest's images (artifacts of different runs?)")
    table = gates_df.drop(columns=["split"]).copy()
    table.insert(1, "file", manifest_df["image_path"].astype(str).to_numpy())
    table.insert(2, "width", manifest_df["width"].astype(int).to_numpy())
    table.insert(3, "height", manifest_df["height"].astype(int).to_numpy())
    table["h"] = np.asarray(h, np.float64)
    return table[(manifest_df["split"] == RUN_SPLIT).to_numpy()].reset_index(drop=True)


def export_run(manifest, consensus, gates, out: str | Path, *, top: int | None, ranking: str = DEFAULT_RANKING,
               letterbox: bool = PAPER.data.letterbox, ls_shape: str = "brush", coco_shape: str = "rle",
               image_url: str | None = None, simulator: bool = False, overwrite: bool = False) -> ReviewExport:
    """Export a run's training images for review (the DAG stage ``review_export``), via :func:`write_export`.

    Each voted mask is brought to the image's own size as the deployed student's is.

    Parameters
    ----------
    manifest : artifact
        The run's opened manifest (``image_id``, ``image_path``, ``width``, ``height``, ``split``).
    consensus : artifact
        The run's opened consensus (``voted`` masks at the working resolution, ``h``: the prompt disagreement).
    gates : artifact
        The run's opened gates (eq:reliability-gate), row for row with the manifest.
    out : str or Path
        The export folder.
    top : int or None
        Export the first ``top`` ranked images (``review.top``); None exports all.
    ranking : str
        A ranking of :data:`pipeline.review.ranking.RANKINGS` (``review.ranking``).
    letterbox : bool
        ``data.letterbox``: how the working-resolution mask maps back to the image's size.
    ls_shape : str
        How the Label Studio predictions draw the voted mask: one of :data:`LS_SHAPES` (``brush``, ``polygon``).
    coco_shape : str
        How the CVAT COCO annotations draw it: one of :data:`COCO_SHAPES` (``rle``, ``polygon``).
    image_url : str or None
        The tasks' image URL prefix (``<image_url><file>``); None: Label Studio's local-files URLs, served by a
        Local files storage (:func:`server_env`).
    simulator : bool
        The teacher is the SIMULATOR (recorded in review.json).
    overwrite : bool
        Replace the export's output paths even where no review.json of this command owns them (never a user's
        file inside a folder it replaces whole).

    Returns
    -------
    ReviewExport
        The folder, the ranked table written, the export id and the ranking.

    Raises
    ------
    pipeline.runtime.errors.InputError
        When the consensus has no prompt disagreement h (an older consensus stage), or from the checks it calls
        (bad options, gates or consensus of another run, outputs in the way).
    """
    _check_options(top, ls_shape, coco_shape)
    if "h" not in consensus:
        raise InputError(f"{consensus.path}: no prompt disagreement h (written by an older consensus stage); "
                         f"rerun the consensus stage")
    out = Path(out)
    table = run_table(manifest.df, gates.df, np.asarray(consensus["h"][...]))
    check_export_outputs(out, overwrite)
    row = {iid: i for i, iid in enumerate(manifest.df["image_id"].astype(str))}
    sizes = dict(zip(table["image_id"], zip(table["width"], table["height"])))

    def mask_of(iid: str) -> np.ndarray:
        voted = np.asarray(consensus["voted"][row[iid]], np.float32)
        return probs_to_size(voted, int(sizes[iid][1]), int(sizes[iid][0]), letterbox) >= 0.5

    return write_export(out, table, mask_of, top=top, ranking=ranking, ls_shape=ls_shape, coco_shape=coco_shape,
                        image_url=image_url, identity={"teacher": consensus.meta.fingerprint},
                        record={"label_dir": None, "input": None, "simulator": bool(simulator)})

