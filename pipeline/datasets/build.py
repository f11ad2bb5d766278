"""List a dataset's rows for the ``prepare`` stage: the synthetic benchmark rendered, or a real dataset's rows.

What follows is :func:`pipeline.datasets.manifest.check_manifest`, then
:func:`pipeline.datasets.loading.decode_rows` and :func:`pipeline.datasets.loading.iter_arrays`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.artifacts.atomic import atomic_path, png_bytes
from pipeline.catalog import output_file
from pipeline.datasets import adapters
from pipeline.datasets import synthetic as syn
from pipeline.datasets.manifest import DatasetSpec
from pipeline.runtime.progress import progress

__all__ = ["source", "synthetic_source"]

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


def source(cfg: dict, out_dir: str | Path) -> DatasetSpec:
    """List the rows of ``data.source``: the synthetic benchmark rendered, or a real dataset's rows.

    A real dataset's rows come from :func:`pipeline.datasets.adapters.build_source`, and ``<out_dir>/synthetic``
    (a DVC output) is replaced by a note, so no stale synthetic files survive a switch of source.

    Parameters
    ----------
    cfg : dict
        The validated ``data:`` section.
    out_dir : str or Path
        The artifacts folder: its ``synthetic`` folder holds the rendered files, or the note.

    Returns
    -------
    DatasetSpec
        The source's rows and reading rules.
    """
    if cfg["source"] == "synthetic":
        return synthetic_source(cfg, out_dir)
    spec = adapters.build_source(cfg)
    with atomic_path(Path(out_dir) / SYNTHETIC_DIR, is_dir=True) as tmp:
        (tmp / output_file("synthetic_files", "readme")).write_text(
            f"data.source={cfg['source']}: the synthetic benchmark was not generated; the manifest points "
            f"into {cfg['root']}\n")
    return spec
