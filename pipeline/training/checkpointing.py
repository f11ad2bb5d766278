"""Per-epoch resume state on disk: the :class:`pipeline.training.loop.Checkpointer` the train stage uses.

The state lives in ``<directory>/state.pt``, ``directory`` being the resume folder under the run's
checkpoint fingerprint (stages/train.py), so a run whose training params changed starts afresh; a
killed run continues where it stopped.  torch stays a lazy import: the stage scripts import this
module at their top and start (``--help``) without torch.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any, Mapping

from pipeline.catalog import RESUME_STATE_FILE as STATE_FILE

log = logging.getLogger(__name__)


class FileCheckpointer:
    """Per-epoch resume state in ``<directory>/state.pt`` (written atomically: temp file + os.replace)."""

    def __init__(self, directory: str | Path):
        self.directory = Path(directory)

    def __repr__(self) -> str:
        return str(self.directory)

    def load(self, run_key: Mapping[str, Any]) -> dict | None:
        """The saved state, or None when there is none or it cannot be read (train checks the run key)."""
        import torch

        path = self.directory / STATE_FILE
        if not path.exists():
            return None
        try:
            # tensors and plain containers only: nothing in a state file can execute code
            return torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:  # a state cut off by a kill during torch.save cannot happen (os.replace)
            log.warning("ignoring unreadable resume state %s (%s)", self.directory, type(e).__name__)
            return None

    def save(self, state: dict) -> None:
        import torch

        self.directory.mkdir(parents=True, exist_ok=True)
        tmp = self.directory / f".{STATE_FILE}.tmp-{os.getpid()}"
        torch.save(state, tmp)
        os.replace(tmp, self.directory / STATE_FILE)
