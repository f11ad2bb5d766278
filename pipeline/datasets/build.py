"""Assemble a dataset for the ``prepare`` stage.

Source rows (the synthetic benchmark rendered, or a real dataset listed) -> (checked by
:func:`pipeline.datasets.manifest.check_manifest`) every file decoded once, a row's files by one
:func:`pipeline.datasets.loading.load_row` call (under the bad-input policy, into the decode cache)
-> working-resolution arrays.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Iterator

import numpy as np
import pandas as pd

from pipeline.artifacts.atomic import atomic_path, png_bytes
from pipeline.catalog import output_file
from pipeline.datasets import adapters
from pipeline.datasets import synthetic as syn
from pipeline.datasets.loading import BadFileError, DecodeCache, Loaded, has_file, load_row
from pipeline.datasets.manifest import BadInputPolicy, DatasetSpec
from pipeline.datasets.params import FrameSettings
from pipeline.params import SPLITS
from pipeline.runtime.errors import InputError
from pipeline.runtime.progress import progress

__all__ = ["source", "synthetic_source", "decode_rows", "iter_arrays"]

log = logging.getLogger(__name__)

SYNTHETIC_DIR = "synthetic"


def synthetic_source(cfg: dict, out_dir: str | Path) -> DatasetSpec:
    """Render the synthetic benchmark into ``<out_dir>/synthetic`` and list it.

    Parameters
    ----------
    cfg : dict
        The validated ``data:`` section (``resolution``, ``seed`` and the ``synthetic`` knobs).
    out_dir : str or Path
        The artifacts folder; its ``synthetic`` folder is replaced whole.

    Returns
    -------
    DatasetSpec
        The rows (one per view, with its background, hard case and area fraction) and the plan as protocol.
    """
    size, seed = int(cfg["resolution"]), int(cfg["seed"])
    syn_cfg = cfg["synthetic"]
    plan = syn.synthetic_plan(syn_cfg)
    opts = syn.sampling_options(syn_cfg)
    final = Path(out_dir) / SYNTHETIC_DIR
    rows = []
    total = sum(p.views for p in plan)
    with atomic_path(final, is_dir=True) as tmp, progress(total=total, desc="render synthetic") as bar:
        for sub in ("images", "masks", "parts"):
            (tmp / sub).mkdir()
        for sc in plan:
            model = syn.make_spacecraft(sc.name, seed)
            for v in range(sc.views):
                view = syn.generate_view(model, v, size, seed, opts)
                iid = f"{sc.name}_v{v:03d}"
                files = {sub: png_bytes(arr, iid, compression=1)  # fast: the decode pass reads them back once
                         for sub, arr in (("images", view.image), ("masks", view.mask.astype(np.uint8) * 255),
                                          ("parts", view.parts))}
                for sub, data in files.items():
                    (tmp / sub / f"{iid}.png").write_bytes(data)
                rows.append(adapters.row(iid, "synthetic", "synthetic", sc.split, sc.group, sc.name,
                                         *(final / sub / f"{iid}.png" for sub in files), view_index=v,
                                         background=view.background, hard_case=view.hard_case,
                                         area_fraction=view.area_fraction))
                bar.update(1)
    return DatasetSpec(rows=pd.DataFrame(rows), protocol={"name": "synthetic", "plan": [vars(p) for p in plan]})


def source(cfg: dict, out_dir: str | Path, policy: BadInputPolicy) -> DatasetSpec:
    """List the rows of ``data.source``: the synthetic benchmark rendered, or a real dataset's rows.

    A real dataset's rows come from :func:`pipeline.datasets.adapters.build_source`, and ``<out_dir>/synthetic``
    (a DVC output) is replaced by a note, so no stale synthetic files survive a switch of source.

    Parameters
    ----------
    cfg : dict
        The validated ``data:`` section.
    out_dir : str or Path
        The artifacts folder: its ``synthetic`` folder holds the rendered files, or the note.
    policy : BadInputPolicy
        Where a scanning source reports unusable entries.

    Returns
    -------
    DatasetSpec
        The source's rows and reading rules.
    """
    if cfg["source"] == "synthetic":
        return synthetic_source(cfg, out_dir)
    spec = adapters.build_source(cfg, policy)
    with atomic_path(Path(out_dir) / SYNTHETIC_DIR, is_dir=True) as tmp:
        (tmp / output_file("synthetic_files", "readme")).write_text(
            f"data.source={cfg['source']}: the synthetic benchmark was not generated; the manifest points "
            f"into {cfg['root']}\n")
    return spec


def decode_rows(rows: pd.DataFrame, spec: DatasetSpec, frames: FrameSettings, size: int, cache: DecodeCache | None,
                policy: BadInputPolicy) -> pd.DataFrame:
    """Decode every file once (into the cache) and fill the width, height and sha256 columns.

    A row with a bad file, or a mask or part file of another size than its image, goes through the policy, which
    lists its other files as not used (:meth:`BadInputPolicy.report_error`).

    Parameters
    ----------
    rows : pandas.DataFrame
        The checked manifest rows (:func:`check_manifest`).
    spec : DatasetSpec
        The source's reading rules (mask threshold, part colours).
    frames : FrameSettings
        How a frame file is read (``data.bit_depth``, ``data.letterbox``, ``data.max_pixels``).
    size : int
        The working resolution (``data.resolution``).
    cache : DecodeCache or None
        The decode cache (None: none).
    policy : BadInputPolicy
        Refuses a bad file or lists it.

    Returns
    -------
    pandas.DataFrame
        The rows kept, with ``width``, ``height`` (as displayed) and ``sha256`` (of the pixels as shown).

    Raises
    ------
    BadFileError
        A mask or part file whose size differs from its image's, when the policy refuses it.
    InputError
        When no image is left, or a bad file the policy refuses.
    """
    kept: dict[int, Loaded] = {}   # row -> its image
    for i, r in enumerate(progress(rows.itertuples(index=False), total=len(rows), desc="decode")):
        try:
            img = load_row(r.image_path, r.mask_path, r.part_path, size, cache, frames, spec.mask_threshold,
                           spec.part_colors)[0]
        except BadFileError as e:  # the policy also lists the row's other files as not used
            policy.report_error(r.image_id, e, [f for f in (r.image_path, r.mask_path, r.part_path) if has_file(f)])
            continue
        kept[i] = img
    out = rows.iloc[list(kept)].reset_index(drop=True).copy()
    out["width"] = np.asarray([im.native_hw[1] for im in kept.values()], np.int64)
    out["height"] = np.asarray([im.native_hw[0] for im in kept.values()], np.int64)
    out["sha256"] = [im.content_sha256 for im in kept.values()]  # an EXIF-turned file: its pixels as shown
    for col in ("mask_path", "part_path"):
        out[col] = [p if has_file(p) else None for p in out[col]]
    if out.empty:
        raise InputError("no usable images left after skipping bad files (see the skipped-files table)")
    for split in SPLITS:
        if not (out["split"] == split).any():
            log.warning("split %r has no images", split)
    return out


def iter_arrays(rows: pd.DataFrame, spec: DatasetSpec, frames: FrameSettings, size: int, cache: DecodeCache | None
                ) -> Iterator[tuple[int, np.ndarray, np.ndarray | None, np.ndarray | None]]:
    """Read each row's arrays at the working resolution, in manifest order.

    Parameters
    ----------
    rows : pandas.DataFrame
        Decoded manifest rows (:func:`decode_rows`).
    spec : DatasetSpec
        The source's reading rules.
    frames : FrameSettings
        How a frame file is read.
    size : int
        The working resolution S.
    cache : DecodeCache or None
        The decode cache (None: none).

    Yields
    ------
    tuple
        ``(row index, image uint8 [S,S,3], mask bool [S,S] or None, parts uint8 [S,S] or None)``.
    """
    for i, r in enumerate(rows.itertuples(index=False)):
        files = load_row(r.image_path, r.mask_path, r.part_path, size, cache, frames, spec.mask_threshold,
                         spec.part_colors)
        yield i, *(None if f is None else f.array for f in files)
