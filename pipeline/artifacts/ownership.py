"""Whose file is it: the user tools replace or remove only what they wrote, recognised by a JSON *record* in their
output folder that lists those files, written before any output (the policy: docs/own-data.md)."""

from __future__ import annotations

import json
from pathlib import Path, PurePosixPath
from typing import Iterable, Mapping

from pipeline.artifacts.atomic import write_json
from pipeline.runtime.errors import OUT, OVERWRITE, InputError, Option, literal

__all__ = ["WRITTEN_BY", "OUTPUTS", "signature", "read_record", "owned_outputs", "refuse_unowned",
           "refuse_foreign_files", "check_outputs", "remove_stale", "record_fields", "claim_outputs"]

WRITTEN_BY = "written_by"
OUTPUTS = "outputs"


def signature(command: str) -> str:
    """The ``written_by`` value of ``command``'s records."""
    return f"geodistill {command}"


def read_record(path: str | Path, command: str, legacy_keys: Iterable[str] = ()) -> dict | None:
    """The record at ``path`` when ``command`` wrote it, else None; ``legacy_keys``: those of a record from before
    ``written_by`` (all present: it is one)."""
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, ValueError, UnicodeDecodeError):
        return None
    legacy = tuple(legacy_keys)
    if isinstance(doc, dict) and (doc.get(WRITTEN_BY) == signature(command) or (
            legacy and WRITTEN_BY not in doc and all(k in doc for k in legacy))):
        return doc
    return None


def owned_outputs(out: str | Path, record: str, command: str, *, legacy_outputs: Iterable[str] = (),
                  legacy_keys: Iterable[str] = ()) -> set[str]:
    """The relative paths ``command``'s record ``out/record`` lists, itself included (a legacy record:
    ``legacy_outputs``); empty without one."""
    doc = read_record(Path(out) / record, command, legacy_keys)
    if doc is None:
        return set()
    listed = doc.get(OUTPUTS)
    names = {str(x) for x in listed} if isinstance(listed, list) else set(legacy_outputs)
    return names | {record}


def _option(option: str | Option) -> Option:
    """An option given by its flag alone as an :class:`Option`."""
    return option if isinstance(option, Option) else Option(option, option.lstrip("-").replace("-", "_"))


def owns(rel: str, own: Iterable[str]) -> bool:
    """Whether a record listing ``own`` owns ``rel``: listed, or inside a listed folder (older records list folders)."""
    own = set(own)
    parts = PurePosixPath(rel).parts
    return any("/".join(parts[:i]) in own for i in range(1, len(parts) + 1))


def _refuse_file(p: Path, command: str, option: Option, where, why: str) -> None:
    raise InputError(f"{{}}: {literal(p)} exists and was not written by {literal(signature(command))} "
                     f"({literal(why)}); {{}} replaces only what {literal(signature(command))} wrote: move it "
                     f"away, or choose another {{}}", option(where), OVERWRITE, option)


def refuse_unowned(paths: Iterable[str | Path], owned: Iterable[str | Path], *, command: str, option: str | Option,
                   where: str | Path, why: str, overwrite: bool) -> None:
    """InputError naming the first of ``paths`` that exists and is not ``owned``: a file or link always, a folder
    unless ``overwrite``.  ``why``: how ``command`` knows its own; ``option``/``where``: what named the location."""
    mine = {Path(p).absolute() for p in owned}
    opt = _option(option)
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
    """InputError naming the first file or link under ``folder`` not in ``own`` (for a command replacing it whole)."""
    folder, own = Path(folder), set(own)
    if not folder.is_dir():
        return
    for p in sorted(folder.rglob("*")):
        if (p.is_file() or p.is_symlink()) and p.relative_to(folder).as_posix() not in own:
            _refuse_file(p, command, _option(option), where, why)


def check_outputs(out: str | Path, targets: Iterable[str], record: str, command: str, *, overwrite: bool,
                  option: str | Option = OUT, legacy_outputs: Iterable[str] = (), legacy_keys: Iterable[str] = ()
                  ) -> None:
    """InputError before anything is written when ``out`` is a file, or when one of ``targets`` (relative paths; the
    record too) or a folder on the way to one exists there and ``command``'s record does not own it."""
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
    """Remove the files of ``previous`` not in ``current`` and the folders that leaves empty (never a listed folder's
    contents); the removed relative paths."""
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
    """``written_by`` and ``outputs`` (what the record listed, ``targets``, itself) of a record ``command`` writes."""
    own = owned_outputs(out, record, command, legacy_outputs=legacy_outputs, legacy_keys=legacy_keys)
    return {WRITTEN_BY: signature(command), OUTPUTS: sorted(own | set(targets) | {record})}


def claim_outputs(out: str | Path, targets: Iterable[str], record: str, command: str,
                  fields: Mapping | None = None, **legacy) -> dict:
    """Write (and return) the record ``out/record`` listing ``targets`` before the outputs, so that the next run
    recognises a killed one's files; ``fields``: the record's other fields."""
    doc = {**dict(fields or {}), **record_fields(out, record, command, targets, **legacy)}
    write_json(Path(out) / record, doc)
    return doc
