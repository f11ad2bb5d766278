"""Conventions shared by every command, the stage scripts' and the user tools'.

``--params``, ``--set``, ``--device``; logs on stderr; a user error is one line and exit code 2, an
operating-system failure one line naming the path and exit code 1.  The stage scripts (``stages/``) import them
from here; nothing under ``pipeline/`` imports ``stages/``.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import os
import sys
from pathlib import Path
from typing import Any, Callable, Iterable

import click

from pipeline.catalog import PARAMS_FILE
from pipeline.runtime.codeversion import ROOT, module_name, code_version_of
from pipeline.runtime.errors import BIT_DEPTH, CLI, MAX_PIXELS, OVERWRITE, SKIP_BAD, InputError, calling
from pipeline.params import AUTO_BIT_DEPTH, BIT_DEPTHS, PAPER, load_params
from pipeline.teacher_table import TEACHER_GROUP, TEACHER_TABLE, folder_options

__all__ = ["setup_logging", "one_line_errors", "overwrite_option", "skip_bad_option", "quiet_option",
           "max_pixels_option", "bit_depth_option", "teacher_workers_options", "teacher_choice_options", "stage_code_version", "stage_command"]


def setup_logging() -> None:
    """Send log records to stderr, at the level ``GEODISTILL_LOG`` names (default INFO; an unknown name: INFO).

    Calls :func:`logging.basicConfig`, so it does nothing when the root logger already has a handler.
    """
    level = os.environ.get("GEODISTILL_LOG", "INFO").upper()
    logging.basicConfig(stream=sys.stderr, level=getattr(logging, level, logging.INFO),
                        format="%(asctime)s %(name)s %(levelname)s %(message)s", datefmt="%H:%M:%S")


EXIT_INPUT, EXIT_OS = 2, 1
_OS_WHAT = {errno.ENOSPC: "no space left on the device", errno.EDQUOT: "disk quota exceeded",
            errno.EACCES: "permission denied", errno.EPERM: "operation not permitted",
            errno.EROFS: "read-only file system", errno.ENAMETOOLONG: "path too long"}


def os_error_line(e: OSError) -> str:
    """Spell an operating-system failure as one line: ``out/masks: no space left on the device (ENOSPC)``."""
    what = _OS_WHAT.get(e.errno) or (e.strerror or str(e) or type(e).__name__)
    name = errno.errorcode.get(e.errno) if e.errno else None
    path = e.filename if e.filename is not None else None
    if path is not None and e.filename2 is not None:
        path = f"{path} -> {e.filename2}"
    line = f"{what} ({name})" if name else what
    return f"{path}: {line}" if path is not None else line


@contextlib.contextmanager
def one_line_errors(command: str):
    """Run a command's body so that a user error or an OS failure ends it with one line, never a traceback.

    Inside, :class:`pipeline.runtime.errors.InputError` messages name the command-line flags.

    Parameters
    ----------
    command : str
        The subcommand's name, printed as ``geodistill <command>: error: <line>``.

    Yields
    ------
    None
        Control to the command's body.

    Raises
    ------
    SystemExit
        Code 2 after an :class:`~pipeline.runtime.errors.InputError` (its first line printed on stderr), code 1
        after an :class:`OSError` (one line naming the path); anything else propagates with its traceback.
    """
    try:
        with calling(CLI):
            yield
    except InputError as e:
        _settle_pending_reads()
        line = e.render(CLI)
        msg = line.splitlines()[0] if line else type(e).__name__
        click.echo(f"geodistill {command}: error: {msg}", err=True)
        sys.exit(EXIT_INPUT)
    except OSError as e:
        _settle_pending_reads()
        click.echo(f"geodistill {command}: error: {os_error_line(e).splitlines()[0]}", err=True)
        sys.exit(EXIT_OS)


#: how long a failing command waits for the reads it cancelled (seconds): a cancelled read ends at once
SETTLE_SECONDS = 5.0


def _settle_pending_reads(timeout: float = SETTLE_SECONDS) -> None:
    """Cancel and await the chunk reads zarr left pending on its I/O loop, the siblings of a read that failed.

    zarr v3 reads a selection's chunks concurrently on its own event loop; when one fails (a corrupt chunk), the
    others keep running, and zarr's exit hook closes the loop under them: asyncio then prints "Task was
    destroyed but it is pending!" lines after the command's one line.  The command is ending, so every task
    there is cancelled.  zarr is not imported here: a command that never read one has nothing pending.
    """
    sync = sys.modules.get("zarr.core.sync")
    loop = getattr(sync, "loop", [None])[0]
    if loop is None or loop.is_closed() or not loop.is_running():
        return

    async def cancel_the_others() -> None:
        tasks = asyncio.all_tasks() - {asyncio.current_task()}
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    with contextlib.suppress(Exception):  # a read that does not end in time is left to zarr's own exit
        asyncio.run_coroutine_threadsafe(cancel_the_others(), loop).result(timeout)


overwrite_option = click.option(
    OVERWRITE.flag, is_flag=True,
    help="write into an existing output folder this command did not make; files of yours there stay, and "
         "a file of yours where an output goes is refused by name either way (docs/own-data.md)")
skip_bad_option = click.option(
    SKIP_BAD.flag, is_flag=True,
    help="leave unreadable images out and list them with the reason (default: stop at the first, naming it)")
quiet_option = click.option("--quiet", "-q", is_flag=True,
                            help="no progress bars (warnings, errors and the summary line stay)")
max_pixels_option = click.option(
    MAX_PIXELS.flag, MAX_PIXELS.keyword, type=int, default=None, metavar="N",
    help="refuse images above N pixels (width x height), read from the file header before decoding; "
         f"with --skip-bad they are left out and listed (default: data.max_pixels, {PAPER.data.max_pixels:,})")

bit_depth_option = click.option(
    BIT_DEPTH.flag, BIT_DEPTH.keyword, type=click.Choice([str(b) for b in BIT_DEPTHS]), default=None, metavar="BITS",
    callback=lambda ctx, param, v: v if v in (None, AUTO_BIT_DEPTH) else int(v),
    help=f"bits a 16-bit frame's sensor fills: {', '.join(map(str, BIT_DEPTHS))} (default: what the bundle records, "
         "else data.bit_depth, "
         f"{PAPER.data.bit_depth!r}: the file's full range)")


def teacher_workers_options(fn):
    """Add ``--workers`` and ``--address``, the teacher's Ray Data executor, to a click command.

    For the teacher stage and ``geodistill label``.

    Parameters
    ----------
    fn : Callable
        The command's function, before ``click.command``.

    Returns
    -------
    Callable
        ``fn`` with the two options, passed as keywords ``workers`` and ``address``.
    """
    fn = click.option("--address", default=None, metavar="ADDRESS",
                      help="Ray cluster to join with --workers (default: RAY_ADDRESS, else an embedded local Ray)")(fn)
    return click.option("--workers", default=0, show_default=True, type=click.IntRange(0),
                        help="teachers in a Ray Data actor pool (one per GPU or CPU worker); 0 = the serial "
                             "loop in this process (same results)")(fn)


def teacher_choice_options(refused: str = ""):
    """Add ``--backend`` and each backend row's folder option to a click command.

    The folder options (``--checkpoint``, ``--imported-dir``) come from the teacher table's ``folder`` column and
    reach the command as keyword arguments.

    Parameters
    ----------
    refused : str
        The end of ``--backend``'s help text.

    Returns
    -------
    callable
        A decorator for a click command.
    """
    def add(fn):
        for name, (option, help_) in reversed(folder_options().items()):
            fn = click.option(option.flag, option.keyword, default=None, type=click.Path(),
                              help=f"{help_}; implies --backend {name}")(fn)
        return click.option("--backend", default=None, metavar="NAME", help="teacher: " + " | ".join(
            f"{name} ({t.description})" for name, t in TEACHER_TABLE.items())
            + f" | an installed plug-in's name (entry points {TEACHER_GROUP}){refused}")(fn)
    return add


def stage_code_version(stage_file: str) -> str:
    """Hash a stage script's code: every project file it imports (:func:`pipeline.runtime.codeversion.code_version_of`).

    Parameters
    ----------
    stage_file : str
        The script's path (its ``__file__``), under the repository root.

    Returns
    -------
    str
        The code version, 16 hex digits.
    """
    return code_version_of(module_name(Path(stage_file).resolve(), ROOT))


#: ``load(params_file, overrides, default_profile) -> params``: passed in, since no stage may import profiles
ProfileLoader = Callable[[Any, Iterable[str], str], dict]


def stage_command(name: str, default_profile: str | None = None, profile_loader: ProfileLoader | None = None
                  ) -> Callable:
    """Make a decorator turning ``fn(params, device, **options)`` into a click command with the shared options.

    The command gets ``--params``, ``--set`` and ``--device``; it sets up logging, loads and validates the params
    and runs ``fn`` under :func:`one_line_errors`.  ``fn``'s docstring is the command's help.

    Parameters
    ----------
    name : str
        The command's name.
    default_profile : str, optional
        The profile whose params apply without ``--params`` (commands that run outside a project, e.g. ``label``);
        None: ``--params`` defaults to :data:`pipeline.catalog.PARAMS_FILE`.
    profile_loader : ProfileLoader, optional
        ``load(params_file, overrides, default_profile) -> params``; given exactly when ``default_profile`` is
        (no stage may import :mod:`pipeline.profiles`).

    Returns
    -------
    Callable
        The decorator: ``fn`` -> :class:`click.Command`.

    Raises
    ------
    TypeError
        Only one of ``default_profile`` and ``profile_loader`` is given.
    """
    if (default_profile is None) != (profile_loader is None):
        raise TypeError(f"stage_command({name!r}): default_profile and profile_loader go together")

    def deco(fn: Callable) -> click.Command:
        def wrapper(params_file: str | None, overrides: tuple[str, ...], device: str, **kw: Any):
            setup_logging()
            with one_line_errors(name):
                if profile_loader is not None:
                    params = profile_loader(params_file, overrides, default_profile)
                else:
                    params = load_params(params_file, overrides)
                return fn(params=params, device=device, **kw)

        wrapper.__click_params__ = list(getattr(fn, "__click_params__", []))
        wrapper.__doc__ = fn.__doc__
        wrapper.__name__ = fn.__name__
        cmd = click.option("--device", default="auto", show_default=True,
                           help="auto | cpu | cuda")(wrapper)
        cmd = click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE",
                           help="override a param, e.g. --set train.epochs_stage1=3 (repeatable)")(cmd)
        cmd = click.option("--params", "params_file", default=None if default_profile else PARAMS_FILE,
                           show_default=True, type=click.Path(dir_okay=False),
                           help=f"params file (default: the {default_profile!r} profile's values)"
                           if default_profile else "params file")(cmd)
        return click.command(name=name, help=fn.__doc__)(cmd)

    return deco
