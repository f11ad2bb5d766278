"""Loading a checkpoint or a deploy bundle for inference: :class:`Segmenter` and its engines.

Decision (the paper is silent on deployment formats): engines (segment ``--engine``): ``torch``
(model.pt / checkpoint), ``torchscript``, ``onnx`` and ``int8`` (bundle only); ``auto`` = onnx when the
bundle holds it and onnxruntime imports, else torch -- exact engines only (:func:`resolve_engine`).
Every engine receives the same preprocessed tensor and the same tau; only the function Z = f(x)
differs.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable

import numpy as np

from pipeline.deploy.bundle import INT8_FILE, checkpoint_resolution, is_deploy_bundle, read_deploy_info
from pipeline.deploy.export import ONNX_INPUT, load_torchscript, onnx_unavailable_reason, ort_session
from pipeline.errors import ArtifactError, InputError
from pipeline.thresholds import lookup_tau, resolve_tau

ENGINES = ("auto", "torch", "torchscript", "onnx", "int8")


@dataclasses.dataclass
class Segmenter:
    """A loaded mask path: ``predict_probs(images uint8 [N,R,R,3]) -> P float32 [N,R,R]``.

    ``engine`` is what computes Z = f(x): torch, torchscript, onnx or int8 (module docstring)."""

    engine: str
    resolution: int | None
    taus: dict  # tau candidates found with the model: {"bundle" | "checkpoint" | "thresholds": (tau, source)}
    predict_logits: Callable  # float32 tensor [N,3,R,R] -> numpy float32 [N,1,R,R]
    info: dict

    def resolve_tau(self, option=None, fixed=None) -> tuple[float, str]:
        """(tau, source) by :func:`pipeline.thresholds.resolve_tau` over ``option`` (--tau), the
        candidates found with the model, and ``fixed`` (calibrate.fixed_tau)."""
        return resolve_tau(option=option, fixed=fixed, **self.taus)

    def predict_probs(self, images: np.ndarray, batch_size: int = 8) -> np.ndarray:
        from pipeline.inference import images_to_tensor

        images = np.asarray(images)
        out = np.empty(images.shape[:3], np.float32)
        for s in range(0, len(images), batch_size):
            z = np.asarray(self.predict_logits(images_to_tensor(images[s:s + batch_size])), np.float32)
            out[s:s + batch_size] = 1.0 / (1.0 + np.exp(-z[:, 0]))
        return out


def resolve_engine(path: str | Path, engine: str) -> str:
    """The engine ``auto`` stands for (module docstring), or ``engine`` itself after validation.

    auto: bundle -> onnx when model.onnx exists and onnxruntime imports, else torch; checkpoint
    directory -> torch (the only engine a checkpoint supports: anything else is an InputError naming
    --engine).  Decision: ``auto`` only picks engines whose masks are identical to PyTorch's; int8 is
    about 3x faster than ONNX fp32 but not exact (reduced synthetic protocol: validation Image IoU
    +0.002, yet a mean per-image IoU of 0.97 between its masks and fp32's), so it must be asked for
    with ``--engine int8`` after checking ``geodistill benchmark``'s IoU columns on your data.
    """
    path = Path(path)
    if engine not in ENGINES:
        raise InputError(f"--engine {engine!r}: expected one of {', '.join(ENGINES)}")
    if not is_deploy_bundle(path):
        if engine not in ("auto", "torch"):
            raise InputError(f"--engine {engine}: needs a deploy bundle (geodistill export); {path} is a "
                             f"checkpoint directory, which supports --engine torch only")
        return "torch"
    if engine != "auto":
        return engine
    if onnx_unavailable_reason() is None and (path / "model.onnx").exists():
        return "onnx"
    return "torch"


def load_segmenter(path: str | Path, engine: str = "auto", device="cpu",
                   thresholds: str | Path | None = None) -> Segmenter:
    """Open a checkpoint directory or a deploy bundle for inference with one engine.

    ``engine``: ``auto`` (:func:`resolve_engine`), ``torch`` (model.pt or the checkpoint),
    ``torchscript`` / ``onnx`` / ``int8`` (bundle only).  tau candidates (``Segmenter.taus``, resolved
    by :meth:`Segmenter.resolve_tau`): deploy.json's tau for a bundle; for a checkpoint its payload's
    tau, else its (method, seed) row in ``thresholds`` (a thresholds.parquet).  The resolution comes
    from deploy.json, or the checkpoint's payload (``payload["resolution"]``) or metadata -- the size the
    model was trained at; it stays None when none is recorded, and segment then asks for
    ``--resolution`` rather than guessing one.  ONNX engines run on the CPU.
    """
    import torch

    from pipeline.inference import load_student

    path = Path(path)
    if not path.exists():
        raise InputError(f"--checkpoint {path}: not found")
    engine = resolve_engine(path, engine)
    device = torch.device(device)
    if is_deploy_bundle(path):
        info = read_deploy_info(path)
        taus = {} if info.get("tau") is None else \
            {"bundle": (info["tau"], f"deploy bundle ({info.get('tau_source', '?')})")}
        resolution = info.get("resolution")
    else:
        info, taus, resolution = {}, {}, None

    if engine == "torch":
        model, payload = load_student(path, device)
        if device.type == "cpu":
            model = model.to(memory_format=torch.channels_last)
        if resolution is None:
            resolution = checkpoint_resolution(path, payload)
        if not taus:
            taus = checkpoint_taus(payload, thresholds)

        def run(x):
            # fp32, channels_last: the same path calibrate used to choose tau
            return predict_logits_torch(model, x, device)
        info = info or {"method": payload.get("method"), "seed": payload.get("seed")}
        return Segmenter("torch", resolution, taus, run, info)

    if engine == "torchscript":
        ts_path = path / "model.ts"
        if not ts_path.exists():
            raise ArtifactError(f"{path}: no model.ts")
        ts = load_torchscript(ts_path, device)

        def run(x):
            with torch.inference_mode():
                return ts(x.to(device)).float().cpu().numpy()
        return Segmenter("torchscript", resolution, taus, run, info)

    reason = onnx_unavailable_reason()
    if reason is not None:
        raise InputError(f"--engine {engine}: {reason}")
    onnx_file = path / (INT8_FILE if engine == "int8" else "model.onnx")
    if not onnx_file.exists():
        why = (info.get("int8_note") or "exported without it") if engine == "int8" else \
            (info.get("onnx_note") or "exported without onnx")
        raise ArtifactError(f"{path}: no {onnx_file.name} ({why}); use --engine torch")
    sess = ort_session(onnx_file)

    def run(x):
        return sess.run(None, {ONNX_INPUT: np.ascontiguousarray(x.numpy(), np.float32)})[0]
    return Segmenter(engine, resolution, taus, run, info)


def predict_logits_torch(model, x, device) -> np.ndarray:
    """fp32 logits of a PyTorch TinyUNet; on CPU the input goes channels_last (as in
    pipeline.inference.predict_probs, which calibrate uses), the model is converted by the caller."""
    import torch

    with torch.inference_mode():
        x = x.to(device)
        if device.type == "cpu":
            x = x.contiguous(memory_format=torch.channels_last)
        return model(x).float().cpu().numpy()


def checkpoint_taus(payload: dict, thresholds: str | Path | None) -> dict:
    """tau candidates of a checkpoint (for :func:`pipeline.thresholds.resolve_tau`): its payload's tau
    (``checkpoint``) and its (method, seed) row in the ``thresholds`` table when that file exists
    (``thresholds``).  The table is read only when the payload has no tau."""
    if payload.get("tau") is not None:
        return {"checkpoint": (float(payload["tau"]), "checkpoint payload")}
    if thresholds is None or not Path(thresholds).exists():
        return {}
    from pipeline.artifacts import open_artifact

    method, seed = payload.get("method"), payload.get("seed")
    found = lookup_tau(open_artifact(thresholds, "thresholds").df, method, seed)
    return {} if found is None else {"thresholds": (found, f"{thresholds} ({method}, seed {seed})")}
