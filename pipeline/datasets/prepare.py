"""The prepare stage's work without the CLI: a dataset to the prepared artifacts.

It writes manifest.parquet, images.zarr, reference.zarr, skipped_files.parquet and the contact sheet, with
eq:spacecraft-disjoint checked where the protocol requires it.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from pipeline import catalog
from pipeline.artifacts.atomic import atomic_path, png_bytes
from pipeline.artifacts.lineage import Meta
from pipeline.artifacts.store import ZarrWriter, write_parquet
from pipeline.datasets import build
from pipeline.datasets.contact_sheet import contact_sheet, sample_for_sheet, tile
from pipeline.datasets.loading import DecodeCache, content_digest, decode_rows, iter_arrays
from pipeline.datasets.manifest import BadInputPolicy, check_manifest
from pipeline.datasets.params import FrameSettings, fingerprint_params
from pipeline.datasets.synthetic import PART_NAMES
from pipeline.runtime.progress import progress

__all__ = ["prepare"]

#: the reference artifact's note: what its masks may be used for
REFERENCE_NOTE = ("reference masks: checkpoint selection, calibration, evaluation and the simulated teacher only "
                  "-- never a training loss")


@dataclasses.dataclass
class Prepared:
    """What :func:`prepare` wrote: the manifest rows, the bad-file policy's record and the decode cache."""

    rows: pd.DataFrame
    policy: BadInputPolicy
    cache: DecodeCache


def prepare(cfg: dict, out: str | Path, meta: Callable[..., Meta]) -> Prepared:
    """Write every prepare artifact under ``out`` from the validated ``data:`` section ``cfg``.

    Parameters
    ----------
    cfg : dict
        The validated ``data:`` section.
    out : str or Path
        The artifacts folder.
    meta : Callable[..., Meta]
        Stamps each artifact: called as ``meta(schema, params=..., **extra)`` with params = the data params, the
        protocol applied and the files' content digest.

    Returns
    -------
    Prepared
        The manifest rows, the bad-file policy's record and the decode cache.
    """
    out = Path(out)
    size = cfg["resolution"]
    frames = FrameSettings.from_params(cfg)  # data.bit_depth, letterbox, max_pixels: read here once, for the reader
    fp_data = fingerprint_params(cfg)
    spec = build.source(cfg, out)
    policy = BadInputPolicy(cfg["skip_bad"])
    rows = check_manifest(spec, policy, where=f"data.source={cfg['source']}")
    cache = DecodeCache(cfg["cache_dir"])
    rows = decode_rows(rows, spec, frames, size, cache, policy, bar=progress)
    fp_params = {"data": fp_data, "protocol": spec.protocol, "content_sha256": content_digest(rows)}
    arrays = iter_arrays(rows, spec, frames, size, cache)  # a generator: each row is read as it is written
    ids = rows["image_id"].tolist()
    n = len(rows)
    has_parts = rows["part_path"].notna().to_numpy()

    with ZarrWriter(catalog.path("images", out), meta("images", params=fp_params)) as wi, \
            ZarrWriter(catalog.path("reference", out), meta("reference", params=fp_params)) as wr:
        wi.create("image", (n, size, size, 3), np.uint8)
        wr.create("mask", (n, size, size), bool)
        wr.create("has_mask", (n,), bool)
        if has_parts.any():
            wr.create("parts", (n, size, size), np.uint8)
            wr.create("has_parts", (n,), bool)
        for i, img, mask, parts in progress(arrays, total=n, desc="write arrays"):
            wi.write("image", i, img)
            wr.write("mask", i, mask if mask is not None else np.zeros((size, size), bool))
            wr.write("has_mask", i, mask is not None)
            if has_parts.any():
                wr.write("parts", i, parts if parts is not None else np.zeros((size, size), np.uint8))
                wr.write("has_parts", i, parts is not None)
        wi.attrs.update(image_ids=ids, resolution=size)
        wr.attrs.update(image_ids=ids, resolution=size, part_names=list(PART_NAMES), note=REFERENCE_NOTE)

    write_parquet(catalog.path("skipped_files", out), policy.table(), meta("skipped_files", params=fp_params))
    write_parquet(catalog.path("manifest", out), rows,
                  meta("manifest", params=fp_params, protocol=spec.protocol, resolution=size,
                       spacecraft_disjoint=spec.spacecraft_disjoint))
    write_contact_sheet(catalog.path("contact_sheet", out), rows, spec, frames, cfg, cache)
    return Prepared(rows, policy, cache)


def write_contact_sheet(path: Path, rows: pd.DataFrame, spec, frames: FrameSettings, cfg: dict,
                        cache: DecodeCache) -> None:
    """Write the contact sheet PNG: ``data.contact_sheet_images`` seeded picks, each with its mask outline."""
    size = cfg["resolution"]
    pick = sample_for_sheet(rows, cfg["contact_sheet_images"], cfg["seed"])
    tsize = max(size, 192)
    tiles = []
    for i in pick:
        r = rows.iloc[int(i)]
        img, mask, _ = next(iter_arrays(rows.iloc[[int(i)]], spec, frames, size, cache))[1:]
        tiles.append(tile(img, mask, f"{r['group']} {r['spacecraft']}", tsize))
    # atomic_path, not write_png: a stage's output, whose killed temporaries the next run removes
    with atomic_path(path) as tmp:
        tmp.write_bytes(png_bytes(contact_sheet(tiles, columns=4), path))
