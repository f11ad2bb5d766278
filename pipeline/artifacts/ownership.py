"""Whose file is it: the user tools replace or remove only what they wrote.

What a tool wrote is recognised by a JSON *record* in its output folder that lists those files, written before
any output (the policy: docs/own-data.md).
"""

from __future__ import annotations

import json
from pathlib import Path, PurePosixPath
from typing import Iterable, Mapping

from pipeline.artifacts.atomic import write_json
from pipeline.runtime.errors import OUT, OVERWRITE, InputError, Option, literal

__all__ = ["WRITTEN_BY", "OUTPUTS", "signature", "read_record", "owned_outputs", "refuse_unowned",
           "refuse_foreign_files", "check_outputs", "remove_stale", "record_fields", "claim_outputs"]

#: the record's key holding its writer (:func:`signature`)
WRITTEN_BY = "written_by"
#: the record's key listing the relative paths its writer owns
OUTPUTS = "outputs"


def signature(command: str) -> str:
    """Return the ``written_by`` value of ``command``'s records.

    Parameters
    ----------
    command : str
        The ``geodistill`` subcommand (``"label"``, ``"segment"``, ...).

    Returns
    -------
    str
        ``"geodistill COMMAND"``.
    """
    return f"geodistill {command}"


def read_record(path: str | Path, command: str, legacy_keys: Iterable[str] = ()) -> dict | None:
    """Read the record at ``path`` when ``command`` wrote it.

    Parameters
    ----------
    path : str or Path
        The record file.
    command : str
        The subcommand whose record it must be (:func:`signature`).
    legacy_keys : Iterable[str], optional
        The keys of a record from before ``written_by``: one without ``written_by`` that holds them all counts as
        ``command``'s.  Empty: no legacy record is recognised.

    Returns
    -------
    dict or None
        The record; None when the file is absent, unreadable, not a JSON object or another writer's.
    """
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
    """List the relative paths ``command``'s record ``out/record`` owns, the record itself included.

    Parameters
    ----------
    out : str or Path
        The output folder.
    record : str
        The record's file name inside ``out``.
    command : str
        The subcommand whose record it must be.
    legacy_outputs : Iterable[str], optional
        What a legacy record (one without an ``outputs`` list) owns.
    legacy_keys : Iterable[str], optional
        The keys that make a record without ``written_by`` a legacy one (:func:`read_record`).

    Returns
    -------
    set[str]
        The owned relative paths (posix); empty when there is no record of ``command``.
    """
    doc = read_record(Path(out) / record, command, legacy_keys)
    if doc is None:
        return set()
    listed = doc.get(OUTPUTS)
    names = {str(x) for x in listed} if isinstance(listed, list) else set(legacy_outputs)
    return names | {record}


def _option(option: str | Option) -> Option:
    """Turn an option given by its flag alone into an :class:`Option`."""
    return option if isinstance(option, Option) else Option(option, option.lstrip("-").replace("-", "_"))


def owns(rel: str, own: Iterable[str]) -> bool:
    """Tell whether a record listing ``own`` owns ``rel``: listed, or inside a listed folder (older records list them).

    Parameters
    ----------
    rel : str
        A relative posix path.
    own : Iterable[str]
        The record's listed paths.

    Returns
    -------
    bool
        True when ``rel`` or one of its parent folders is listed.
    """
    own = set(own)
    parts = PurePosixPath(rel).parts
    return any("/".join(parts[:i]) in own for i in range(1, len(parts) + 1))


def _refuse_file(p: Path, command: str, option: Option, where, why: str) -> None:
    raise InputError(f"{{}}: {literal(p)} exists and was not written by {literal(signature(command))} "
                     f"({literal(why)}); {{}} replaces only what {literal(signature(command))} wrote: move it "
                     f"away, or choose another {{}}", option(where), OVERWRITE, option)


def refuse_unowned(paths: Iterable[str | Path], owned: Iterable[str | Path], *, command: str, option: str | Option,
                   where: str | Path, why: str, overwrite: bool) -> None:
    """Refuse to write over the first of ``paths`` that exists and is not ``owned``.

    A file or link that exists is refused always, a folder unless ``overwrite``.

    Parameters
    ----------
    paths : Iterable[str or Path]
        The paths about to be written.
    owned : Iterable[str or Path]
        The paths ``command`` may replace.
    command : str
        The subcommand writing (named in the message).
    option : str or pipeline.runtime.errors.Option
        The option that named the location (a bare flag is turned into an Option).
    where : str or Path
        The value of ``option``, named in the message.
    why : str
        How ``command`` knows its own files, for the message.
    overwrite : bool
        Whether the user passed ``--overwrite`` (``overwrite=True``): then an existing folder is written into.

    Raises
    ------
    pipeline.runtime.errors.InputError
        One of ``paths`` exists and is not owned (a folder: only without ``overwrite``); one line naming it, the
        option and the way out.
    """
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
    """Refuse to replace ``folder`` whole while it holds a file or link not in ``own``.

    Parameters
    ----------
    folder : str or Path
        The folder about to be replaced; absent: nothing to refuse.
    own : Iterable[str]
        The relative posix paths the command owns there.
    command : str
        The subcommand writing (named in the message).
    option : str or pipeline.runtime.errors.Option
        The option that named the location.
    where : str or Path
        The value of ``option``, named in the message.
    why : str
        How ``command`` knows its own files, for the message.

    Raises
    ------
    pipeline.runtime.errors.InputError
        A file or link under ``folder`` is not in ``own``; one line naming the first, in sorted order.
    """
    folder, own = Path(folder), set(own)
    if not folder.is_dir():
        return
    for p in sorted(folder.rglob("*")):
        if (p.is_file() or p.is_symlink()) and p.relative_to(folder).as_posix() not in own:
            _refuse_file(p, command, _option(option), where, why)


def check_outputs(out: str | Path, targets: Iterable[str], record: str, command: str, *, overwrite: bool,
                  option: str | Option = OUT, legacy_outputs: Iterable[str] = (), legacy_keys: Iterable[str] = ()
                  ) -> None:
    """Check, before anything is written, that ``command`` may write ``targets`` and its record into ``out``.

    Refused: ``out`` is a file, or one of ``targets``, the record or a folder on the way to one exists there and
    ``command``'s record does not own it (an unowned existing folder is accepted with ``overwrite``).

    Parameters
    ----------
    out : str or Path
        The output folder.
    targets : Iterable[str]
        The relative posix paths about to be written.
    record : str
        The record's file name inside ``out``.
    command : str
        The subcommand writing.
    overwrite : bool
        Whether the user passed ``--overwrite``.
    option : str or pipeline.runtime.errors.Option, optional
        The option that named ``out`` (default ``--out``).
    legacy_outputs, legacy_keys : Iterable[str], optional
        How a record from before ``written_by`` is recognised and what it owns (:func:`owned_outputs`).

    Raises
    ------
    pipeline.runtime.errors.InputError
        ``out`` is a file, or a path in the way is not owned; one line naming it.
    """
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
    """Remove the files of ``previous`` not in ``current``, and the folders that leaves empty.

    A listed folder's contents are never removed: only files and links listed in ``previous`` themselves.

    Parameters
    ----------
    out : str or Path
        The output folder.
    previous : Iterable[str]
        The relative paths the last run's record listed.
    current : Iterable[str]
        The relative paths this run writes.

    Returns
    -------
    list[str]
        The relative paths of the files removed, sorted.
    """
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
    """Build the ``written_by`` and ``outputs`` fields of the record ``command`` writes.

    Parameters
    ----------
    out : str or Path
        The output folder.
    record : str
        The record's file name inside ``out``.
    command : str
        The subcommand writing.
    targets : Iterable[str]
        The relative paths this run writes.
    legacy_outputs, legacy_keys : Iterable[str], optional
        How a record from before ``written_by`` is recognised and what it owns (:func:`owned_outputs`).

    Returns
    -------
    dict
        ``{WRITTEN_BY: signature(command), OUTPUTS: [...]}``, the outputs sorted: what the existing record owned,
        ``targets`` and the record itself.
    """
    own = owned_outputs(out, record, command, legacy_outputs=legacy_outputs, legacy_keys=legacy_keys)
    return {WRITTEN_BY: signature(command), OUTPUTS: sorted(own | set(targets) | {record})}


def claim_outputs(out: str | Path, targets: Iterable[str], record: str, command: str,
                  fields: Mapping | None = None, **legacy) -> dict:
    """Write the record ``out/record`` listing ``targets``, before the outputs, atomically.

    Written first, so that the next run recognises the files of a run that was killed.

    Parameters
    ----------
    out : str or Path
        The output folder.
    targets : Iterable[str]
        The relative paths this run writes.
    record : str
        The record's file name inside ``out``.
    command : str
        The subcommand writing.
    fields : Mapping, optional
        The record's other fields; ``written_by`` and ``outputs`` take precedence over theirs.
    **legacy
        ``legacy_outputs`` and ``legacy_keys``, passed to :func:`record_fields`.

    Returns
    -------
    dict
        The record as written.
    """
    doc = {**dict(fields or {}), **record_fields(out, record, command, targets, **legacy)}
    write_json(Path(out) / record, doc)
    return doc
