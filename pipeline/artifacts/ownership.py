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

The policy -- a command replaces only what it wrote, ``--overwrite`` or not -- is written here once
(docs/own-data.md describes it for users):

* a record lists the **files** the command wrote (``label`` and ``segment`` file by file; ``distill``
  its project files and the folders DVC fills); a rerun replaces, and (``label``) removes when this
  run no longer makes them, exactly the listed files (:func:`remove_stale`).  A folder listed by a
  record of an earlier version owns the files at the paths this run writes inside it, nothing else;
* a **file** the command did not write, where one of its outputs would go, is refused before anything
  is written: one line naming it (exit code 2, :class:`~pipeline.runtime.errors.InputError`) -- with
  ``--overwrite`` too, since the command can neither leave it in place nor replace it;
* a **folder** in the way that no record of the command claims (the user's ``masks/``) is refused
  unless ``--overwrite``: the user's yes to write the command's files into it;
* every other file in the output folders is **left in place** -- never deleted, never replaced
  (``export``, which swaps its bundle folder in whole, and ``review export``, which swaps its
  ``labelstudio/`` and ``cvat/``, refuse a foreign file inside them instead: :func:`refuse_foreign_files`).
"""

from __future__ import annotations

import json
from pathlib import Path, PurePosixPath
from typing import Iterable, Mapping

from pipeline.artifacts.atomic import write_json
from pipeline.runtime.errors import OUT, OVERWRITE, InputError, Option, literal

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


def owns(rel: str, own: Iterable[str]) -> bool:
    """Whether the relative path ``rel`` (posix) is owned by a record listing ``own``: listed itself,
    or inside a listed folder (records of earlier versions listed folders, not files)."""
    own = set(own)
    parts = PurePosixPath(rel).parts
    return any("/".join(parts[:i]) in own for i in range(1, len(parts) + 1))


def _refuse_file(p: Path, command: str, option: Option, where, why: str) -> None:
    raise InputError(f"{{}}: {literal(p)} exists and was not written by {literal(signature(command))} "
                     f"({literal(why)}); {{}} replaces only what {literal(signature(command))} wrote: move it "
                     f"away, or choose another {{}}", option(where), OVERWRITE, option)


def refuse_unowned(paths: Iterable[str | Path], owned: Iterable[str | Path], *, command: str, option: str | Option,
                   where: str | Path, why: str, overwrite: bool) -> None:
    """InputError naming the first of ``paths`` that exists (a broken link counts) and is not in
    ``owned`` (module docstring): a file -- or link -- always; a folder unless ``overwrite`` (the
    user's yes to write into it; what is in it stays).  ``why``: how ``command`` recognises its own
    output (e.g. "not listed in its label.json"); ``option``/``where``: the option and value that
    named the output location (``--out run/``)."""
    mine = {Path(p).absolute() for p in owned}
    opt = _option(option)  # named in the caller's terms (pipeline.runtime.errors)
    for p in paths:
        p = Path(p)
        if not (p.is_symlink() or p.exists()) or p.absolute() in mine:
            continue
        if p.is_dir() and not p.is_symlink():
            if overwrite:
                continue
            raise InputError(f"{{}}: {literal(p)} exists and was not written by {literal(signature(command))} "
                             f"({literal(why)}); pass {{}} to write into it (files there that "
                             f"{literal(signature(command))} does not write stay), or choose another {{}}",
                             opt(where), OVERWRITE, opt)
        _refuse_file(p, command, opt, where, why)


def refuse_foreign_files(folder: str | Path, own: Iterable[str], *, command: str, option: str | Option,
                         where: str | Path, why: str) -> None:
    """InputError naming the first file (or link) under ``folder`` whose relative path is not in
    ``own``: for a command that replaces ``folder`` whole, so that nothing it did not write is lost
    (``--overwrite`` or not)."""
    folder, own = Path(folder), set(own)
    if not folder.is_dir():
        return
    for p in sorted(folder.rglob("*")):
        if (p.is_file() or p.is_symlink()) and p.relative_to(folder).as_posix() not in own:
            _refuse_file(p, command, _option(option), where, why)


def check_outputs(out: str | Path, targets: Iterable[str], record: str, command: str, *, overwrite: bool,
                  option: str | Option = OUT, legacy_outputs: Iterable[str] = (), legacy_keys: Iterable[str] = ()) -> None:
    """Refuse (InputError, one line) before anything is written when ``out`` is a file, or when one of
    ``targets`` (paths relative to ``out``, files or folders; the record is added) or a folder on the
    way to one exists under ``out`` and the record of ``command`` there does not own it
    (:func:`owns`, :func:`refuse_unowned`)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError("{}: is a file, not a folder", _option(option)(out))
    own = owned_outputs(out, record, command, legacy_outputs=legacy_outputs, legacy_keys=legacy_keys)
    names = list(dict.fromkeys([*targets, record]))
    folders = list(dict.fromkeys(str(q) for t in names for q in reversed(PurePosixPath(t).parents) if str(q) != "."))
    claimed = {str(q) for o in own for q in PurePosixPath(o).parents} | own  # a folder holding a listed file
    in_way = [n for n in folders if n not in claimed and not owns(n, own)] + [n for n in names if not owns(n, own)]
    refuse_unowned([out / t for t in in_way], [], command=command, option=option, where=out,
                   why=f"not listed in a {record} of {signature(command)} there", overwrite=overwrite)


def remove_stale(out: str | Path, previous: Iterable[str], current: Iterable[str]) -> list[str]:
    """Remove the files a record listed before (``previous``) that this run did not write (``current``)
    -- the command's own, from a run with other formats or other images -- and the folders that leaves
    empty; never anything else (a listed folder of an earlier version's record is not walked).
    Returns the removed paths (relative)."""
    out, keep, removed = Path(out), set(current), []
    for rel in sorted(set(previous) - keep):
        p = out / rel
        if p.is_symlink() or p.is_file():
            p.unlink()
            removed.append(rel)
            for parent in p.relative_to(out).parents:
                d = out / parent
                if parent == Path(".") or any(d.iterdir()):
                    break
                d.rmdir()
    return removed


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
