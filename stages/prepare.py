"""Stage prepare: dataset -> manifest.parquet, images.zarr, reference.zarr, skipped_files.parquet, contact sheet."""

from __future__ import annotations

import logging

import click

from pipeline import catalog
from pipeline.catalog import ARTIFACTS_DIR
from pipeline.datasets.params import check_data_params
from pipeline.params import SOURCES, section
from pipeline.datasets.prepare import prepare
from stages._common import stage_command, stage_context

log = logging.getLogger("geodistill.prepare")


@stage_command("prepare")
@click.option("--out-dir", default=ARTIFACTS_DIR, show_default=True, type=click.Path(file_okay=False))
@click.option("--source", default=None, help=f"override data.source ({'|'.join(SOURCES)})")
@click.option("--root", default=None, help="override data.root (dataset root for real sources)")
@click.option("--protocol", default=None, help="override data.protocol (protocol YAML)")
@click.option("--skip-bad", is_flag=True, help="leave bad files out (recorded in skipped_files.parquet)")
def main(params, device, out_dir, source, root, protocol, skip_bad):
    """Build the manifest and working-resolution image/reference arrays (synthetic benchmark by default)."""
    given = {"source": source, "root": root, "protocol": protocol, "skip_bad": skip_bad or None}
    cfg = check_data_params({**section(params, "data"), **{k: v for k, v in given.items() if v is not None}})
    done = prepare(cfg, out_dir, stage_context("prepare", __file__, params).meta)
    if (line := done.policy.summary("prepare", catalog.path("skipped_files", out_dir))) is not None:
        click.echo(line, err=True)
    counts = done.rows.groupby(["split", "group"]).size().to_dict()
    log.info("prepared %d images (%s) at %dpx; skipped %d; decode cache hits %d misses %d",
             len(done.rows), ", ".join(f"{s}/{g}: {c}" for (s, g), c in counts.items()), cfg["resolution"],
             len(done.policy.skipped), done.cache.hits, done.cache.misses)


if __name__ == "__main__":
    main()
