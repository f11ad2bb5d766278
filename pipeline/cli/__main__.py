"""``python -m pipeline.cli``: the ``geodistill`` console script."""

from pipeline.cli.main import main

main(prog_name="geodistill")
