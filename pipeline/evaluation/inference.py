"""Student checkpoints and inference.

Saving, loading, the runs under ``checkpoints/``, batched inference of the mask path, and the validation images a
run reads.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np

from pipeline import catalog
from pipeline.artifacts.lineage import make_meta, require_same_run
from pipeline.artifacts.store import Artifact, artifact_dir, open_artifact, read_chunk_rows, write_parquet
from pipeline.catalog import META_FILE, TRAINING_LOG_FILE
from pipeline.params import PAPER
from pipeline.runtime.device import autocast, autocast_dtype
from pipeline.runtime.errors import ArtifactError, InputError

__all__ = ["iter_runs", "load_student", "images_to_tensor", "predict_probs", "save_checkpoint", "open_labelled_split",
           "REVIEW_MODE_KEY", "CORRECTED_VALIDATION", "validation_corrections", "require_mode",
           "corrected_validation", "with_validation_corrections", "active_runs"]


def iter_runs(checkpoints_dir: str | Path) -> Iterator[tuple[str, int, Path]]:
    """List every run under ``checkpoints/<method>/<seed>/`` that holds a checkpoint, sorted.

    Parameters
    ----------
    checkpoints_dir : str or Path
        The checkpoints folder.

    Yields
    ------
    tuple
        ``(method, seed, run folder)``; hidden folders and folders without metadata are passed over.

    Raises
    ------
    ArtifactError
        The folder does not exist (on the first step of the iteration).
    """
    root = Path(checkpoints_dir)
    if not root.exists():
        raise ArtifactError(f"{root}: checkpoints directory not found")
    for mdir in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")):
        for sdir in sorted((p for p in mdir.iterdir() if p.is_dir() and not p.name.startswith(".")),
                           key=lambda p: p.name):
            if (sdir / META_FILE).exists():
                yield mdir.name, int(sdir.name), sdir


def load_student(path: str | Path, device="cpu"):
    """Load a student's mask path from a checkpoint or bundle folder, or a weights file.

    Parameters
    ----------
    path : str or Path
        A checkpoint folder, a deploy bundle folder or a weights file.
    device : str or torch.device
        Where the model is placed.

    Returns
    -------
    tuple
        ``(TinyUNet in eval mode, payload)``; the payload holds the config, the state and what was recorded
        (method, seed, tau, ...).

    Raises
    ------
    ArtifactError
        Weights that do not build the model.
    """
    from pipeline.model import TinyUNet
    from pipeline.artifacts.weights import read_weights, weights_path

    pt = weights_path(path)
    payload = read_weights(pt)
    try:
        model = TinyUNet(**payload["config"])
        model.load_state_dict(payload["state_dict"])
    except Exception as e:
        raise ArtifactError(f"{pt}: unreadable checkpoint ({type(e).__name__})") from None
    model.to(device).eval()
    return model, payload


def images_to_tensor(images: np.ndarray):
    """Convert uint8 images [N,H,W,3] (or one [H,W,3]) to the model's input, float32 [N,3,H,W] in [0, 1].

    Parameters
    ----------
    images : numpy.ndarray
        uint8, channels last.

    Returns
    -------
    torch.Tensor
        float32 [N, 3, H, W], values / 255.

    Raises
    ------
    ValueError
        Images that are not uint8.
    """
    import torch

    arr = np.asarray(images)
    if arr.ndim == 3:
        arr = arr[None]
    if arr.dtype != np.uint8:
        raise ValueError(f"images must be uint8 NHWC, got {arr.dtype}")
    return torch.from_numpy(np.ascontiguousarray(arr)).permute(0, 3, 1, 2).float().div_(255.0)


def predict_probs(model, images, device="cpu", batch_size: int = 16, precision: str = "fp32",
                  channels_last: bool = PAPER.train.channels_last) -> np.ndarray:
    """Compute the mask path's probabilities P = sigmoid(Z) of uint8 images, a batch at a time.

    Parameters
    ----------
    model : torch.nn.Module
        The student (its mask path's logit Z on channel 0).
    images : array_like or zarr array
        uint8 [N, H, W, 3], read a batch at a time.
    device : str or torch.device
        Where the model runs.
    batch_size : int
        Images per forward pass.
    precision : str
        ``fp32``, or a mixed precision the device supports (:func:`pipeline.runtime.device.autocast_dtype`).
    channels_last : bool
        Run in channels-last memory format (``train.channels_last``).

    Returns
    -------
    numpy.ndarray
        P, float32 [N, H, W].
    """
    import torch

    device = torch.device(device)
    dtype = autocast_dtype(device, precision)
    model = model.to(device).eval()
    if channels_last:
        model = model.to(memory_format=torch.channels_last)
    n = images.shape[0]
    out = np.empty((n, images.shape[1], images.shape[2]), dtype=np.float32)
    with torch.inference_mode(), autocast(device, dtype):
        for s in range(0, n, batch_size):
            x = images_to_tensor(np.asarray(images[s:s + batch_size])).to(device)
            if channels_last:
                x = x.contiguous(memory_format=torch.channels_last)
            out[s:s + batch_size] = torch.sigmoid(model(x).float())[:, 0].cpu().numpy()
    return out


def save_checkpoint(path: str | Path, model, meta, log, **payload) -> Path:
    """Write a checkpoint folder atomically: the weights, model.json and the training log.

    Parameters
    ----------
    path : str or Path
        The checkpoint folder, replaced whole.
    model : TinyUNet
        The student (its mask path, and its geometry heads when it has them).
    meta : Meta
        The folder's ``checkpoint`` metadata; the training log's is derived from it.
    log : pandas.DataFrame
        The training log (one row per epoch).
    **payload
        JSON fields added to model.json (method, seed, stage, ...).

    Returns
    -------
    Path
        The folder written.
    """
    from pipeline.artifacts.weights import write_weights

    geo = model.geometry_heads.state_dict() if getattr(model, "geometry_heads", None) is not None else None
    with artifact_dir(path, meta) as tmp:
        write_weights(tmp, model.mask_path_state_dict(), model.config, geo, **payload)
        log_meta = make_meta("training_log", meta.stage, meta.code_version, meta.params,
                             [(str(path), meta)])
        write_parquet(tmp / TRAINING_LOG_FILE, log, log_meta)
    return Path(path)


def open_labelled_split(artifacts: str | Path, split: str, purpose: str, allow_empty: bool = False):
    """Open the prepared artifacts and find the ``split`` rows that have a reference mask.

    Parameters
    ----------
    artifacts : str or Path
        The artifacts folder.
    split : str
        ``train``, ``val`` or ``test``.
    purpose : str
        Completes the error's message (what needed the masks).
    allow_empty : bool
        Return no rows instead of refusing.

    Returns
    -------
    tuple
        ``(manifest, images, reference, indices)``: the opened artifacts and the rows' manifest indices.

    Raises
    ------
    InputError
        No ``split`` row has a reference mask, unless ``allow_empty``.
    """
    manifest = open_artifact(catalog.path("manifest", artifacts), "manifest")
    images = open_artifact(catalog.path("images", artifacts), "images")
    reference = open_artifact(catalog.path("reference", artifacts), "reference")
    require_same_run(manifest, images, reference)
    idx = np.flatnonzero((manifest.df["split"].to_numpy() == split) & reference.numpy("has_mask").astype(bool))
    if idx.size == 0 and not allow_empty:
        name = "validation" if split == "val" else split
        raise InputError(f"{manifest.path}: no {name} image has a reference mask; {purpose}")
    return manifest, images, reference, idx


REVIEW_MODE_KEY = "review.mode"
#: the review mode whose corrected images are validation masks (checkpoint selection, tau, the report)
VALIDATE = "validate"
#: the thresholds artifact's meta field counting the corrected images calibrate validated on
CORRECTED_VALIDATION = "corrected_validation"


def validation_corrections(artifacts: str | Path, review) -> Artifact | None:
    """Open the ``corrected`` artifact when the review's corrections are validation masks.

    Parameters
    ----------
    artifacts : str or Path
        The artifacts folder.
    review : Mapping or None
        The validated ``review:`` section.

    Returns
    -------
    Artifact or None
        The artifact when ``review.mode: validate`` with ``review.corrections`` set; else None.

    Raises
    ------
    InputError
        The artifact was written for another review mode (:func:`require_mode`).
    """
    if not (review and review.get("corrections") and review.get("mode") == VALIDATE):
        return None
    corrected = open_artifact(catalog.path("corrected", artifacts), "corrected")
    require_mode(corrected, VALIDATE)
    return corrected


def require_mode(corrected, mode: str) -> None:
    """Check that the opened ``corrected`` artifact was written for ``review.mode`` = ``mode``.

    Parameters
    ----------
    corrected : Artifact
        The opened ``corrected`` artifact.
    mode : str
        The review mode the params say.

    Raises
    ------
    InputError
        It was written for another mode: rerun the corrections stage.
    """
    if corrected.attrs.get("mode") != mode:
        raise InputError(f"{corrected.path}: written for {REVIEW_MODE_KEY}={corrected.attrs.get('mode')!r}, the "
                         f"params say {mode!r}; rerun the corrections stage")


def corrected_validation(corrected, images) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Read the corrected images and their masks, in ascending manifest row.

    Parameters
    ----------
    corrected : Artifact
        The opened ``corrected`` artifact.
    images : Artifact
        The opened images artifact.

    Returns
    -------
    tuple
        ``(image ids, images [M,R,R,C], masks bool [M,R,R])``.
    """
    rows = np.asarray(corrected["row"], dtype=np.int64)
    order = np.argsort(rows, kind="stable")  # chunk reads want ascending rows; keep ids in step
    ids = [list(corrected.attrs["image_ids"])[i] for i in order]
    return ids, read_chunk_rows(images["image"], rows[order]), np.asarray(corrected["mask"], dtype=bool)[order]


def with_validation_corrections(val_images: np.ndarray, val_masks: np.ndarray, corrected, images
                                ) -> tuple[np.ndarray, np.ndarray]:
    """Append the corrected images and masks to the validation ones.

    Parameters
    ----------
    val_images : numpy.ndarray
        Validation images [V, R, R, C].
    val_masks : numpy.ndarray
        Their reference masks [V, R, R].
    corrected : Artifact or None
        The opened ``corrected`` artifact (:func:`validation_corrections`); None: nothing appended.
    images : Artifact
        The opened images artifact.

    Returns
    -------
    tuple of numpy.ndarray
        ``(images, masks)``.
    """
    if corrected is None:
        return val_images, val_masks
    _, imgs, masks = corrected_validation(corrected, images)
    if len(val_images) == 0:
        return imgs, masks
    return np.concatenate([val_images, imgs]), np.concatenate([val_masks, masks])


def active_runs(checkpoints_dir: str | Path, purpose: str) -> list[tuple[str, int, Path]]:
    """List the trained runs (:func:`iter_runs`), refusing when there is none.

    Parameters
    ----------
    checkpoints_dir : str or Path
        The checkpoints folder.
    purpose : str
        What needs them, completing the error's message.

    Returns
    -------
    list of tuple
        ``(method, seed, run folder)`` per run.

    Raises
    ------
    InputError
        No trained checkpoint.
    """
    runs = list(iter_runs(checkpoints_dir))
    if not runs:
        raise InputError(f"{checkpoints_dir}: no trained checkpoint to {purpose}")
    return runs
