"""Whose file is it: no command deletes or replaces a file it did not write (issue 23).

The user tools (``label``, ``distill``, ``segment``, ``export``, ``profile``) each recognise their own
earlier output by a *record*:

* ``label``, ``segment`` and ``distill`` write a JSON record file into their output folder
  (``label.json``, ``segment.json``, ``distill.json``) BEFORE any other output, holding
  ``written_by: "geodistill <command>"`` and ``outputs``: the paths (relative to the folder, posix)
  the command writes there.  A rerun may replace exactly those paths -- so a rerun into the same
  folder replaces or resumes its own output, and a run killed half-way is recognised too;
* ``export``'s bundle folder is its own when it holds a deploy artifact's ``meta.json``;
* ``profile``'s params file is its own when it starts with the generated header.

Any other existing path in the way is refused before anything is written: one line naming it (exit
code 2, :class:`~pipeline.errors.InputError`).  ``--overwrite`` is the user's explicit yes.  The
policy is written here once; docs/own-data.md describes it for users.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Iterable, Mapping

from pipeline.artifacts import write_json
from pipeline.errors import OUT, OVERWRITE, InputError, Option, literal

WRITTEN_BY = "written_by"
OUTPUTS = "outputs"


def signature(command: str) -> str:
    """The ``written_by`` value of ``command``'s records: ``"geodistill <command>"``."""
    return f"geodistill {command}"


def read_record(path: str | Path, command: str, legacy_keys: Iterable[str] = ()) -> dict | None:
    """The record at ``path`` when ``command`` wrote it, else None (missing, unreadable, not JSON, or
    someone else's file).  ``legacy_keys``: a record written before records had ``written_by`` is
    recognised by holding all of these keys (empty: not recognised)."""
    p = Path(path)
    try:
        doc = json.loads(p.read_text())
    except (OSError, ValueError, UnicodeDecodeError):
        return None
    if not isinstance(doc, dict):
        return None
    if doc.get(WRITTEN_BY) == signature(command):
        return doc
    legacy = tuple(legacy_keys)
    if legacy and WRITTEN_BY not in doc and all(k in doc for k in legacy):
        return doc
    return None


def owned_outputs(out: str | Path, record: str, command: str, *, legacy_outputs: Iterable[str] = (),
                  legacy_keys: Iterable[str] = ()) -> set[str]:
    """The relative paths under ``out`` that ``command``'s record ``out/record`` lists (the record
    itself included); empty when there is no record of ``command``.  A legacy record (no
    ``outputs`` list) owns ``legacy_outputs``."""
    doc = read_record(Path(out) / record, command, legacy_keys)
    if doc is None:
        return set()
    listed = doc.get(OUTPUTS)
    names = {str(x) for x in listed} if isinstance(listed, list) else set(legacy_outputs)
    return names | {record}


def _option(option: str | Option) -> Option:
    """An option given by its flag alone (commands without a Python API) as an :class:`Option`."""
    return option if isinstance(option, Option) else Option(option, option.lstrip("-").replace("-", "_"))


def refuse_unowned(paths: Iterable[str | Path], owned: Iterable[str | Path], *, command: str, option: str | Option,
                   where: str | Path, why: str, overwrite: bool) -> None:
    """InputError naming the first of ``paths`` that exists (a broken link counts) and is not in
    ``owned``, unless ``overwrite`` (the user's explicit yes).  ``why``: how ``command`` recognises its
    own output (e.g. "not listed in its label.json"); ``option``/``where``: the option and value that
    named the output location (``--out run/``)."""
    if overwrite:
        return
    mine = {Path(p).absolute() for p in owned}
    for p in paths:
        p = Path(p)
        if (p.is_symlink() or p.exists()) and p.absolute() not in mine:
            opt = _option(option)  # named in the caller's terms (pipeline.errors)
            raise InputError(f"{{}}: {literal(p)} exists and was not written by {literal(signature(command))} "
                             f"({literal(why)}); pass {{}} to replace it, or choose another {{}}",
                             opt(where), OVERWRITE, opt)


def check_outputs(out: str | Path, targets: Iterable[str], record: str, command: str, *, overwrite: bool,
                  option: str | Option = OUT, legacy_outputs: Iterable[str] = (), legacy_keys: Iterable[str] = ()) -> None:
    """Refuse (InputError, one line) before anything is written when ``out`` is a file, or when one of
    ``targets`` (paths relative to ``out``; the record is added) exists under ``out`` and the record
    of ``command`` there does not list it (:func:`refuse_unowned`)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError("{}: is a file, not a folder", _option(option)(out))
    own = owned_outputs(out, record, command, legacy_outputs=legacy_outputs, legacy_keys=legacy_keys)
    names = list(dict.fromkeys([*targets, record]))
    refuse_unowned([out / t for t in names], [out / t for t in own], command=command, option=option, where=out,
                   why=f"not listed in a {record} of {signature(command)} there", overwrite=overwrite)


def record_fields(out: str | Path, record: str, command: str, targets: Iterable[str],
                  legacy_outputs: Iterable[str] = (), legacy_keys: Iterable[str] = ()) -> dict:
    """``written_by`` and ``outputs`` (what the record listed before, plus ``targets`` and the record):
    merge them into every version of the record a command writes."""
    own = owned_outputs(out, record, command, legacy_outputs=legacy_outputs, legacy_keys=legacy_keys)
    return {WRITTEN_BY: signature(command), OUTPUTS: sorted(own | set(targets) | {record})}


def claim_outputs(out: str | Path, targets: Iterable[str], record: str, command: str,
                  fields: Mapping | None = None, **legacy) -> dict:
    """Write the record ``out/record`` listing ``targets`` (and what it listed before) BEFORE the
    outputs themselves, so that a run killed half-way is recognised as the command's own by the
    next run; ``fields``: the command's other record fields.  Returns the record written."""
    doc = {**dict(fields or {}), **record_fields(out, record, command, targets, **legacy)}
    write_json(Path(out) / record, doc)
    return doc
