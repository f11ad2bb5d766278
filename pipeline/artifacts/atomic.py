"""Atomic replacement of files and folders, and the per-file PNG and CSV writers of the user commands.

A write goes through a hidden sibling temporary: a kill at any instant leaves the old or the new output, never a
partial one.  The fault points here are where the kill tests stop a process (``label``, ``segment`` write
through :func:`write_png` and :func:`write_csv`).
"""

from __future__ import annotations

import contextlib
import csv
import ctypes
import json
import os
import re
import shutil
import signal
import uuid
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import numpy as np

from pipeline.runtime.errors import InputError

__all__ = ["atomic_path", "write_text_if_changed", "read_json", "write_json", "folders_gone_on_failure", "write_png",
           "png_bytes", "write_csv"]

FAULT_ENV = "GEODISTILL_FAULT"
_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def fault_point(name: str) -> None:
    """``GEODISTILL_FAULT=<name>`` makes the process SIGKILL itself here (the kill tests)."""
    if os.environ.get(FAULT_ENV) == name:
        os.kill(os.getpid(), signal.SIGKILL)


def _sibling(path: Path, kind: str) -> Path:
    return path.with_name(f".{path.name}.{kind}-{os.getpid()}-{uuid.uuid4().hex[:8]}")


def _exchange(a: Path, b: Path) -> bool:
    """Atomically swap two paths (Linux ``renameat2(RENAME_EXCHANGE)``); False where unsupported."""
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    return fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        p.unlink(missing_ok=True)


def clean_leftovers(path: Path) -> None:
    """Remove temporaries of earlier writes of ``path`` whose writer process is gone (a killed stage)."""
    prefix = f".{path.name}."
    if not path.parent.is_dir():
        return
    for p in path.parent.iterdir():
        kind, _, tail = p.name[len(prefix):].partition("-")
        if not p.name.startswith(prefix) or kind not in ("tmp", "old"):
            continue
        pid = tail.split("-")[0]
        if pid.isdigit() and _pid_alive(int(pid)) and int(pid) != os.getpid():
            continue  # another live writer
        _remove(p)


def _replace(tmp: Path, path: Path) -> None:
    """Move ``tmp`` onto ``path``: a file by ``os.replace``, a folder by an atomic exchange.

    Where the exchange is unsupported the old folder is first moved aside to ``.<name>.old-PID-*``, which the
    next write removes.
    """
    fault_point("before_replace")
    if not path.is_dir() or path.is_symlink():
        os.replace(tmp, path)
    elif _exchange(tmp, path):
        fault_point("after_exchange")
        shutil.rmtree(tmp, ignore_errors=True)
    else:
        old = _sibling(path, "old")
        os.replace(path, old)
        os.replace(tmp, path)
        shutil.rmtree(old, ignore_errors=True)


def _errno_of(e: OSError) -> int | None:
    """``e.errno``, or the ``[errno N]`` that libraries (pyarrow) put in the message only."""
    if e.errno:
        return e.errno
    m = re.search(r"\[errno (\d+)\]", str(e), re.I)
    return int(m.group(1)) if m else None


@contextlib.contextmanager
def atomic_path(path: str | Path, is_dir: bool = False) -> Iterator[Path]:
    """Yield a hidden temporary sibling of ``path``; on success rename it onto ``path``, else delete it.

    Parameters
    ----------
    path : str or Path
        The output file or folder; its parent is created.
    is_dir : bool
        Whether the temporary is a folder (created empty) rather than a file name to write.

    Yields
    ------
    Path
        The temporary to write; it replaces ``path`` when the block ends without an error.

    Raises
    ------
    OSError
        The block failed with an OSError naming no file or the temporary: the same error, naming ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    clean_leftovers(path)
    tmp = _sibling(path, "tmp")
    if is_dir:
        tmp.mkdir()
    try:
        yield tmp
    except BaseException as e:
        _remove(tmp)
        if isinstance(e, OSError) and e.filename in (None, str(tmp)) and (code := _errno_of(e)):
            # the error names no file or the hidden temporary: name the output the user asked for
            raise OSError(code, os.strerror(code), str(path)) from e
        raise
    _replace(tmp, path)


def write_text_if_changed(path: str | Path, text: str) -> bool:
    """Replace ``path`` atomically when its text differs from ``text`` (else keep it and its mtime).

    Parameters
    ----------
    path : str or Path
        The file to write.
    text : str
        Its new text.

    Returns
    -------
    bool
        Whether the file was written.
    """
    path = Path(path)
    if path.is_file() and path.read_text() == text:
        return False
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return True


def read_json(path: str | Path) -> dict:
    """Read the JSON object in ``path``, or {} when it is missing, unreadable or not an object.

    Parameters
    ----------
    path : str or Path
        The JSON file.

    Returns
    -------
    dict
        Its object, or {}.
    """
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return {}
    return doc if isinstance(doc, dict) else {}


def write_json(path: str | Path, obj: Any) -> Path:
    """Write ``obj`` as indented, key-sorted JSON atomically.

    Parameters
    ----------
    path : str or Path
        The file to write.
    obj : Any
        A JSON-serialisable value.

    Returns
    -------
    Path
        ``path``.
    """
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=1, sort_keys=True) + "\n")
    return Path(path)


@contextlib.contextmanager
def folders_gone_on_failure(*folders: str | Path) -> Iterator[None]:
    """Remove, when the block fails, each of ``folders`` that did not exist before it (folders that existed stay).

    Parameters
    ----------
    *folders : str or Path
        The folders the block may create.

    Yields
    ------
    None
        Control to the block; its error is re-raised after the clean-up.
    """
    new = [Path(f) for f in folders if not Path(f).exists()]
    try:
        yield
    except BaseException:
        for f in new:
            if f.is_dir() and not f.is_symlink():
                shutil.rmtree(f, ignore_errors=True)
        raise


def write_png(path: Path, array: np.ndarray) -> None:
    """Write a PNG atomically; an RGB array is converted to OpenCV's BGR.

    Parameters
    ----------
    path : Path
        The PNG file.
    array : numpy.ndarray
        uint8 or uint16 [H,W] or RGB [H,W,3].

    Raises
    ------
    pipeline.runtime.errors.InputError
        OpenCV could not encode the array, or the file could not be written (one line naming ``path``).
    """
    data = png_bytes(array, path)
    _replace_file(path, lambda tmp: tmp.write_bytes(data))


def png_bytes(array: np.ndarray, what: str | Path = "array", compression: int | None = None) -> bytes:
    """Encode an array as PNG bytes; an RGB array is converted to OpenCV's BGR first.

    Parameters
    ----------
    array : numpy.ndarray
        uint8 or uint16 [H,W] or RGB [H,W,3].
    what : str or Path
        What the error names (the file it is for).
    compression : int, optional
        zlib level 0-9 (``IMWRITE_PNG_COMPRESSION``); None: OpenCV's default.

    Returns
    -------
    bytes
        The PNG file's bytes.

    Raises
    ------
    pipeline.runtime.errors.InputError
        OpenCV could not encode the array (one line naming ``what``).
    """
    import cv2

    arr = array[..., ::-1] if array.ndim == 3 else array
    params = [] if compression is None else [cv2.IMWRITE_PNG_COMPRESSION, compression]
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(arr), params)
    if not ok:
        raise InputError(f"{what}: PNG encoding failed")
    return buf.tobytes()


def _replace_file(path: Path, write: Callable[[Path], object]) -> Path:
    """``write`` a temporary sibling of ``path`` and rename it into place; an OSError is one InputError line.

    Not :func:`atomic_path`: a command writes thousands of masks into one folder, and a scan of the folder for
    leftovers (:func:`clean_leftovers`) before each would make the run quadratic in its images.
    """
    tmp = path.with_name(f".{path.name}.tmp-{uuid.uuid4().hex[:8]}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        write(tmp)
        os.replace(tmp, path)
    except OSError as e:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise InputError(f"{path}: cannot write ({e.strerror or e})") from None
    return path


def write_csv(path: str | Path, header: list[str], rows: Iterable) -> Path:
    """Write a CSV file of ``header`` and ``rows``, replaced atomically.

    Parameters
    ----------
    path : str or Path
        The CSV file.
    header : list of str
        The column names.
    rows : Iterable
        The rows, each a sequence of cells.

    Returns
    -------
    Path
        ``path``.
    """
    def write(tmp: Path) -> None:
        with open(tmp, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(header)
            w.writerows(rows)
    return _replace_file(Path(path), write)
