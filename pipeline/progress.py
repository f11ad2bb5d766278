"""Progress bars (stderr) for every loop a user waits on; quiet when GEODISTILL_QUIET=1."""

from __future__ import annotations

import os
import sys

from tqdm.auto import tqdm


def progress(iterable=None, desc: str = "", total: int | None = None, **kw):
    disable = os.environ.get("GEODISTILL_QUIET", "") == "1"
    return tqdm(iterable, desc=desc, total=total, file=sys.stderr, disable=disable,
                dynamic_ncols=True, mininterval=0.5, leave=False, **kw)
