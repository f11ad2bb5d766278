"""``geodistill reproduce-check``: check that this run's student metrics reproduce the committed ones.

Those committed at ``--ref``, within :data:`pipeline.reproducibility.TOLERANCE`.  Exit 0 yes, 1 no, 2 bad input.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import click

from pipeline import catalog
from pipeline.catalog import ARTIFACTS_DIR
from pipeline.runtime.errors import InputError
from pipeline.reproducibility import TOLERANCE, compare_metrics, difference_table, reproduced
from pipeline.cli.conventions import one_line_errors

__all__ = ["main"]


def _git(args: list[str], cwd: Path) -> str:
    """Run ``git args`` in ``cwd`` and return its stdout; InputError when git fails."""
    try:
        out = subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True)
    except FileNotFoundError:
        raise InputError("git not found: the committed metrics are read with git") from None
    if out.returncode != 0:
        msg = (out.stderr.strip().splitlines() or ["failed"])[0]
        raise InputError(f"git {' '.join(args)}: {msg}")
    return out.stdout


def _parse(text: str, where: str) -> dict[str, float]:
    """Read a DVC metrics file's text, a JSON object of numbers; InputError naming ``where`` otherwise."""
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise InputError(f"{where}: not JSON ({e.msg})") from None
    if not isinstance(data, dict) or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                             for v in data.values()):
        raise InputError(f"{where}: expected a JSON object of numbers (a DVC metrics file)")
    return data


def committed_metrics(metrics_dir: Path, ref: str) -> dict[str, dict[str, float]]:
    """Read ``{<group>/<method>.json: metrics}`` of ``metrics_dir`` as committed at ``ref``."""
    top = Path(_git(["rev-parse", "--show-toplevel"], Path.cwd()).strip())
    try:
        rel = metrics_dir.resolve().relative_to(top.resolve()).as_posix()
    except ValueError:
        raise InputError(f"{metrics_dir}: not inside the git checkout {top}") from None
    names = _git(["ls-tree", "-r", "--name-only", ref, "--", rel], top).splitlines()
    files = [n for n in names if n.endswith(".json")]
    if not files:
        raise InputError(f"{ref}:{rel}: no committed student metrics to compare with")
    return {n[len(rel) + 1:]: _parse(_git(["show", f"{ref}:{n}"], top), f"{ref}:{n}") for n in files}


def fresh_metrics(metrics_dir: Path) -> dict[str, dict[str, float]]:
    """Read ``{<group>/<method>.json: metrics}`` of the files in ``metrics_dir`` ({} when it does not exist)."""
    if not metrics_dir.is_dir():
        return {}
    return {p.relative_to(metrics_dir).as_posix(): _parse(p.read_text(), str(p))
            for p in sorted(metrics_dir.rglob("*.json"))}


@click.command(name="reproduce-check")
@click.option("--ref", default="HEAD", show_default=True, help="the commit whose metrics are the reference")
@click.option("--artifacts", default=ARTIFACTS_DIR, show_default=True, type=click.Path(file_okay=False),
              help="artifacts directory of the run (the metrics lie beside it, pipeline.catalog)")
def main(ref, artifacts):
    """Compare this run's student metrics with the committed ones; exit 1 when one differs beyond tolerance."""
    metrics_dir = catalog.path("metrics_students", artifacts)
    with one_line_errors("reproduce-check"):
        committed, fresh = committed_metrics(metrics_dir, ref), fresh_metrics(metrics_dir)
    rows = compare_metrics(committed, fresh)
    tol = ", ".join(f"{k} {v}" for k, v in TOLERANCE.items())
    click.echo(f"Student metrics of this run ({metrics_dir}) against {ref} (tolerance: {tol})\n")
    click.echo(difference_table(rows))
    bad = [r for r in rows if r.status != "ok"]
    if reproduced(rows):
        click.echo(f"\nreproduce-check: all {len(rows)} metrics within tolerance")
        return
    click.echo(f"\nreproduce-check: FAILED: {len(bad)} of {len(rows)} metrics not reproduced", err=True)
    sys.exit(1)


if __name__ == "__main__":
    main()
