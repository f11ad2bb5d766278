"""A checkpoint or a deploy bundle loaded for inference with one engine: :class:`Segmenter`.

Every engine receives the same preprocessed tensor and the same tau; only Z = f(x) differs.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from pipeline.datasets.loading import check_bit_depth, pixel_limit, probs_to_size, read_rgb, resize_image, to_rgb8
from pipeline.deploy.confidence import frame_confidence
from pipeline.deploy.bundle import (INT8_FILE, ONNX_FILE, checkpoint_resolution, frame_reading, is_deploy_bundle,
                                   read_deploy_info)
from pipeline.deploy.engines import ENGINES, Source
from pipeline.deploy.mask_path import onnx_unavailable_reason
from pipeline.runtime.errors import CHECKPOINT, ArtifactError, InputError
from pipeline.evaluation.inference import images_to_tensor, load_student
from pipeline.engine_table import AUTO, ENGINE_CHOICES, MODEL_ENGINES, engine_name
from pipeline.params import PAPER
from pipeline.thresholds import mask_from_probs, resolve_resolution, resolve_tau, tau_candidates

__all__ = ["Segmenter", "resolve_engine", "load_segmenter"]


@dataclasses.dataclass
class Segmenter:
    """A loaded mask path: images in, probabilities or masks (eq:inference-mask) out.

    Frames are read and resized as the model's training images were (``bit_depth``, ``letterbox``); results come
    back at each image's own size.  Build one with :meth:`from_bundle`.

    Attributes
    ----------
    engine : str
        The engine's name (``pipeline.engine_table``).
    resolution : int or None
        The working resolution R (None: not recorded; :meth:`from_bundle` requires one).
    taus : dict
        The model's tau candidates ``{source: (tau, text)}`` (:func:`pipeline.thresholds.tau_candidates`).
    predict_logits : callable
        float32 tensor [N,3,R,R] -> numpy float32 logits [N,1,R,R].
    info : dict
        The bundle's deploy.json (for a checkpoint: its method and seed) with the engine's details.
    tau : float or None
        The threshold :meth:`predict` binarises with (set by :meth:`from_bundle`).
    tau_source : str
        Where ``tau`` came from.
    max_pixels : int or None
        Larger image files are refused on their header (None: ``data.max_pixels``).
    bit_depth : str or int
        Bits a 16-bit frame's sensor fills, or ``"auto"`` (``data.bit_depth`` unless given).
    letterbox : bool
        Whether frames are letterboxed (aspect kept) rather than stretched to R x R (``data.letterbox`` unless
        given).
    """

    engine: str
    resolution: int | None
    taus: dict  # {source: (tau, text)}: pipeline.thresholds.tau_candidates
    predict_logits: Callable  # float32 tensor [N,3,R,R] -> numpy float32 [N,1,R,R]
    info: dict
    tau: float | None = None  # what predict binarises with (set by from_bundle)
    tau_source: str = ""
    max_pixels: int | None = None  # larger image files are refused on their header (None: data.max_pixels)
    bit_depth: str | int = PAPER.data.bit_depth
    letterbox: bool = PAPER.data.letterbox

    def __repr__(self) -> str:
        """Return one short line, without the deploy.json in ``info``."""
        tau = "unset" if self.tau is None else f"{self.tau:.4g}"
        return f"Segmenter(engine={self.engine!r}, resolution={self.resolution}, tau={tau})"

    @classmethod
    def from_bundle(cls, path: str | Path, *, engine: str = AUTO, device="cpu", tau: float | None = None,
                    resolution: int | None = None, max_pixels: int | None = None, bit_depth=None,
                    letterbox: bool | None = None) -> "Segmenter":
        """Open a deploy bundle or a checkpoint folder for notebooks, tau and resolution resolved once.

        tau: ``tau`` > the bundle's > the checkpoint's > ``calibrate.fixed_tau`` (with a warning).

        Parameters
        ----------
        path : str or Path
            A deploy bundle (``geodistill export``) or a checkpoint folder.
        engine : str, optional
            An engine of ``pipeline.engine_table.ENGINE_CHOICES``; ``"auto"`` (default) as :func:`resolve_engine`.
        device : str or torch.device, optional
            Where torch engines run (default ``"cpu"``).
        tau : float, optional
            A threshold in [0, 1] overriding the model's.
        resolution : int, optional
            A working resolution overriding the recorded one (>= 8).
        max_pixels : int, optional
            Refuse image files above this many pixels (None: ``data.max_pixels``).
        bit_depth : str or int, optional
            ``"auto"``, 10, 12, 14 or 16 (None: what the bundle records).
        letterbox : bool, optional
            None: what the bundle records.

        Returns
        -------
        Segmenter
            Ready to :meth:`predict`.

        Raises
        ------
        InputError
            The path is missing, the engine unknown or unavailable, an option invalid, no tau or no resolution
            is found.
        ArtifactError
            The bundle lacks the engine's model file.

        Examples
        --------
        >>> seg = Segmenter.from_bundle("out/artifacts/deploy")          # doctest: +SKIP
        >>> mask = seg.predict("image.png")  # bool [H, W] at the image's own size   # doctest: +SKIP
        """
        seg = load_segmenter(path, engine, device, params=PAPER.model_dump())
        seg.max_pixels = pixel_limit(max_pixels)
        seg.bit_depth = check_bit_depth(seg.bit_depth if bit_depth is None else bit_depth)
        seg.letterbox = seg.letterbox if letterbox is None else bool(letterbox)
        seg.tau, seg.tau_source = seg.resolve_tau(option=tau)
        seg.resolution, _ = resolve_resolution(option=(resolution, "resolution="), recorded=(seg.resolution, str(path)),
                                               missing=f"{path}: no working resolution recorded; pass resolution=...")
        return seg

    def probabilities(self, image) -> np.ndarray:
        """Return P at the original size of ``image``.

        Parameters
        ----------
        image : str, Path or array_like
            A file path, or an array (grey, RGB or RGBA; uint8, uint16, other integers, or float in [0, 1]) read by
            the dataset loader's rules.

        Returns
        -------
        numpy.ndarray
            float32 [H,W], P resized back bilinearly.

        Raises
        ------
        InputError
            No working resolution, or the image is unreadable or too large.
        """
        probs, (h, w) = self.working_probabilities(image)
        return probs_to_size(probs, h, w, self.letterbox)

    def working_probabilities(self, image) -> tuple[np.ndarray, tuple[int, int]]:
        """Return P at the working resolution with the frame's size.

        Parameters
        ----------
        image : str, Path or array_like
            As :meth:`probabilities`.

        Returns
        -------
        tuple
            (P float32 [R,R], (height, width) of the frame).

        Raises
        ------
        InputError
            ``resolution`` is unset, or the image is unreadable or too large.
        """
        if self.resolution is None:
            raise InputError("Segmenter: no working resolution; set .resolution or use Segmenter.from_bundle")
        if isinstance(image, (str, Path)):
            rgb = read_rgb(image, max_pixels=self.max_pixels, bit_depth=self.bit_depth)
        else:
            arr = np.asarray(image)
            if arr.ndim == 3 and arr.shape[2] in (3, 4):  # to_rgb8 takes OpenCV's BGR(A) order
                arr = arr[..., [2, 1, 0, 3][:arr.shape[2]]]
            rgb = to_rgb8(arr, bit_depth=self.bit_depth)
        probs = self.predict_probs(resize_image(rgb, self.resolution, self.letterbox)[None], batch_size=1)[0]
        return probs, rgb.shape[:2]

    def predict(self, image, *, return_score: bool = False):
        """Predict the mask M = [P >= tau] (eq:inference-mask) at the original size of ``image``.

        Parameters
        ----------
        image : str, Path, array_like, or list of them
            As :meth:`probabilities`; a list or tuple gives a list.
        return_score : bool, optional
            Also return the frame confidence (:func:`pipeline.deploy.confidence.frame_confidence`).

        Returns
        -------
        numpy.ndarray or tuple or list
            bool [H,W]; ``(mask, confidence)`` with ``return_score``; a list for a list.

        Raises
        ------
        InputError
            ``tau`` or ``resolution`` is unset, or an image is unreadable or too large.
        """
        tau = self._tau()
        if isinstance(image, (list, tuple)):
            return [self.predict(one, return_score=return_score) for one in image]
        probs, (h, w) = self.working_probabilities(image)
        mask = mask_from_probs(probs_to_size(probs, h, w, self.letterbox), tau)
        return (mask, frame_confidence(probs, tau)) if return_score else mask

    def score(self, image) -> float:
        """Return the frame's confidence in [0, 1] (:func:`pipeline.deploy.confidence.frame_confidence`).

        Parameters
        ----------
        image : str, Path or array_like
            As :meth:`probabilities`.

        Returns
        -------
        float
            The confidence.

        Raises
        ------
        InputError
            ``tau`` or ``resolution`` is unset, or the image is unreadable or too large.
        """
        return frame_confidence(self.working_probabilities(image)[0], self._tau())

    def _tau(self) -> float:
        if self.tau is None:
            raise InputError("Segmenter: no tau; use Segmenter.from_bundle (or set .tau)")
        return self.tau

    def resolve_tau(self, option=None) -> tuple[float, str]:
        """Resolve tau over ``option`` and the model's candidates (:func:`pipeline.thresholds.resolve_tau`).

        Parameters
        ----------
        option : float, optional
            A ``--tau`` value, first in order.

        Returns
        -------
        tuple
            (tau, source text).

        Raises
        ------
        InputError
            No candidate, or an invalid one.
        """
        return resolve_tau(option=option, **self.taus)

    def predict_probs(self, images: np.ndarray, batch_size: int = 8) -> np.ndarray:
        """Return P for images already at the working resolution, in batches.

        Parameters
        ----------
        images : array_like
            uint8 RGB [N,R,R,3].
        batch_size : int, optional
            Images per engine call (default 8).

        Returns
        -------
        numpy.ndarray
            float32 [N,R,R].
        """
        images = np.asarray(images)
        out = np.empty(images.shape[:3], np.float32)
        for s in range(0, len(images), batch_size):
            z = np.asarray(self.predict_logits(images_to_tensor(images[s:s + batch_size])), np.float32)
            out[s:s + batch_size] = 1.0 / (1.0 + np.exp(-z[:, 0]))
        return out


def resolve_engine(path: str | Path, engine: str, device=None) -> str:
    """Validate an engine name, or say what ``auto`` stands for.

    ``auto``: ``cuda`` on a CUDA device, else ``onnxruntime_fp32`` for a bundle with model.onnx when
    onnxruntime is installed, else ``torch`` -- engines whose masks are PyTorch's, never int8
    (docs/performance.md).  An old engine name gives its new one.

    Parameters
    ----------
    path : str or Path
        The bundle or checkpoint folder.
    engine : str
        The requested engine, or ``"auto"``.
    device : str or torch.device, optional
        The device the caller runs on.

    Returns
    -------
    str
        The engine's name.

    Raises
    ------
    InputError
        The engine is unknown, or needs a deploy bundle and ``path`` is a checkpoint folder.
    """
    path = Path(path)
    engine = engine_name(engine)
    if engine not in ENGINE_CHOICES:
        raise InputError(f"--engine {engine!r}: expected one of {', '.join(ENGINE_CHOICES)}")
    bundle = is_deploy_bundle(path)
    if engine != AUTO:
        if not bundle and engine not in MODEL_ENGINES:
            raise InputError(f"--engine {engine}: needs a deploy bundle (geodistill export); {path} is a "
                             f"checkpoint directory, which supports --engine torch or cuda only")
        return engine
    if device is not None and str(device).startswith("cuda"):
        return "cuda"
    if bundle and onnx_unavailable_reason() is None and (path / ONNX_FILE).exists():
        return "onnxruntime_fp32"
    return "torch"


def load_segmenter(path: str | Path, engine: str = AUTO, device="cpu", thresholds: str | Path | None = None,
                   params: dict | None = None) -> Segmenter:
    """Open a checkpoint folder or a deploy bundle with one engine (:func:`resolve_engine`).

    The tau candidates come from :func:`pipeline.thresholds.tau_candidates`; the resolution is the one recorded
    with the model, else None (never guessed); tau is not resolved here.

    Parameters
    ----------
    path : str or Path
        A checkpoint folder or a deploy bundle.
    engine : str, optional
        An engine name or ``"auto"`` (default).
    device : str or torch.device, optional
        Where torch engines run (default ``"cpu"``).
    thresholds : str or Path, optional
        A checkpoint's thresholds table (a tau candidate).
    params : dict, optional
        Params whose ``calibrate.fixed_tau`` is the last tau candidate.

    Returns
    -------
    Segmenter
        Without ``tau`` set.

    Raises
    ------
    InputError
        ``path`` does not exist, the engine is unknown, or it is unavailable here.
    ArtifactError
        The bundle lacks the engine's model file.
    """
    path = Path(path)
    if not path.exists():
        raise InputError("{}: not found", CHECKPOINT(path))
    engine = resolve_engine(path, engine, device)
    spec = ENGINES[engine]
    device = torch.device(device)
    bundle = is_deploy_bundle(path)
    info = read_deploy_info(path) if bundle else {}
    resolution = info.get("resolution")
    taus = tau_candidates(bundle=info, params=params) if bundle else {}
    model = None
    if spec.needs == "model":
        model, payload = load_student(path, "cpu")
        resolution = resolution if resolution is not None else checkpoint_resolution(path, payload)
        taus = taus if "bundle" in taus else tau_candidates(payload=payload, thresholds=thresholds, params=params)
        info = info or {"method": payload.get("method"), "seed": payload.get("seed")}
    elif (reason := spec.requires()) is not None:
        raise InputError(f"--engine {engine}: {reason}")
    elif not (path / spec.needs).exists():
        why = {INT8_FILE: info.get("int8_note") or "exported without it",
               ONNX_FILE: info.get("onnx_note") or "exported without onnx"}.get(spec.needs)
        raise ArtifactError(f"{path}: no {spec.needs}" + (f" ({why}); use --engine torch" if why else ""))
    source = Source(model, device, resolution, {spec.needs: path / spec.needs} if spec.needs != "model" else {})
    runner = spec.load(source)

    def run(x):
        return runner.run(x).float().cpu().numpy()
    frames = frame_reading(info.get("frames"))
    return Segmenter(engine, resolution, taus, run, {**info, **runner.info},
                     bit_depth=check_bit_depth(frames["bit_depth"]), letterbox=frames["letterbox"])
