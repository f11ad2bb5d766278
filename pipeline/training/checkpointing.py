"""Where a training run's per-epoch resume state lives (:class:`Checkpointer`).

Nowhere (:class:`NoCheckpointer`), or on disk in the train stage's resume folder (:class:`FileCheckpointer`;
torch imported lazily: the stages start without it).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any, Mapping, Protocol

from pipeline.catalog import RESUME_STATE_FILE as STATE_FILE

__all__ = ["Checkpointer", "NoCheckpointer", "FileCheckpointer"]

log = logging.getLogger(__name__)


class Checkpointer(Protocol):
    """Where a run's per-epoch resume state lives: ``load(run_key)`` the last saved (or None), ``save(state)``."""

    def load(self, run_key: Mapping[str, Any]) -> dict | None:
        """Load the last saved resume state.

        Parameters
        ----------
        run_key : Mapping
            The run's key: what a state must have been saved under to be resumed (the method, seed, epochs,
            training image ids, threads, autocast dtype and, under ``until: plateau``, the stopping rule).  A
            checkpointer may return a state of another key; :func:`pipeline.training.loop.train` compares the
            keys.

        Returns
        -------
        dict or None
            The state :meth:`save` was last given, or None: there is none.
        """
        ...

    def save(self, state: dict) -> None:
        """Save the resume state after an epoch, replacing the one before.

        Parameters
        ----------
        state : dict
            The complete resume state (version, run key, epoch, model, optimizer, scheduler, torch RNG, log,
            the selection candidate and, where used, the weight averages and the ``until: plateau`` state); its
            weights on the CPU, the optimizer's state on the training device.
        """
        ...


class NoCheckpointer:
    """No resume: nothing is loaded, saves are dropped."""

    def load(self, run_key: Mapping[str, Any]) -> dict | None:
        """Load nothing.

        Parameters
        ----------
        run_key : Mapping
            The run's key (unread).

        Returns
        -------
        None
            Always: every run starts at epoch 1.
        """
        return None

    def save(self, state: dict) -> None:
        """Drop ``state``.

        Parameters
        ----------
        state : dict
            The resume state (discarded).
        """
        pass


class FileCheckpointer:
    """Per-epoch resume state in ``<directory>/state.pt``, replaced atomically.

    Parameters
    ----------
    directory : str or Path
        The resume folder (made at the first save).

    Attributes
    ----------
    directory : Path
        The resume folder.
    """

    def __init__(self, directory: str | Path):
        self.directory = Path(directory)

    def __repr__(self) -> str:
        """Return the resume folder's path (the train stage's log names the checkpointer by it)."""
        return str(self.directory)

    def load(self, run_key: Mapping[str, Any]) -> dict | None:
        """Load the saved state (torch ``weights_only``: nothing loaded executes code).

        Parameters
        ----------
        run_key : Mapping
            The run's key (unread here: :func:`pipeline.training.loop.train` compares it with the state's).

        Returns
        -------
        dict or None
            The state last saved, on the CPU; None when there is none or it cannot be read (a warning says so).
        """
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
        """Save ``state`` in the folder (:data:`pipeline.catalog.RESUME_STATE_FILE`), replacing the last atomically.

        Parameters
        ----------
        state : dict
            The complete resume state (:meth:`Checkpointer.save`).
        """
        import torch

        self.directory.mkdir(parents=True, exist_ok=True)
        tmp = self.directory / f".{STATE_FILE}.tmp-{os.getpid()}"
        torch.save(state, tmp)
        os.replace(tmp, self.directory / STATE_FILE)
