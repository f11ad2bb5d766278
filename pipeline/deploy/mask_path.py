"""The deployed mask path exported to TorchScript and ONNX, and its parity with PyTorch (docs/decisions.md).

The mask path is Z = f(x), x float32 [B,3,H,W] RGB in [0, 1]; its mask is M = [Z >= logit(tau)], the same as
[sigmoid(Z) >= tau] (eq:inference-mask).
"""

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

__all__ = ["ONNX_INPUT", "ONNX_OUTPUT", "ParityError", "parity_inputs", "onnx_unavailable_reason", "export_torchscript",
           "export_onnx", "ort_session", "load_torchscript", "torch_logits", "compare_logits", "check_parity",
           "device_parity", "require_parity"]

#: the ONNX model's input and output names
ONNX_INPUT = "image"
ONNX_OUTPUT = "logits"


class ParityError(RuntimeError):
    """An exported model does not reproduce the PyTorch mask path (a bug, not a user error)."""


def export_module(model):
    """Build the module exported: the mask path with its normalisation folded into the first convolution.

    Parameters
    ----------
    model : TinyUNet
        The student.

    Returns
    -------
    ExportMaskPath
        Float32 on the CPU, in eval mode, without gradients.
    """
    return ExportMaskPath(mask_path_model(model)).eval().requires_grad_(False)


def parity_inputs(resolution: int, n: int = 2,
                  seed: int = 0):  # not a param: the parity images' random stream
    """Draw deterministic smooth random RGB images: blobs plus fine noise.

    Parameters
    ----------
    resolution : int
        R, their side.
    n : int
        How many.
    seed : int
        The seed of their random stream.

    Returns
    -------
    torch.Tensor
        float32 [n,3,R,R] in [0, 1].
    """
    g = torch.Generator().manual_seed(seed)
    low = torch.rand(n, 3, max(2, resolution // 8), max(2, resolution // 8), generator=g)
    x = torch.nn.functional.interpolate(low, size=(resolution, resolution), mode="bilinear",
                                        align_corners=False)
    x = 0.85 * x + 0.15 * torch.rand(n, 3, resolution, resolution, generator=g)
    return x.clamp_(0, 1).contiguous()


def onnx_unavailable_reason() -> str | None:
    """Tell why ONNX export or ONNX Runtime cannot be used here.

    Returns
    -------
    str or None
        None when ``onnx`` and ``onnxruntime`` import, else which do not (naming the extra to install).
    """
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
    """Save the traced mask path as TorchScript, unfrozen (it still moves between devices), without debug records.

    Parameters
    ----------
    model : TinyUNet
        The student.
    path : str or Path
        The file written.
    resolution : int
        The side of the example image it is traced with.

    Returns
    -------
    Path
        ``path``.
    """
    deployed = export_module(model)
    example = torch.zeros(1, deployed.config["in_channels"], resolution, resolution)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # TracerWarning; torch 2.13's deprecation notice for torch.jit
        traced = torch.jit.trace(deployed, example, check_trace=False)
    return save_without_debug_records(traced, path)


# records torch's own writer adds to every archive (copied, they would be written twice)
_WRITER_RECORDS = ("version", "byteorder", ".data/serialization_id")


def save_without_debug_records(module, path: str | Path) -> Path:
    """Save like ``torch.jit.save``, less the ``*.debug_pkl`` records (absolute source paths), by torch's zip writer.

    Parameters
    ----------
    module : torch.jit.ScriptModule
        The scripted or traced module.
    path : str or Path
        The file written.

    Returns
    -------
    Path
        ``path``.
    """
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
    """Save the mask path as ONNX, batch, height and width dynamic (the TorchScript-based exporter).

    Parameters
    ----------
    model : TinyUNet
        The student.
    path : str or Path
        The file written.
    resolution : int
        The side of the example image it is exported with.
    opset : int
        The ONNX opset (``deploy.opset``).

    Returns
    -------
    Path
        ``path``.
    """
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
    """Open an ONNX Runtime CPU session.

    Parameters
    ----------
    path : str or Path
        The ONNX model.
    threads : int or None
        Intra-op threads; None: torch's thread count.
    optimize : bool
        Apply every graph optimisation (``ORT_ENABLE_ALL``); False disables them.
    spinning : bool
        Idle thread pools spin; False: they sleep.

    Returns
    -------
    onnxruntime.InferenceSession
        The session, on the CPU execution provider.
    """
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
    """Load a TorchScript file in eval mode, torch 2.13's deprecation notice silenced.

    Parameters
    ----------
    path : str or Path
        The TorchScript file.
    device : str or torch.device
        Where its tensors are mapped.

    Returns
    -------
    torch.jit.ScriptModule
        The module, in eval mode.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return torch.jit.load(str(path), map_location=device).eval()


def torch_logits(model, x) -> np.ndarray:
    """Run a module without gradients and return its output as numpy.

    Parameters
    ----------
    model : Callable
        The mask path (a torch module or TorchScript).
    x : torch.Tensor
        float32 [B,3,H,W] RGB in [0, 1], on the module's device.

    Returns
    -------
    np.ndarray
        The logits, float32 [B,1,H,W], on the CPU.
    """
    with torch.inference_mode():
        return model(x).float().cpu().numpy()


def compare_logits(reference: np.ndarray, logits: np.ndarray, tau: float, atol: float) -> dict:
    """Check the parity of ``logits`` with the PyTorch ``reference``.

    It passes when the logits are finite and max |dZ| <= ``atol``; the masks [Z >= logit(tau)]
    (eq:inference-mask) are compared too, and reported.

    Parameters
    ----------
    reference : np.ndarray
        The PyTorch mask path's logits.
    logits : np.ndarray
        The exported model's logits on the same inputs.
    tau : float
        The mask threshold.
    atol : float
        The largest absolute logit difference allowed (``deploy.parity_atol``).

    Returns
    -------
    dict
        ``passed``, ``max_abs_diff``, ``atol``, ``masks_identical``, ``mask_pixels_differ`` and ``pixels`` (a
        shape mismatch fails, with a ``note``).
    """
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
    """Check each given exported file against the PyTorch mask path on :func:`parity_inputs`.

    Each file is compared on the CPU by :func:`compare_logits`; on a CUDA ``device`` :func:`device_parity` is
    reported too.  It does not raise: :func:`require_parity` does.

    Parameters
    ----------
    model : TinyUNet
        The student.
    tau : float
        The mask threshold.
    resolution : int
        The side of the parity images.
    atol : float
        The largest absolute logit difference allowed (``deploy.parity_atol``).
    torchscript : str or Path or None
        The TorchScript file, when checked.
    onnx : str or Path or None
        The ONNX file, when checked.
    device : str or torch.device or None
        A device to report parity on as well (CUDA only).

    Returns
    -------
    dict
        ``inputs``, ``tau`` and the :func:`compare_logits` result of each format checked (``torchscript``,
        ``onnx``), plus ``device`` (:func:`device_parity`) on CUDA.
    """
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
    """Check the TorchScript file and the fast engine on ``device`` against the fp32 PyTorch mask path there.

    Parameters
    ----------
    model : TinyUNet
        The student.
    tau : float
        The mask threshold.
    resolution : int
        The side of the parity images.
    atol : float
        The largest absolute logit difference allowed.
    device : str or torch.device
        Where all three run (TF32 off for the fp32 pair).
    torchscript : str or Path or None
        The TorchScript file, when checked.

    Returns
    -------
    dict
        ``device``, ``fast_engine`` and (with ``torchscript``) ``torchscript``: each a :func:`compare_logits`
        result with ``mask_iou`` (:func:`pipeline.metrics.mask_agreement`).
    """
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
    """Raise when a checked format failed its parity check.

    Parameters
    ----------
    parity : dict
        A :func:`check_parity` result.

    Raises
    ------
    ParityError
        TorchScript or ONNX was checked and did not pass.
    """
    for fmt in ("torchscript", "onnx"):
        res = parity.get(fmt)
        if res is not None and not res["passed"]:
            raise ParityError(f"{fmt} export differs from PyTorch: max |dZ| = {res['max_abs_diff']:.3g} "
                              f"(atol {res.get('atol')}), {res['mask_pixels_differ']} mask pixels differ at tau")
