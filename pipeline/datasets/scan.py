"""The one folder scan of label, distill / prepare (folder source) and segment (docs/own-data.md).

Recursive, never following links out of the folder.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

from pipeline.runtime.errors import InputError

__all__ = ["scan_inputs"]


@dataclasses.dataclass
class FolderScan:
    """What :func:`scan_inputs` found under one input path: the images, and each entry it skipped or left unused."""

    root: Path                       # the input folder, or the parent of the single input file
    files: list[Path]                # images to segment, sorted
    skipped: list[tuple[str, str]]   # (path, reason): bad entries -- links not followed, non-regular files
    is_dir: bool
    unused: list[tuple[str, str]] = dataclasses.field(default_factory=list)  # not images: listed, not an error


def scan_inputs(input_path: str | Path, *, keep_broken_links: bool = False) -> FolderScan:
    """List the images under ``input_path`` (a file: as given), sorting out the entries that are not.

    Hidden entries and non-images are ``unused``; bad ones are ``skipped``: links leaving the folder or to
    folders, special files, broken links.

    Parameters
    ----------
    input_path : str or Path
        An image file or a folder.
    keep_broken_links : bool
        Put broken links in ``files`` instead, for the caller's decode pass to report.

    Returns
    -------
    FolderScan
        The folder (or the file's parent), the image files sorted, the skipped and unused entries with their
        reasons, and whether ``input_path`` is a folder.

    Raises
    ------
    pipeline.runtime.errors.InputError
        ``input_path`` does not exist.
    """
    from pipeline.datasets.loading import SUPPORTED_SUFFIXES, broken_link_reason

    p = Path(input_path)
    if not p.exists():
        raise InputError(f"--input {p}: not found")
    if not p.is_dir():
        return FolderScan(p.parent, [p], [], False)
    root_r = p.resolve()
    files: list[Path] = []
    skipped: list[tuple[str, str]] = []
    unused: list[tuple[str, str]] = []

    def walk_error(e: OSError) -> None:
        skipped.append((str(e.filename), f"folder unreadable ({e.strerror or type(e).__name__})"))

    for dirpath, dirnames, filenames in os.walk(p, onerror=walk_error, followlinks=False):
        d = Path(dirpath)
        unused.extend((str(d / n), "hidden folder, not read") for n in sorted(dirnames) if n.startswith("."))
        dirnames[:] = sorted(n for n in dirnames if not n.startswith("."))
        for n in dirnames:
            if (d / n).is_symlink():  # os.walk does not descend into it: say so
                skipped.append((str(d / n), "symbolic link to a folder (links to folders are not followed)"))
        for n in sorted(filenames):
            f = d / n
            if n.startswith("."):
                unused.append((str(f), "hidden file, not read"))
                continue
            if f.suffix.lower() not in SUPPORTED_SUFFIXES:
                unused.append((str(f), f"not an image file (suffix {f.suffix or '(none)'!r}; images are "
                                       f"{', '.join(s.lstrip('.') for s in SUPPORTED_SUFFIXES)}), not read"))
                continue
            if f.is_symlink():
                try:
                    target = f.resolve(strict=True)
                except (OSError, RuntimeError):
                    if keep_broken_links:
                        files.append(f)
                    else:
                        skipped.append((str(f), broken_link_reason(f)))
                    continue
                if not target.is_relative_to(root_r):
                    skipped.append((str(f), f"symbolic link pointing outside the input folder (to {target})"))
                    continue
            if not f.is_file():
                skipped.append((str(f), "not a regular file"))
                continue
            files.append(f)
    return FolderScan(p, sorted(files), sorted(skipped), True, sorted(unused))
