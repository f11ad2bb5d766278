"""Progress bars on stderr for every loop a user waits on, counting the user's units.

None under ``GEODISTILL_QUIET=1`` or :func:`quiet_bars` (a command's ``--quiet``).
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
    """Tell whether bars are off: ``GEODISTILL_QUIET=1`` or inside :func:`quiet_bars`.

    Returns
    -------
    bool
        True when no bar is drawn.
    """
    return _QUIET.get() or os.environ.get(QUIET_ENV, "") == "1"


@contextlib.contextmanager
def quiet_bars(on: bool = True):
    """Turn progress bars off inside the block (when ``on``); the previous state is restored after, whatever happens.

    Parameters
    ----------
    on : bool
        Whether to silence the bars (a command passes its ``--quiet``).

    Yields
    ------
    None
        Control to the block.
    """
    token = _QUIET.set(bool(on) or _QUIET.get())
    try:
        yield
    finally:
        _QUIET.reset(token)


def progress(iterable=None, desc: str = "", total: int | None = None, **kw):
    """Wrap ``iterable`` in a tqdm bar on stderr that stays when done (``leave=True`` unless a caller says otherwise).

    Parameters
    ----------
    iterable : Iterable, optional
        What to iterate; None for a bar updated by hand.
    desc : str
        The bar's label.
    total : int, optional
        The number of units (default: ``len(iterable)`` where it has one).
    **kw
        Further tqdm options.

    Returns
    -------
    tqdm.tqdm
        The bar, disabled when :func:`bars_quiet`.
    """
    kw.setdefault("leave", True)
    return tqdm(iterable, desc=desc, total=total, file=sys.stderr, disable=bars_quiet(),
                dynamic_ncols=True, mininterval=0.5, **kw)


@contextlib.contextmanager
def library_bars_off():
    """Turn transformers' own progress bars (``from_pretrained``'s "Loading weights") off inside; warnings stay.

    Yields
    ------
    None
        Control to the block; the bars' previous state is restored after it.
    """
    from transformers.utils import logging as hf_logging

    was_on = hf_logging.is_progress_bar_enabled()
    hf_logging.disable_progress_bar()
    try:
        yield
    finally:
        if was_on:
            hf_logging.enable_progress_bar()
