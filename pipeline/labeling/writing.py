"""The files ``geodistill label`` writes under ``out`` (their names: :data:`OUTPUTS`; the layout is in
:mod:`pipeline.labeling.run`'s docstring): per image as it is voted (PNG mask, YOLO label and image), then
the tables, COCO, contact sheet, skipped.csv and the record, each written atomically."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import shutil
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd

from pipeline.artifacts.atomic import atomic_path, write_json
from pipeline.catalog import output_file, output_names
from pipeline.datasets.contact_sheet import contact_sheet, sample_for_sheet, tile
from pipeline.datasets.loading import load_rgb
from pipeline.deploy.files import write_png, write_skipped_csv
from pipeline.geometry import area_ratios, foreground_agreement
from pipeline.labeling.formats import (coco_annotation, coco_document, yolo_data_yaml, yolo_image_list,
                                       yolo_lines, yolo_readme, yolo_split)
from pipeline.artifacts.ownership import OUTPUTS as RECORD_OUTPUTS
from pipeline.artifacts.ownership import WRITTEN_BY, owned_outputs, remove_stale, signature
from pipeline.runtime.progress import progress
from pipeline.pseudo_labels import Gates, gate_columns, vote_block

log = logging.getLogger("pipeline.labeling.run")  # label's one logger: callers listen to it

FORMATS = ("png", "coco", "yolo")
#: the files and folders written under ``out`` (pipeline.catalog.OUTPUT_FILES)
OUTPUTS = output_names("label")
#: yolo/'s image lists: training, then validation (pipeline.labeling.formats.yolo_split)
YOLO_LISTS = (output_file("label_yolo", "train"), output_file("label_yolo", "val"))
YOLO_DATA, YOLO_README = output_file("label_yolo", "data"), output_file("label_yolo", "readme")
#: the outputs written whatever the formats (label.json lists them and the files of each format,
#: :func:`label_targets`; pipeline.artifacts.ownership); the caches under .cache/ only add files
ALWAYS = tuple(OUTPUTS[k] for k in ("table", "csv", "sheet", "skipped"))
SIMULATOR_NOTE = ("teacher.backend=simulated is a SIMULATOR of foundation-model errors that reads the "
                  "reference masks given with --reference-masks; these are not a real teacher's labels")


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
        out += [f"{OUTPUTS['yolo']}/{name}" for name in (YOLO_DATA, *lists, YOLO_README)]
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
    for name, text in ((YOLO_DATA, yolo_data_yaml(len(train), len(val), seed)),
                       (YOLO_README, yolo_readme(len(train), len(val), seed, copies))):
        with atomic_path(yolo_dir / name) as tmp:
            tmp.write_text(text)


@dataclasses.dataclass
class Votes:
    """Per-image results of :func:`vote_and_export`: the gate inputs c (eq:foreground-agreement), a
    (eq:pseudo-area) and n_valid, the prompt disagreement h, the mask's pixels at the image's own size,
    the COCO annotations and the contact sheet's (image, voted) pairs."""

    c: np.ndarray
    a: np.ndarray
    n_valid: np.ndarray
    pixels: np.ndarray
    h: np.ndarray
    annotations: list = dataclasses.field(default_factory=list)
    sheet: dict = dataclasses.field(default_factory=dict)


def vote_and_export(job, runner, fmts: tuple[str, ...], vote_threshold: float, copy_images: bool = False) -> Votes:
    """The consensus stage's vote (:func:`pipeline.pseudo_labels.vote_block`) of each image's teacher
    answers, written as soon as it exists at the image's own size (PNG; YOLO label, and image as a
    relative link or with ``copy_images`` a copy), with the gate inputs and COCO annotations collected.
    ``job``: a :class:`pipeline.labeling.reading.LabelJob` after its files were read."""
    import cv2  # opencv: heavy, imported where used

    n, out = len(job.files), job.out
    rng = np.random.default_rng(int(job.data_cfg["seed"]))
    sheet_rows = set(sample_for_sheet(pd.DataFrame({"split": ["train"] * n, "group": ["label"] * n}),
                                      int(job.data_cfg["contact_sheet_images"]), int(rng.integers(2**31))).tolist())
    v = Votes(np.zeros(n), np.zeros(n), np.zeros(n, np.int64), np.zeros(n, np.int64), np.zeros(n))
    # file by file, never a folder swapped in whole: what label did not write there stays (pipeline.artifacts.ownership)
    masks_dir, yolo_dir = out / OUTPUTS["masks"], out / OUTPUTS["yolo"]
    for row in progress(range(n), desc="label: vote + export", unit="img"):
        masks, scores, _, _ = runner.answers(row)
        cons, h = vote_block(masks[None], scores[None], vote_threshold)  # a block of one image
        v.c[row], v.a[row] = foreground_agreement(cons.agreement, cons.voted)[0], area_ratios(cons.voted)[0]
        v.n_valid[row], v.h[row], voted = cons.n_valid[0], h[0], cons.voted[0]
        hh, ww = job.sizes[row]
        full = cv2.resize(voted.astype(np.uint8), (ww, hh), interpolation=cv2.INTER_NEAREST) > 0
        v.pixels[row] = int(np.count_nonzero(full))
        if "png" in fmts:
            write_png(masks_dir / f"{job.ids[row]}.png", full.astype(np.uint8) * 255)
        if "coco" in fmts:
            v.annotations.append(coco_annotation(full, row + 1, row + 1))
        if "yolo" in fmts:
            with atomic_path(yolo_dir / "labels" / f"{job.ids[row]}.txt") as dst:
                dst.write_text("".join(line + "\n" for line in yolo_lines(full)))
            _link_or_copy(job.files[row], yolo_dir / "images" / job.files[row].relative_to(job.root), copy_images)
        if row in sheet_rows:
            v.sheet[row] = (load_rgb(job.files[row], job.size, job.cache, max_pixels=job.data_cfg["max_pixels"],
                                     bit_depth=job.data_cfg.get("bit_depth", "auto")).array, voted)
    if "yolo" in fmts:
        _write_yolo_dataset(yolo_dir, [f.relative_to(job.root).as_posix() for f in job.files], job.ids,
                            int(job.data_cfg["seed"]), copy_images)
    return v


def _write_coco(job, table: pd.DataFrame, v: Votes, g: np.ndarray) -> None:
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


def write_outputs(job, fmts: tuple[str, ...], v: Votes, gates: Gates, record: dict) -> pd.DataFrame:
    """After the vote: the table (one row per image: the gate columns of the gates table, h, sizes), COCO,
    the contact sheet (captioned with g), skipped.csv, the removal of label's own files of an earlier
    run that this one does not write (``job.previous``), and last the record label.json (``record`` plus
    the outputs and their checksums).  Returns the table."""
    out, g = job.out, gates.factors.g
    table = pd.DataFrame({
        "image_id": job.ids, "file": [f.relative_to(job.root).as_posix() for f in job.files],
        "width": [s[1] for s in job.sizes], "height": [s[0] for s in job.sizes],
        "n_valid": v.n_valid.astype(np.int16), **gate_columns(v.c, v.a, gates), "h": v.h, "mask_pixels": v.pixels})
    table["teacher_backend"] = job.tcfg["backend"]
    table["simulator"] = job.simulated
    _write_table(out, table)
    if "coco" in fmts:
        _write_coco(job, table, v, g)
    tiles = [tile(img, voted, f"{job.ids[r]} g={g[r]:.2f}", max(job.size, 192)) for r, (img, voted) in
             sorted(v.sheet.items())]
    write_png(out / OUTPUTS["sheet"], contact_sheet(tiles, columns=4))
    write_skipped_csv(out / OUTPUTS["skipped"], job.policy.rows())  # header only when nothing was skipped
    current = label_targets(job.root, job.files, job.ids, fmts)
    removed = remove_stale(out, job.previous - {OUTPUTS["record"]}, current)
    if removed:
        log.info("label: removed %d file(s) an earlier label run wrote that this run does not (first: %s)",
                 len(removed), removed[0])
    write_json(out / OUTPUTS["record"], {
        **record, "checksums": file_checksums(out, current),
        WRITTEN_BY: signature("label"), RECORD_OUTPUTS: sorted({*current, OUTPUTS["record"]})})
    return table
