"""The files ``geodistill label`` writes under ``out``, each atomically.

Per image as its vote comes, then each format's finishing files, the tables, the contact sheet, skipped.csv,
and last the record label.json.  The built-in formats (png, coco, yolo) are registered here
(:class:`~pipeline.labeling.formats.LabelFormat`, :func:`~pipeline.labeling.formats.register_format`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import shutil
from pathlib import Path
from typing import Callable, Iterable

import numpy as np
import pandas as pd

from pipeline.artifacts.atomic import atomic_path, write_json, write_png
from pipeline.artifacts.ownership import OUTPUTS as RECORD_OUTPUTS
from pipeline.artifacts.ownership import WRITTEN_BY, remove_stale, signature
from pipeline.catalog import output_file
from pipeline.datasets.contact_sheet import contact_sheet, sample_for_sheet, tile
from pipeline.datasets.loading import load_rgb
from pipeline.datasets.manifest import write_skipped_csv
from pipeline.labeling.formats import (LABEL_FORMATS, LabelFormat, coco_annotation, coco_document, register_format,
                                       yolo_data_yaml, yolo_image_list, yolo_lines, yolo_readme, yolo_split)
from pipeline.labeling.reading import OUTPUTS, SIMULATOR_NOTE, LabelJob
from pipeline.pseudo_labels import Gates, gate_columns

__all__ = ["write_votes", "write_outputs"]

log = logging.getLogger("pipeline.labeling.run")  # label's one logger: callers listen to it


def _save(path: Path, content: str | Callable[[Path], object]) -> None:
    """``content`` (a text, or a function writing a given path) at ``path``, atomically."""
    with atomic_path(path) as tmp:
        if callable(content):
            content(tmp)
        else:
            tmp.write_text(content)


def _link_or_copy(src: Path, dst: Path, copy: bool) -> None:
    """Link ``dst`` to ``src`` by a relative symbolic link, or copy it.

    The link survives moving the input and output folders together; with ``copy``, or where links are refused,
    a copy.  An earlier run's file there is replaced.
    """
    dst.parent.mkdir(parents=True, exist_ok=True)
    if dst.is_symlink() or dst.is_file():  # never written through
        dst.unlink()
    if not copy:
        try:  # real paths on both sides: a link inside a linked folder still points at the file
            os.symlink(os.path.relpath(os.path.realpath(src), os.path.realpath(dst.parent)), dst)
            return
        except OSError:
            pass
    _save(dst, lambda tmp: shutil.copy2(src, tmp))


#: yolo/'s image lists: training, then validation
YOLO_LISTS = (output_file("label_yolo", "train"), output_file("label_yolo", "val"))
YOLO_DATA, YOLO_README = output_file("label_yolo", "data"), output_file("label_yolo", "readme")
MASKS, COCO, YOLO = OUTPUTS["masks"], OUTPUTS["coco"], OUTPUTS["yolo"]


def _png_mask(job: LabelJob, row: int, mask: np.ndarray) -> None:
    write_png(job.out / MASKS / f"{job.ids[row]}.png", mask.astype(np.uint8) * 255)


def _coco_document(job: LabelJob, annotations: list, table: pd.DataFrame) -> None:
    """Write coco.json: every image, and the annotation of each non-empty mask with its gate and agreement."""
    images = [{"id": i + 1, "file_name": f, "width": int(w), "height": int(h)}
              for i, (f, w, h) in enumerate(zip(table["file"], table["width"], table["height"]))]
    for i, ann in enumerate(annotations):
        if ann is not None:
            ann.update(gate=round(float(table["g"].iloc[i]), 6), agreement=round(float(table["c"].iloc[i]), 6))
    desc = "geodistill label: voted multi-prompt pseudo-masks" + (f" -- {SIMULATOR_NOTE}" if job.simulated else "")
    doc = coco_document(images, [x for x in annotations if x is not None], description=desc,
                        teacher_backend=job.tcfg["backend"], simulator=job.simulated)
    _save(job.out / COCO, json.dumps(doc, separators=(",", ":")))


def _yolo_files(ids, rels) -> list[str]:
    lists = YOLO_LISTS if len(ids) >= 2 else YOLO_LISTS[:1]  # no val.txt below 2 images (yolo_split)
    return ([f"{YOLO}/labels/{i}.txt" for i in ids] + [f"{YOLO}/images/{r}" for r in rels] +
            [f"{YOLO}/{name}" for name in (YOLO_DATA, *lists, YOLO_README)])


def _yolo_image(job: LabelJob, row: int, mask: np.ndarray) -> None:
    """Write the image (a relative link; a copy with ``job.copy_images`` or where links are refused), its label."""
    _link_or_copy(job.files[row], job.out / YOLO / "images" / job.files[row].relative_to(job.root), job.copy_images)
    _save(job.out / YOLO / "labels" / f"{job.ids[row]}.txt", "".join(line + "\n" for line in yolo_lines(mask)))


def _yolo_dataset(job: LabelJob, per_image: list, table: pd.DataFrame) -> None:
    """Write yolo/'s image lists (yolo_split), data.yaml and README.txt."""
    yolo_dir, rels, seed = job.out / YOLO, list(table["file"]), int(job.data_cfg["seed"])
    train, val = yolo_split(job.ids, seed)
    copies = job.copy_images or not (yolo_dir / "images" / rels[0]).is_symlink()
    for name, rows in zip(YOLO_LISTS, (train, val)):
        if rows:
            _save(yolo_dir / name, yolo_image_list([rels[i] for i in rows]))
    _save(yolo_dir / YOLO_DATA, yolo_data_yaml(len(train), len(val), seed))
    _save(yolo_dir / YOLO_README, yolo_readme(len(train), len(val), seed, copies))


def _yolo_summary(out: Path, n: int) -> str:
    val = out / YOLO / YOLO_LISTS[1]
    return f"yolo val: {len(val.read_text().splitlines())} of {n} images" if val.is_file() else \
        "yolo: no val split (README.txt)"


for _fmt in (
        LabelFormat("png", lambda ids, rels: [f"{MASKS}/{i}.png" for i in ids], _png_mask, image_folders=(f"{MASKS}/",),
                    mask_file=lambda iid: f"{MASKS}/{iid}.png"),
        LabelFormat("coco", lambda ids, rels: [COCO], lambda job, row, mask: coco_annotation(mask, row + 1, row + 1),
                    _coco_document),
        LabelFormat("yolo", _yolo_files, _yolo_image, _yolo_dataset, (f"{YOLO}/labels/", f"{YOLO}/images/"),
                    summary=_yolo_summary)):
    register_format(_fmt)


@dataclasses.dataclass
class Votes:
    """What the vote gave per image, collected while the per-image files are written.

    Attributes
    ----------
    c : numpy.ndarray
        Foreground agreement (eq:foreground-agreement).
    a : numpy.ndarray
        Area ratio (eq:pseudo-area) at the working resolution.
    n_valid : numpy.ndarray
        |V|.
    pixels : numpy.ndarray
        The mask's foreground pixels at the image's own size.
    h : numpy.ndarray
        The prompt disagreement.
    per_format : dict
        Format name -> list, per image, of what its ``LabelFormat.write_image`` returned (e.g. coco's
        record, None for an empty mask), handed to its ``finish``.
    sheet : dict
        Row -> (image, voted mask) of the contact sheet's sample.
    """

    c: np.ndarray
    a: np.ndarray
    n_valid: np.ndarray
    pixels: np.ndarray
    h: np.ndarray
    per_format: dict = dataclasses.field(default_factory=dict)
    sheet: dict = dataclasses.field(default_factory=dict)


def write_votes(job: LabelJob, fmts: tuple[str, ...], votes: Iterable) -> Votes:
    """Write each image's files as its vote comes, at the image's own size (nearest-neighbour resize).

    Each format's ``LabelFormat.write_image`` per image (png: the mask; yolo: the label and the image, a
    relative link, or with ``job.copy_images`` or where links are refused a copy; coco: the record, kept).

    Parameters
    ----------
    job : pipeline.labeling.reading.LabelJob
        An opened job.
    fmts : tuple of str
        The formats written: names in :data:`~pipeline.labeling.formats.LABEL_FORMATS`.
    votes : iterable
        (voted, c, a, n_valid, h) per image, in the job's order (:func:`pipeline.labeling.run.folder_votes`).

    Returns
    -------
    Votes
        The per-image values.
    """
    import cv2  # opencv: heavy, imported where used

    n = len(job.files)
    rng = np.random.default_rng(int(job.data_cfg["seed"]))
    sheet_rows = set(sample_for_sheet(pd.DataFrame({"split": ["train"] * n, "group": ["label"] * n}),
                                      int(job.data_cfg["contact_sheet_images"]), int(rng.integers(2**31))).tolist())
    v = Votes(np.zeros(n), np.zeros(n), np.zeros(n, np.int64), np.zeros(n, np.int64), np.zeros(n),
              {name: [] for name in fmts})
    # file by file, never a folder swapped in whole: what label did not write there stays
    for row, (voted, c, a, n_valid, h) in enumerate(votes):
        v.c[row], v.a[row], v.n_valid[row], v.h[row] = c, a, n_valid, h
        hh, ww = job.sizes[row]
        full = cv2.resize(voted.astype(np.uint8), (ww, hh), interpolation=cv2.INTER_NEAREST) > 0
        v.pixels[row] = int(np.count_nonzero(full))
        for name in fmts:
            v.per_format[name].append(LABEL_FORMATS[name].write_image(job, row, full))
        if row in sheet_rows:
            v.sheet[row] = (load_rgb(job.files[row], job.size, job.cache, max_pixels=job.data_cfg["max_pixels"],
                                     bit_depth=job.data_cfg["bit_depth"]).array, voted)
    return v


def write_outputs(job: LabelJob, fmts: tuple[str, ...], v: Votes, gates: Gates, record: dict) -> pd.DataFrame:
    """Write each format's finishing files, the tables, the contact sheet (captioned with g), skipped.csv, label.json.

    Each format's ``LabelFormat.finish`` (coco: coco.json; yolo: its lists, data.yaml and README.txt) runs
    first.  Label's files of an earlier run that this one does not write are removed before the record; the
    record, written last, holds ``record``, the outputs and their sha256 (links to the inputs left out).

    Parameters
    ----------
    job : pipeline.labeling.reading.LabelJob
        The job.
    fmts : tuple of str
        The formats written: names in :data:`~pipeline.labeling.formats.LABEL_FORMATS`.
    v : Votes
        From :func:`write_votes`.
    gates : pipeline.pseudo_labels.Gates
        The gates.
    record : dict
        label.json's content besides checksums and outputs.

    Returns
    -------
    pandas.DataFrame
        The table, one row per image.
    """
    out, g = job.out, gates.factors.g
    table = pd.DataFrame({
        "image_id": job.ids, "file": [f.relative_to(job.root).as_posix() for f in job.files],
        "width": [s[1] for s in job.sizes], "height": [s[0] for s in job.sizes],
        "n_valid": v.n_valid.astype(np.int16), **gate_columns(v.c, v.a, gates), "h": v.h, "mask_pixels": v.pixels})
    table["teacher_backend"] = job.tcfg["backend"]
    table["simulator"] = job.simulated
    for name in fmts:
        LABEL_FORMATS[name].finish(job, v.per_format[name], table)
    _save(out / OUTPUTS["table"], lambda tmp: table.to_parquet(tmp, index=False))
    _save(out / OUTPUTS["csv"], lambda tmp: table.to_csv(tmp, index=False, float_format="%.6g"))
    tiles = [tile(img, voted, f"{job.ids[r]} g={g[r]:.2f}", max(job.size, 192)) for r, (img, voted) in
             sorted(v.sheet.items())]
    write_png(out / OUTPUTS["sheet"], contact_sheet(tiles, columns=4))
    write_skipped_csv(out / OUTPUTS["skipped"], job.policy.rows())  # header only when nothing was skipped
    removed = remove_stale(out, job.previous - {OUTPUTS["record"]}, job.targets)
    if removed:
        log.info("label: removed %d file(s) an earlier label run wrote that this run does not (first: %s)",
                 len(removed), removed[0])
    files = [(rel, out / rel) for rel in job.targets]
    sums = {rel: hashlib.sha256(p.read_bytes()).hexdigest() for rel, p in files if p.is_file() and not p.is_symlink()}
    write_json(out / OUTPUTS["record"], {**record, "checksums": sums, WRITTEN_BY: signature("label"),
                                         RECORD_OUTPUTS: sorted({*job.targets, OUTPUTS["record"]})})
    return table
