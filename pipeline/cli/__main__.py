"""``python -m pipeline.cli``: the console script, under its own name."""

from pipeline.artifacts.lineage import PROGRAM
from pipeline.cli.main import main

main(prog_name=PROGRAM)
