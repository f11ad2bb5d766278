"""The files ``geodistill label`` writes under ``out``, each atomically.

Per image as its vote comes, then the tables, COCO, the contact sheet, skipped.csv, and last the record
label.json.
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
from pipeline.datasets.contact_sheet import contact_sheet, sample_for_sheet, tile
from pipeline.datasets.loading import load_rgb
from pipeline.datasets.manifest import write_skipped_csv
from pipeline.labeling.formats import (coco_annotation, coco_document, yolo_data_yaml, yolo_image_list,
                                       yolo_lines, yolo_readme, yolo_split)
from pipeline.labeling.reading import OUTPUTS, SIMULATOR_NOTE, YOLO_DATA, YOLO_LISTS, YOLO_README, LabelJob
from pipeline.pseudo_labels import Gates, gate_columns

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
    annotations : list
        The COCO records (None for an empty mask).
    sheet : dict
        Row -> (image, voted mask) of the contact sheet's sample.
    """

    c: np.ndarray
    a: np.ndarray
    n_valid: np.ndarray
    pixels: np.ndarray
    h: np.ndarray
    annotations: list = dataclasses.field(default_factory=list)
    sheet: dict = dataclasses.field(default_factory=dict)


def write_votes(job: LabelJob, fmts: tuple[str, ...], votes: Iterable, copy_images: bool = False) -> Votes:
    """Write each image's files as its vote comes, at the image's own size (nearest-neighbour resize).

    The PNG mask, the YOLO label and image (a relative link, or with ``copy_images`` or where links are refused a
    copy), then yolo/'s lists, data.yaml and README.txt.

    Parameters
    ----------
    job : pipeline.labeling.reading.LabelJob
        An opened job.
    fmts : tuple of str
        The formats written.
    votes : iterable
        (voted, c, a, n_valid, h) per image, in the job's order (:func:`pipeline.labeling.run.folder_votes`).
    copy_images : bool, optional
        yolo/images holds copies instead of relative links.

    Returns
    -------
    Votes
        The per-image values.
    """
    import cv2  # opencv: heavy, imported where used

    n, out, seed = len(job.files), job.out, int(job.data_cfg["seed"])
    rng = np.random.default_rng(seed)
    sheet_rows = set(sample_for_sheet(pd.DataFrame({"split": ["train"] * n, "group": ["label"] * n}),
                                      int(job.data_cfg["contact_sheet_images"]), int(rng.integers(2**31))).tolist())
    v = Votes(np.zeros(n), np.zeros(n), np.zeros(n, np.int64), np.zeros(n, np.int64), np.zeros(n))
    rels = [f.relative_to(job.root).as_posix() for f in job.files]
    # file by file, never a folder swapped in whole: what label did not write there stays
    masks_dir, yolo_dir = out / OUTPUTS["masks"], out / OUTPUTS["yolo"]
    for row, (voted, c, a, n_valid, h) in enumerate(votes):
        v.c[row], v.a[row], v.n_valid[row], v.h[row] = c, a, n_valid, h
        hh, ww = job.sizes[row]
        full = cv2.resize(voted.astype(np.uint8), (ww, hh), interpolation=cv2.INTER_NEAREST) > 0
        v.pixels[row] = int(np.count_nonzero(full))
        if "png" in fmts:
            write_png(masks_dir / f"{job.ids[row]}.png", full.astype(np.uint8) * 255)
        if "coco" in fmts:
            v.annotations.append(coco_annotation(full, row + 1, row + 1))
        if "yolo" in fmts:
            _link_or_copy(job.files[row], yolo_dir / "images" / rels[row], copy_images)
            _save(yolo_dir / "labels" / f"{job.ids[row]}.txt", "".join(line + "\n" for line in yolo_lines(full)))
        if row in sheet_rows:
            v.sheet[row] = (load_rgb(job.files[row], job.size, job.cache, max_pixels=job.data_cfg["max_pixels"],
                                     bit_depth=job.data_cfg["bit_depth"]).array, voted)
    if "yolo" in fmts:
        train, val = yolo_split(job.ids, seed)
        copies = copy_images or not (yolo_dir / "images" / rels[0]).is_symlink()
        for name, rows in zip(YOLO_LISTS, (train, val)):
            if rows:
                _save(yolo_dir / name, yolo_image_list([rels[i] for i in rows]))
        _save(yolo_dir / YOLO_DATA, yolo_data_yaml(len(train), len(val), seed))
        _save(yolo_dir / YOLO_README, yolo_readme(len(train), len(val), seed, copies))
    return v


def write_outputs(job: LabelJob, fmts: tuple[str, ...], v: Votes, gates: Gates, record: dict) -> pd.DataFrame:
    """Write the tables, COCO, the contact sheet (captioned with g), skipped.csv and last label.json.

    Label's files of an earlier run that this one does not write are removed before the record; the record holds
    ``record``, the outputs and their sha256 (links to the inputs left out).

    Parameters
    ----------
    job : pipeline.labeling.reading.LabelJob
        The job.
    fmts : tuple of str
        The formats written.
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
    if "coco" in fmts:
        images = [{"id": i + 1, "file_name": table["file"].iloc[i], "width": int(w), "height": int(h)}
                  for i, (h, w) in enumerate(job.sizes)]
        for i, ann in enumerate(v.annotations):
            if ann is not None:
                ann.update(gate=round(float(g[i]), 6), agreement=round(float(v.c[i]), 6))
        desc = "geodistill label: voted multi-prompt pseudo-masks" + (f" -- {SIMULATOR_NOTE}" if job.simulated else "")
        doc = coco_document(images, [x for x in v.annotations if x is not None], description=desc,
                            teacher_backend=job.tcfg["backend"], simulator=job.simulated)
        _save(out / OUTPUTS["coco"], json.dumps(doc, separators=(",", ":")))
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
