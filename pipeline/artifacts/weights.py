"""A model's weights: ``model.safetensors`` and ``model.json`` (config, the run's fields).

An older run's ``model.pt`` is read tensors-only; both read into one payload (``state_dict``,
``geometry_state_dict``, ``config``).
"""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from pipeline.catalog import LEGACY_WEIGHTS_FILE, WEIGHTS_CONFIG_FILE, WEIGHTS_FILE
from pipeline.runtime.errors import ArtifactError

__all__ = ["write_weights", "weights_path", "read_weights"]

GEOMETRY_PREFIX = "geometry_heads."
#: ONE key: safetensors writes the metadata map in hash order, so two would make the bytes differ between runs
HEADER = {"format": "pt"}


def write_weights(directory: str | Path, state_dict: dict, config: dict,
                  geometry_state_dict: dict | None = None, **fields) -> None:
    """Write ``model.safetensors`` and ``model.json`` into ``directory``.

    Parameters
    ----------
    directory : str or Path
        An existing folder (a checkpoint's temporary, written atomically by the caller).
    state_dict : dict
        The TinyUNet's tensors.
    config : dict
        The model config (``model.json``'s ``config``).
    geometry_state_dict : dict, optional
        The training-only geometry heads' tensors, stored under their own prefix.
    **fields
        The run's JSON values, stored in ``model.json`` beside the config.
    """
    directory = Path(directory)
    tensors = {k: _plain(v) for k, v in state_dict.items()}
    for k, v in (geometry_state_dict or {}).items():
        tensors[GEOMETRY_PREFIX + k] = _plain(v)
    save_file(tensors, directory / WEIGHTS_FILE, metadata=HEADER)
    doc = {"config": dict(config), "geometry_heads": geometry_state_dict is not None, **fields}
    (directory / WEIGHTS_CONFIG_FILE).write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n")


def _plain(t: torch.Tensor) -> torch.Tensor:
    """Make a tensor safetensors can write: detached, on the CPU, contiguous, its own storage."""
    return t.detach().to("cpu").contiguous().clone()


def weights_path(path: str | Path) -> Path:
    """Find the weights file of a checkpoint or bundle folder (safetensors first), or ``path`` when it is a file.

    Parameters
    ----------
    path : str or Path
        A checkpoint or bundle folder, or a weights file.

    Returns
    -------
    Path
        ``model.safetensors``, else the legacy ``model.pt``.

    Raises
    ------
    pipeline.runtime.errors.ArtifactError
        ``path`` is a missing file, or a folder with neither weights file.
    """
    path = Path(path)
    if not path.is_dir():
        if path.is_file():
            return path
        raise ArtifactError(f"{path}: no such weights file")
    for name in (WEIGHTS_FILE, LEGACY_WEIGHTS_FILE):
        if (path / name).is_file():
            return path / name
    raise ArtifactError(f"{path}: no {WEIGHTS_FILE} or {LEGACY_WEIGHTS_FILE} (not a trained checkpoint)")


def read_weights(path: str | Path) -> dict:
    """Read the payload of a checkpoint or bundle folder, or of one weights file.

    Parameters
    ----------
    path : str or Path
        A checkpoint or bundle folder, or a weights file.

    Returns
    -------
    dict
        ``state_dict``, ``config`` and the run's fields (a legacy ``model.pt`` unpickles tensors and plain data
        only).

    Raises
    ------
    pipeline.runtime.errors.ArtifactError
        One line naming the bad file: missing, unreadable, refused, or no ``state_dict``/``config``.
    """
    f = weights_path(path)
    payload = _read_legacy(f) if f.suffix == ".pt" else _read_safetensors(f)
    if not isinstance(payload, dict) or "state_dict" not in payload or not isinstance(payload.get("config"), dict):
        raise ArtifactError(f"{f}: not a GeoDistill checkpoint (no state_dict/config)")
    return payload


def _read_safetensors(f: Path) -> dict:
    """Read the payload of ``model.safetensors`` and the ``model.json`` beside it."""
    cfg_path = f.with_name(WEIGHTS_CONFIG_FILE)
    try:
        tensors = load_file(f, device="cpu")
    except (SafetensorError, OSError, ValueError) as e:
        raise ArtifactError(f"{f}: unreadable weights ({type(e).__name__})") from None
    try:
        doc = json.loads(cfg_path.read_text())
    except FileNotFoundError:
        raise ArtifactError(f"{f}: no {WEIGHTS_CONFIG_FILE} beside it (the model config)") from None
    except (OSError, ValueError) as e:
        raise ArtifactError(f"{cfg_path}: unreadable ({type(e).__name__})") from None
    if not isinstance(doc, dict):
        raise ArtifactError(f"{cfg_path}: not a model config (a JSON object)")
    geo = {k[len(GEOMETRY_PREFIX):]: v for k, v in tensors.items() if k.startswith(GEOMETRY_PREFIX)}
    state = {k: v for k, v in tensors.items() if not k.startswith(GEOMETRY_PREFIX)}
    fields = {k: v for k, v in doc.items() if k != "geometry_heads"}
    return {**fields, "state_dict": state, "geometry_state_dict": geo if doc.get("geometry_heads") else None}


def _read_legacy(f: Path) -> dict:
    """Read the dict of a legacy ``model.pt``, unpickling tensors and plain data only."""
    try:
        return torch.load(f, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        raise ArtifactError(f"{f}: refused: holds objects other than tensors and plain data "
                            "(loading it could execute code)") from None
    except Exception as e:
        raise ArtifactError(f"{f}: unreadable checkpoint ({type(e).__name__})") from None
