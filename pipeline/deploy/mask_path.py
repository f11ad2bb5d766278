"""The deployed mask path Z = f(x) (x float32 [B,3,H,W] RGB in [0, 1]; M = [Z >= logit(tau)],
eq:inference-mask) exported to TorchScript and ONNX, and its parity with PyTorch (docs/decisions.md)."""

from __future__ import annotations

import io
import warnings
from pathlib import Path

import numpy as np
import torch

from pipeline.deploy.cuda_engine import FastStudent
from pipeline.metrics import mask_agreement
from pipeline.model import ExportMaskPath, mask_path_model
from pipeline.thresholds import logit_threshold

ONNX_INPUT = "image"
ONNX_OUTPUT = "logits"


class ParityError(RuntimeError):
    """An exported model does not reproduce the PyTorch mask path (a bug, not a user error)."""


def export_module(model):
    """The mask path with its normalisation folded into the first convolution, float32 CPU, eval mode."""
    return ExportMaskPath(mask_path_model(model)).eval().requires_grad_(False)


def parity_inputs(resolution: int, n: int = 2, seed: int = 0):
    """Deterministic smooth random RGB images float32 [n,3,R,R] in [0,1]: blobs plus fine noise."""
    g = torch.Generator().manual_seed(seed)
    low = torch.rand(n, 3, max(2, resolution // 8), max(2, resolution // 8), generator=g)
    x = torch.nn.functional.interpolate(low, size=(resolution, resolution), mode="bilinear",
                                        align_corners=False)
    x = 0.85 * x + 0.15 * torch.rand(n, 3, resolution, resolution, generator=g)
    return x.clamp_(0, 1).contiguous()


def onnx_unavailable_reason() -> str | None:
    """None when ONNX export and ONNX Runtime work here, else why not (naming the extra)."""
    missing = []
    for mod in ("onnx", "onnxruntime"):
        try:
            __import__(mod)
        except Exception:  # noqa: BLE001 -- ImportError or a broken binary wheel
            missing.append(mod)
    if missing:
        return (f"{' and '.join(missing)} not importable; ONNX export/benchmark skipped "
                f"(install the extra: pip install 'geodistill-refine[onnx]')")
    return None


def export_torchscript(model, path: str | Path, resolution: int) -> Path:
    """The traced mask path saved unfrozen (it still moves between devices), without debug records."""
    deployed = export_module(model)
    example = torch.zeros(1, deployed.config["in_channels"], resolution, resolution)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # TracerWarning; torch 2.13's deprecation notice for torch.jit
        traced = torch.jit.trace(deployed, example, check_trace=False)
    return save_without_debug_records(traced, path)


# records torch's own writer adds to every archive (copied, they would be written twice)
_WRITER_RECORDS = ("version", "byteorder", ".data/serialization_id")


def save_without_debug_records(module, path: str | Path) -> Path:
    """``torch.jit.save`` minus the ``*.debug_pkl`` records (absolute source paths), by torch's own zip writer."""
    buf = io.BytesIO()
    torch.jit.save(module, buf)
    buf.seek(0)
    reader = torch._C.PyTorchFileReader(buf)
    writer = torch._C.PyTorchFileWriter(str(path))
    for name in reader.get_all_records():
        if name.endswith(".debug_pkl") or name in _WRITER_RECORDS:
            continue
        data = reader.get_record(name)
        writer.write_record(name, data, len(data))
    writer.write_end_of_file()
    del writer  # closes the file
    return Path(path)


def export_onnx(model, path: str | Path, resolution: int, opset: int) -> Path:
    """The mask path in ONNX, batch, height and width dynamic (the TorchScript-based exporter)."""
    deployed = export_module(model)
    example = torch.zeros(1, deployed.config["in_channels"], resolution, resolution)
    axes = {0: "batch", 2: "height", 3: "width"}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # deprecation notice of the TorchScript-based exporter
        torch.onnx.export(deployed, (example,), str(path), opset_version=int(opset), dynamo=False,
                          input_names=[ONNX_INPUT], output_names=[ONNX_OUTPUT],
                          dynamic_axes={ONNX_INPUT: axes, ONNX_OUTPUT: axes}, do_constant_folding=True)
    return Path(path)


def ort_session(path: str | Path, threads: int | None = None, optimize: bool = True, spinning: bool = True):
    """ONNX Runtime CPU session with torch's thread count unless ``threads``; ``spinning=False``: idle pools sleep."""
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = int(threads or torch.get_num_threads())
    so.inter_op_num_threads = 1
    so.log_severity_level = 3
    if not spinning:
        so.add_session_config_entry("session.intra_op.allow_spinning", "0")
        so.add_session_config_entry("session.inter_op.allow_spinning", "0")
    so.graph_optimization_level = (ort.GraphOptimizationLevel.ORT_ENABLE_ALL if optimize
                                   else ort.GraphOptimizationLevel.ORT_DISABLE_ALL)
    return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])


def load_torchscript(path: str | Path, device="cpu"):
    """torch.jit.load in eval mode, torch 2.13's deprecation notice silenced."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return torch.jit.load(str(path), map_location=device).eval()


def torch_logits(model, x) -> np.ndarray:
    with torch.inference_mode():
        return model(x).float().cpu().numpy()


def compare_logits(reference: np.ndarray, logits: np.ndarray, tau: float, atol: float) -> dict:
    """Parity of ``logits`` with the PyTorch ``reference``: finite and max |dZ| <= ``atol``; the masks
    [Z >= logit(tau)] (eq:inference-mask) compared too."""
    reference = np.asarray(reference, np.float64)
    logits = np.asarray(logits, np.float64)
    if reference.shape != logits.shape:
        return {"passed": False, "max_abs_diff": float("inf"), "atol": float(atol), "masks_identical": False,
                "mask_pixels_differ": -1, "note": f"shape {logits.shape} != {reference.shape}"}
    finite = bool(np.isfinite(logits).all())
    diff = float(np.max(np.abs(reference - logits))) if reference.size and finite else (0.0 if finite else float("inf"))
    z_tau = logit_threshold(tau)
    differ = (reference >= z_tau) != (logits >= z_tau)
    return {"passed": bool(finite and diff <= atol), "max_abs_diff": diff, "atol": float(atol),
            "masks_identical": bool(not differ.any()), "mask_pixels_differ": int(np.count_nonzero(differ)),
            "pixels": int(reference.size)}


def check_parity(model, tau: float, resolution: int, atol: float, torchscript: str | Path | None = None,
                 onnx: str | Path | None = None, device=None) -> dict:
    """:func:`compare_logits` of each given file on :func:`parity_inputs`; on a CUDA ``device`` also
    :func:`device_parity` (reported only).  Does not raise (:func:`require_parity`)."""
    x = parity_inputs(resolution)
    ref = torch_logits(mask_path_model(model), x)
    out: dict = {"inputs": f"{x.shape[0]} deterministic smooth random images {resolution}x{resolution} (seed 0)",
                 "tau": float(tau)}
    if torchscript is not None:
        ts = load_torchscript(torchscript, "cpu")
        out["torchscript"] = compare_logits(ref, torch_logits(ts, x), tau, atol)
    if onnx is not None:
        sess = ort_session(onnx)
        out["onnx"] = compare_logits(ref, sess.run(None, {ONNX_INPUT: x.numpy()})[0], tau, atol)
    if device is not None and torch.device(device).type == "cuda":
        out["device"] = device_parity(model, tau, resolution, atol, device, torchscript)
    return out


def device_parity(model, tau: float, resolution: int, atol: float, device, torchscript=None) -> dict:
    """The TorchScript file and the fast engine on ``device`` against the fp32 PyTorch mask path there, with
    ``mask_iou`` (:func:`pipeline.metrics.mask_agreement`)."""
    dev = torch.device(device)
    x = parity_inputs(resolution)
    z_tau = logit_threshold(tau)
    out: dict = {"device": str(dev)}
    # with TF32 (cuDNN's default) two fp32 engines disagree on about 2 % of a mask's pixels
    tf32 = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    try:
        ref = torch_logits(mask_path_model(model).to(dev), x.to(dev))
        if torchscript is not None:
            ts_z = torch_logits(load_torchscript(torchscript, dev), x.to(dev))
            out["torchscript"] = {**compare_logits(ref, ts_z, tau, atol), "mask_iou": mask_agreement(ts_z, ref, z_tau)}
    finally:
        torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = tf32
    fast = FastStudent(model, dev)
    fz = fast.logits(x).float().cpu().numpy()
    out["fast_engine"] = {**compare_logits(ref, fz, tau, atol), "precision": fast.precision,
                          "cuda_graphs": fast.cuda_graphs, "mask_iou": mask_agreement(fz, ref, z_tau)}
    return out


def require_parity(parity: dict) -> None:
    """Raise :class:`ParityError` when a checked format failed its parity check."""
    for fmt in ("torchscript", "onnx"):
        res = parity.get(fmt)
        if res is not None and not res["passed"]:
            raise ParityError(f"{fmt} export differs from PyTorch: max |dZ| = {res['max_abs_diff']:.3g} "
                              f"(atol {res.get('atol')}), {res['mask_pixels_differ']} mask pixels differ at tau")
