"""Stage corrections (only when params ``review.corrections`` is set): the corrections artifact checked
against this run and at the working resolution -> corrected.zarr, for ``review.mode``."""

from __future__ import annotations

import click

from pipeline import catalog
from pipeline.artifacts.store import open_artifact
from pipeline.catalog import ARTIFACTS_DIR
from pipeline.runtime.errors import InputError
from pipeline.params import get_path
from pipeline.review.apply import CORRECTIONS, MODE_KEY, corrected_masks, write_corrected
from stages._common import stage_command, stage_context


@stage_command("corrections")
@click.option("--corrections", "corrections_path", default=None,
              help="the corrections artifact [default: params review.corrections]")
@click.option("--artifacts", default=ARTIFACTS_DIR, show_default=True, type=click.Path(file_okay=False))
@click.option("--out", default=catalog.dvc_path("corrected"), show_default=True, help="corrected.zarr output")
def main(params, device, corrections_path, artifacts, out):
    """Check the corrected masks against this run and write them at the working resolution for review.mode."""
    corrections_path = corrections_path or get_path(params, "review.corrections")
    if not corrections_path:
        raise InputError("{}: none given and params review.corrections is null", CORRECTIONS(None))
    art = open_artifact(corrections_path, "corrections")
    manifest = open_artifact(catalog.path("manifest", artifacts), "manifest")
    images = open_artifact(catalog.path("images", artifacts), "images")
    mode = get_path(params, MODE_KEY)
    ids, rows, masks = corrected_masks(art, manifest, int(images["image"].shape[1]), mode,
                                       get_path(params, "data.source"))
    meta = stage_context("corrections", __file__, params).meta("corrected", [art, manifest, images])
    write_corrected(out, ids, rows, masks, mode, meta)
    click.echo(f"corrections: {len(ids)} corrected training images, mode {mode} -> {out}", err=True)


if __name__ == "__main__":
    main()
