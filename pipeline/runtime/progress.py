"""Progress bars on stderr for every loop a user waits on, counting the user's units; none under
``GEODISTILL_QUIET=1`` or :func:`quiet_bars` (a command's ``--quiet``).
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import sys

from tqdm.auto import tqdm

__all__ = ["QUIET_ENV", "bars_quiet", "quiet_bars", "progress", "library_bars_off"]

_QUIET = contextvars.ContextVar("geodistill_quiet_bars", default=False)
#: how a command's --quiet reaches its child processes
QUIET_ENV = "GEODISTILL_QUIET"


def bars_quiet() -> bool:
    """Whether bars are off: ``GEODISTILL_QUIET=1`` or inside :func:`quiet_bars`."""
    return _QUIET.get() or os.environ.get(QUIET_ENV, "") == "1"


@contextlib.contextmanager
def quiet_bars(on: bool = True):
    """No progress bar inside (``on``); restored after, whatever happens."""
    token = _QUIET.set(bool(on) or _QUIET.get())
    try:
        yield
    finally:
        _QUIET.reset(token)


def progress(iterable=None, desc: str = "", total: int | None = None, **kw):
    """A tqdm bar on stderr that stays when done (``leave=True`` unless a caller says otherwise)."""
    kw.setdefault("leave", True)
    return tqdm(iterable, desc=desc, total=total, file=sys.stderr, disable=bars_quiet(),
                dynamic_ncols=True, mininterval=0.5, **kw)


@contextlib.contextmanager
def library_bars_off():
    """Transformers' own progress bars (``from_pretrained``'s "Loading weights") off inside; warnings stay."""
    from transformers.utils import logging as hf_logging

    was_on = hf_logging.is_progress_bar_enabled()
    hf_logging.disable_progress_bar()
    try:
        yield
    finally:
        if was_on:
            hf_logging.enable_progress_bar()
