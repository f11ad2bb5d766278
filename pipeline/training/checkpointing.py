"""Per-epoch resume state on disk, in the train stage's resume folder (torch imported lazily: the stages start
without it)."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any, Mapping

from pipeline.catalog import RESUME_STATE_FILE as STATE_FILE

log = logging.getLogger(__name__)


class FileCheckpointer:
    """Per-epoch resume state in ``<directory>/state.pt``, replaced atomically."""

    def __init__(self, directory: str | Path):
        self.directory = Path(directory)

    def __repr__(self) -> str:
        return str(self.directory)

    def load(self, run_key: Mapping[str, Any]) -> dict | None:
        """The saved state, or None when there is none or it cannot be read."""
        import torch

        path = self.directory / STATE_FILE
        if not path.exists():
            return None
        try:
            return torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:
            log.warning("ignoring unreadable resume state %s (%s)", self.directory, type(e).__name__)
            return None

    def save(self, state: dict) -> None:
        import torch

        self.directory.mkdir(parents=True, exist_ok=True)
        tmp = self.directory / f".{STATE_FILE}.tmp-{os.getpid()}"
        torch.save(state, tmp)
        os.replace(tmp, self.directory / STATE_FILE)
