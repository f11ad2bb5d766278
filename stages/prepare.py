"""Stage `prepare`: dataset -> manifest.parquet, images.zarr, reference.zarr, skipped_files.parquet, contact sheet.

Default source: the embedded synthetic spacecraft benchmark (PNG files under ``<out-dir>/synthetic``).
Real sources: ``--source spacesense|speedplus|tango|folder --root DIR [--protocol FILE]``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import click
import cv2
import numpy as np

from pipeline.catalog import ARTIFACTS_DIR
from pipeline.artifacts import ZarrWriter, atomic_path, write_parquet
from pipeline.datasets import build
from pipeline.datasets.contact_sheet import contact_sheet, sample_for_sheet, tile
from pipeline.datasets.loading import DecodeCache
from pipeline.datasets.manifest import BadInputPolicy
from pipeline.datasets.params import check_data_params, fingerprint_params
from pipeline.datasets.synthetic import PART_NAMES
from pipeline.params import section
from pipeline.progress import progress
from stages._common import stage_command, stage_context

log = logging.getLogger("geodistill.prepare")


@stage_command("prepare")
@click.option("--out-dir", default=ARTIFACTS_DIR, show_default=True, type=click.Path(file_okay=False))
@click.option("--source", default=None, help="override data.source (synthetic|spacesense|speedplus|tango|folder)")
@click.option("--root", default=None, help="override data.root (dataset root for real sources)")
@click.option("--protocol", default=None, help="override data.protocol (protocol YAML)")
@click.option("--skip-bad", is_flag=True, help="leave bad files out (recorded in skipped_files.parquet)")
def main(params, device, out_dir, source, root, protocol, skip_bad):
    """Build the manifest and working-resolution image/reference arrays (synthetic benchmark by default)."""
    cfg = section(params, "data")
    for key, value in (("source", source), ("root", root), ("protocol", protocol)):
        if value is not None:
            cfg[key] = value
    if skip_bad:
        cfg["skip_bad"] = True
    cfg = check_data_params(cfg)
    out = Path(out_dir)
    size = cfg["resolution"]
    cache = DecodeCache(cfg["cache_dir"])
    policy = BadInputPolicy(cfg["skip_bad"])

    spec = (build.synthetic_source(cfg, out, cache) if cfg["source"] == "synthetic"
            else build.real_source(cfg, policy, out))
    rows = build.check_manifest(spec, policy, where=f"data.source={cfg['source']}")
    rows = build.decode_rows(rows, spec, size, cache, policy)
    ctx = stage_context("prepare", __file__, params)
    # fingerprint: the data params, the protocol actually applied, and the selected files' content
    fp_params = {"data": fingerprint_params(cfg), "protocol": spec.protocol,
                 "content_sha256": build.content_digest(rows)}
    ids = rows["image_id"].tolist()
    n = len(rows)
    has_parts = rows["part_path"].notna().to_numpy()

    with ZarrWriter(out / "images.zarr", ctx.meta("images", params=fp_params)) as wi, \
            ZarrWriter(out / "reference.zarr", ctx.meta("reference", params=fp_params)) as wr:
        wi.create("image", (n, size, size, 3), np.uint8)
        wr.create("mask", (n, size, size), bool)
        wr.create("has_mask", (n,), bool)
        if has_parts.any():
            wr.create("parts", (n, size, size), np.uint8)
            wr.create("has_parts", (n,), bool)
        for i, img, mask, parts in progress(build.iter_arrays(rows, spec, size, cache), total=n, desc="write arrays"):
            wi.write("image", i, img)
            wr.write("mask", i, mask if mask is not None else np.zeros((size, size), bool))
            wr.write("has_mask", i, mask is not None)
            if has_parts.any():
                wr.write("parts", i, parts if parts is not None else np.zeros((size, size), np.uint8))
                wr.write("has_parts", i, parts is not None)
        wi.attrs.update(image_ids=ids, resolution=size)
        wr.attrs.update(image_ids=ids, resolution=size, part_names=list(PART_NAMES),
                        note="reference masks: checkpoint selection, calibration, evaluation and the "
                             "simulated teacher only -- never a training loss")

    write_parquet(out / "skipped_files.parquet", policy.table(),
                  ctx.meta("skipped_files", params=fp_params))
    write_parquet(out / "manifest.parquet", rows,
                  ctx.meta("manifest", params=fp_params, protocol=spec.protocol,
                           resolution=size, spacecraft_disjoint=spec.spacecraft_disjoint))

    pick = sample_for_sheet(rows, cfg["contact_sheet_images"], cfg["seed"])
    tsize = max(size, 192)
    tiles = []
    for i in pick:
        r = rows.iloc[int(i)]
        img, mask, _ = next(build.iter_arrays(rows.iloc[[int(i)]], spec, size, cache))[1:]
        tiles.append(tile(img, mask, f"{r['group']} {r['spacecraft']}"[:28], tsize))
    sheet = contact_sheet(tiles, columns=4)
    with atomic_path(out / "figures" / "contact_sheet.png") as tmp:
        ok, buf = cv2.imencode(".png", sheet[..., ::-1])
        tmp.write_bytes(buf.tobytes())

    if (line := policy.summary("prepare", out / "skipped_files.parquet")) is not None:
        click.echo(line, err=True)
    counts = rows.groupby(["split", "group"]).size().to_dict()
    log.info("prepared %d images (%s) at %dpx; skipped %d; decode cache hits %d misses %d",
             n, ", ".join(f"{s}/{g}: {c}" for (s, g), c in counts.items()), size,
             len(policy.skipped), cache.hits, cache.misses)


if __name__ == "__main__":
    main()
