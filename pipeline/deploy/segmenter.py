"""Loading a checkpoint or a deploy bundle for inference: :class:`Segmenter` and its engines.

Decision (the paper is silent on deployment formats): engines (segment ``--engine``; one registry with
the benchmark, pipeline.deploy.engines): ``torch`` (the weights of a checkpoint or a bundle), ``cuda``
(the same weights: the GPU fast path), ``torchscript``, ``onnxruntime_fp32``, ``onnxruntime_int8`` and
``openvino_int8`` (bundle only; old names: :data:`pipeline.deploy.engine_table.ENGINE_ALIASES`); ``auto`` =
onnxruntime_fp32 when the bundle holds model.onnx and onnxruntime imports, else torch -- exact engines
only -- and ``cuda`` on a CUDA device (:func:`resolve_engine`).
Every engine receives the same preprocessed tensor and the same tau; only the function Z = f(x)
differs.

Per-frame confidence: :func:`pipeline.deploy.confidence.frame_confidence` (``score`` and
``predict(..., return_score=True)``).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable

import numpy as np

from pipeline.datasets.loading import check_bit_depth, pixel_limit, probs_to_size, read_rgb, resize_image, to_rgb8
from pipeline.deploy.confidence import CONFIDENCE_BAND, confidence_rank_check, frame_confidence  # noqa: F401
from pipeline.deploy.bundle import INT8_FILE, ONNX_FILE, checkpoint_resolution, is_deploy_bundle, read_deploy_info
from pipeline.deploy.engines import ENGINES, Source
from pipeline.deploy.mask_path import onnx_unavailable_reason
from pipeline.runtime.errors import CHECKPOINT, ArtifactError, InputError
from pipeline.evaluation.inference import images_to_tensor, load_student
from pipeline.deploy.engine_table import AUTO, ENGINE_CHOICES, MODEL_ENGINES, engine_name
from pipeline.params import PAPER
from pipeline.thresholds import mask_from_probs, resolve_resolution, resolve_tau, tau_candidates


@dataclasses.dataclass
class Segmenter:
    """A loaded mask path: ``predict_probs(images uint8 [N,R,R,3]) -> P float32 [N,R,R]``.

    ``engine`` is what computes Z = f(x) (module docstring)."""

    engine: str
    resolution: int | None
    taus: dict  # tau candidates of the model (pipeline.thresholds.tau_candidates): {source: (tau, text)}
    predict_logits: Callable  # float32 tensor [N,3,R,R] -> numpy float32 [N,1,R,R]
    info: dict
    tau: float | None = None  # the tau :meth:`predict` binarises with (set by :meth:`from_bundle`)
    tau_source: str = ""
    #: image files above this many pixels are refused on their header before decoding (None:
    #: ``data.max_pixels``'s default; :func:`pipeline.datasets.loading.read_rgb`)
    max_pixels: int | None = None
    #: how frames are read and resized, as the model's training images were (params ``data.bit_depth`` and
    #: ``data.letterbox``; a bundle records both, :meth:`from_bundle`): 16-bit frames' stated bit depth
    #: (:func:`pipeline.datasets.loading.scale_16bit`), and squash (False, the paper) or letterbox
    bit_depth: str | int = "auto"
    letterbox: bool = False

    def __repr__(self) -> str:
        """One short line (the dataclass default would print the whole deploy.json in ``info``)."""
        tau = "unset" if self.tau is None else f"{self.tau:.4g}"
        return f"Segmenter(engine={self.engine!r}, resolution={self.resolution}, tau={tau})"

    @classmethod
    def from_bundle(cls, path: str | Path, *, engine: str = "auto", device="cpu", tau: float | None = None,
                    resolution: int | None = None, max_pixels: int | None = None, bit_depth=None,
                    letterbox: bool | None = None) -> "Segmenter":
        """A segmenter for notebooks: a deploy bundle (``geodistill export`` / ``distill``) or a
        checkpoint directory (image files above ``max_pixels`` pixels are refused on their header; None =
        ``data.max_pixels``'s default), with its tau resolved once (:func:`pipeline.thresholds.resolve_tau`:
        ``tau`` > the bundle's > the checkpoint's > ``calibrate.fixed_tau`` 0.5 with a warning).
        ``bit_depth`` (auto, 10, 12, 14, 16) and ``letterbox`` default to what the bundle records
        (its ``frames``; a checkpoint or an older bundle: auto and squash).

        >>> seg = Segmenter.from_bundle("out/artifacts/deploy")          # doctest: +SKIP
        >>> mask = seg.predict("image.png")  # bool [H, W] at the image's own size   # doctest: +SKIP
        """
        seg = load_segmenter(path, engine, device, params=PAPER.model_dump())
        seg.max_pixels = pixel_limit(max_pixels)
        frames = seg.info.get("frames") or {}
        seg.bit_depth = check_bit_depth(frames.get("bit_depth", "auto") if bit_depth is None else bit_depth)
        seg.letterbox = bool(frames.get("letterbox", False) if letterbox is None else letterbox)
        seg.tau, seg.tau_source = seg.resolve_tau(option=tau)
        seg.resolution, _ = resolve_resolution(option=(resolution, "resolution="), recorded=(seg.resolution, str(path)),
                                               missing=f"{path}: no working resolution recorded; pass resolution=...")
        return seg

    def probabilities(self, image) -> np.ndarray:
        """P float32 [H,W] in [0,1] at the ORIGINAL size of ``image``: a file path, or an array of any
        size -- grey [H,W] / [H,W,1], RGB [H,W,3], RGBA [H,W,4] (alpha dropped); uint8, uint16 (/257),
        other integers (clipped to 0..255) or float in [0,1] -- read by the dataset loader's rules
        (:func:`pipeline.datasets.loading.to_rgb8`, 16-bit under :attr:`bit_depth`), resized to the
        working resolution like the training images (area; :attr:`letterbox`: padded to a square first),
        P resized back bilinearly (:func:`pipeline.datasets.loading.probs_to_size`, the pad cropped)."""
        probs, (h, w) = self.working_probabilities(image)
        return probs_to_size(probs, h, w, self.letterbox)

    def working_probabilities(self, image) -> tuple[np.ndarray, tuple[int, int]]:
        """(P float32 [R,R] at the working resolution, the frame's (height, width)): :meth:`probabilities`
        before the way back."""
        if self.resolution is None:
            raise InputError("Segmenter: no working resolution; set .resolution or use Segmenter.from_bundle")
        if isinstance(image, (str, Path)):
            rgb = read_rgb(image, max_pixels=self.max_pixels, bit_depth=self.bit_depth)
        else:
            arr = np.asarray(image)
            if arr.ndim == 3 and arr.shape[2] in (3, 4):  # RGB(A) -> the BGR(A) order to_rgb8 takes from OpenCV
                arr = arr[..., [2, 1, 0, 3][:arr.shape[2]]]
            rgb = to_rgb8(arr, bit_depth=self.bit_depth)
        probs = self.predict_probs(resize_image(rgb, self.resolution, self.letterbox)[None], batch_size=1)[0]
        return probs, rgb.shape[:2]

    def predict(self, image, *, return_score: bool = False):
        """The spacecraft mask M = [P >= tau] (eq:inference-mask), bool [H,W] at the ORIGINAL size of
        ``image`` (a path or an array, see :meth:`probabilities`); for a list or tuple of images, the
        list of their masks.  ``return_score``: ``(mask, score)`` (a list of them for a list) with the
        frame's confidence in [0, 1] (:func:`frame_confidence`, module docstring; low = don't trust it)."""
        tau = self._tau()
        if isinstance(image, (list, tuple)):
            return [self.predict(one, return_score=return_score) for one in image]
        probs, (h, w) = self.working_probabilities(image)
        mask = mask_from_probs(probs_to_size(probs, h, w, self.letterbox), tau)
        return (mask, frame_confidence(probs, tau)) if return_score else mask

    def score(self, image) -> float:
        """The frame's confidence in [0, 1] (:func:`frame_confidence`; low = don't trust this frame)."""
        return frame_confidence(self.working_probabilities(image)[0], self._tau())

    def _tau(self) -> float:
        if self.tau is None:
            raise InputError("Segmenter: no tau; use Segmenter.from_bundle (or set .tau)")
        return self.tau

    def resolve_tau(self, option=None) -> tuple[float, str]:
        """(tau, source) by :func:`pipeline.thresholds.resolve_tau` over ``option`` (--tau) and the
        model's candidates (:attr:`taus`, calibrated and fixed)."""
        return resolve_tau(option=option, **self.taus)

    def predict_probs(self, images: np.ndarray, batch_size: int = 8) -> np.ndarray:
        images = np.asarray(images)
        out = np.empty(images.shape[:3], np.float32)
        for s in range(0, len(images), batch_size):
            z = np.asarray(self.predict_logits(images_to_tensor(images[s:s + batch_size])), np.float32)
            out[s:s + batch_size] = 1.0 / (1.0 + np.exp(-z[:, 0]))
        return out


def resolve_engine(path: str | Path, engine: str, device=None) -> str:
    """The engine ``auto`` stands for (module docstring), or ``engine`` (an old name: its new one) after validation.

    auto: bundle -> onnxruntime_fp32 when model.onnx exists and onnxruntime imports, else torch; checkpoint
    directory -> torch (the only engine a checkpoint supports: anything else is an InputError naming
    --engine).  Decision: ``auto`` only picks engines whose masks are identical to PyTorch's; int8 is
    about 3x faster than ONNX fp32 but not exact (reduced synthetic protocol: validation Image IoU
    +0.002, yet a mean per-image IoU of 0.97 between its masks and fp32's), so it must be asked for
    with ``--engine onnxruntime_int8`` after checking ``geodistill benchmark``'s IoU columns on your data.
    ``openvino_int8`` is the same int8 file on OpenVINO (pipeline.deploy.openvino_engine).  On a CUDA
    ``device``, ``auto`` = ``cuda`` (pipeline.deploy.cuda_engine: bf16 + channels_last + CUDA graphs):
    on a GPU no engine reproduces the CPU's fp32 masks bit for bit anyway, and its masks are checked
    against fp32 on the GPU (benchmark's ``mIoU fp32``); ``--engine torch`` stays the fp32 reference.
    """
    path = Path(path)
    engine = engine_name(engine)
    if engine not in ENGINE_CHOICES:
        raise InputError(f"--engine {engine!r}: expected one of {', '.join(ENGINE_CHOICES)}")
    on_cuda = device is not None and str(device).startswith("cuda")
    if not is_deploy_bundle(path):
        if engine == AUTO:
            return "cuda" if on_cuda else "torch"
        if engine not in MODEL_ENGINES:
            raise InputError(f"--engine {engine}: needs a deploy bundle (geodistill export); {path} is a "
                             f"checkpoint directory, which supports --engine torch or cuda only")
        return engine
    if engine != AUTO:
        return engine
    if on_cuda:
        return "cuda"
    if onnx_unavailable_reason() is None and (path / ONNX_FILE).exists():
        return "onnxruntime_fp32"
    return "torch"


def load_segmenter(path: str | Path, engine: str = AUTO, device="cpu", thresholds: str | Path | None = None,
                   params: dict | None = None) -> Segmenter:
    """Open a checkpoint directory or a deploy bundle for inference with one engine.

    ``engine``: ``auto`` (:func:`resolve_engine`) or a name of :data:`pipeline.deploy.engine_table.SEGMENT_ENGINES`
    (the registry says what each runs).  tau candidates (``Segmenter.taus``, resolved
    by :meth:`Segmenter.resolve_tau`): :func:`pipeline.thresholds.tau_candidates` -- deploy.json's tau for
    a bundle; for a checkpoint its payload's tau, else its (method, seed) row in ``thresholds`` (a
    thresholds.parquet); and ``calibrate.fixed_tau`` of ``params`` (None: no fixed tau).  The resolution comes
    from deploy.json, or the checkpoint's payload (``payload["resolution"]``) or metadata -- the size the
    model was trained at; it stays None when none is recorded, and segment then asks for
    ``--resolution`` rather than guessing one.  ONNX engines run on the CPU.
    """
    import torch

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
    frames = info.get("frames") or {}  # read frames as the model's training images were (segment and from_bundle)
    return Segmenter(engine, resolution, taus, run, {**info, **runner.info},
                     bit_depth=check_bit_depth(frames.get("bit_depth", "auto")),
                     letterbox=bool(frames.get("letterbox", False)))


def predict_logits_torch(model, x, device) -> np.ndarray:
    """fp32 logits of a PyTorch TinyUNet; on CPU the input goes channels_last (as in
    pipeline.evaluation.inference.predict_probs, which calibrate uses), the model is converted by the caller."""
    import torch

    with torch.inference_mode():
        x = x.to(device)
        if device.type == "cpu":
            x = x.contiguous(memory_format=torch.channels_last)
        return model(x).float().cpu().numpy()
