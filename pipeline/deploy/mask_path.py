"""Export of the deployed mask path (TorchScript, ONNX) and its parity check against PyTorch.

The deployed function is Z = f(x), x float32 [B,3,H,W] RGB in [0, 1] (normalisation is inside the
model), M = [Z >= logit(tau)] (eq:inference-mask).

Decisions (the paper is silent on deployment formats):

* TorchScript is produced by ``torch.jit.trace`` of the mask path (TinyUNet holds a class-level
  normalisation constant and an optional training-only module, which ``torch.jit.script`` rejects);
  the traced graph reads sizes from the input, so it is batch- and size-generic.  It is saved
  unfrozen so that it still moves between devices.
* ONNX uses the TorchScript-based exporter (``torch.onnx.export(..., dynamo=False)``): torch 2.13
  defaults to the dynamo exporter, which needs ``onnxscript`` (not a dependency, not installed here).
  Both are traced from :class:`pipeline.model.ExportMaskPath`: the same function with the input
  normalisation folded into the first convolution (the graph input is the image).
* Parity (export time and tests): PyTorch, TorchScript and ONNX Runtime logits on deterministic
  smooth random images at the working resolution (batch 2, exercising the dynamic batch axis).
  Passing needs finite logits with max |dZ| <= ``atol``; then a mask pixel can only differ where the
  PyTorch logit lies within ``atol`` of logit(tau), i.e. by float round-off alone.  Strict mask
  equality at tau (``masks_identical``) and the number of differing pixels are reported alongside
  (and the tests require identical masks on their inputs).
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path

import numpy as np

from pipeline.deploy.cuda_engine import FastStudent
from pipeline.metrics import mask_agreement
from pipeline.model import ExportMaskPath, mask_path_model
from pipeline.thresholds import logit_threshold

ONNX_INPUT = "image"
ONNX_OUTPUT = "logits"


class ParityError(RuntimeError):
    """An exported model does not reproduce the PyTorch mask path (a bug, not a user error)."""


def export_module(model):
    """The exported form of the mask path (:class:`pipeline.model.ExportMaskPath`: same function,
    input normalisation folded into the first convolution), float32 CPU, eval mode."""
    return ExportMaskPath(mask_path_model(model)).eval().requires_grad_(False)


def parity_inputs(resolution: int, n: int = 2, seed: int = 0):
    """Deterministic smooth random RGB images float32 [n,3,R,R] in [0,1] (blobs plus fine noise),
    so that the parity check sees both foreground-like and background-like logits."""
    import torch

    g = torch.Generator().manual_seed(seed)
    low = torch.rand(n, 3, max(2, resolution // 8), max(2, resolution // 8), generator=g)
    x = torch.nn.functional.interpolate(low, size=(resolution, resolution), mode="bilinear",
                                        align_corners=False)
    x = 0.85 * x + 0.15 * torch.rand(n, 3, resolution, resolution, generator=g)
    return x.clamp_(0, 1).contiguous()


def onnx_unavailable_reason() -> str | None:
    """None when ONNX export and ONNX Runtime work here, else a one-line reason (install the extra)."""
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
    """Trace the mask path on a [1,3,R,R] example and save it (unfrozen, CPU weights), without debug
    records (:func:`save_without_debug_records`): the same model gives the same bytes in any folder."""
    import torch

    deployed = export_module(model)
    example = torch.zeros(1, deployed.config["in_channels"], resolution, resolution)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # TracerWarning; torch 2.13's deprecation notice for torch.jit
        traced = torch.jit.trace(deployed, example, check_trace=False)
    return save_without_debug_records(traced, path)


# Records torch's own writer adds at the end of every archive (copying them would write them twice).
_WRITER_RECORDS = ("version", "byteorder", ".data/serialization_id")


def save_without_debug_records(module, path: str | Path) -> Path:
    """``torch.jit.save`` of ``module`` to ``path`` minus its ``*.debug_pkl`` records.

    Those records hold the source ranges of the traced code: absolute paths of our files and of
    torch's (in the virtual environment), so the same model exported from two clones gave two files
    (and a DVC output that moved with the checkout's folder).  They serve error messages only;
    ``torch.jit.load`` does without them.  The archive is rewritten by torch's own zip writer
    (``torch._C.PyTorchFileWriter``, the one ``torch.jit.save`` uses: aligned records, its own
    version and serialization id), record for record in the original order.
    """
    import torch

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
    """Export the mask path to ONNX (input ``image`` [B,3,H,W] float32, output ``logits`` [B,1,H,W]),
    batch, height and width dynamic, with the TorchScript-based exporter (module docstring)."""
    import torch

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
    """ONNX Runtime CPU session; ``threads`` defaults to torch's intra-op thread count (same budget).

    ``spinning=False`` stops ORT's idle thread pools from busy-waiting between calls (session config
    ``session.intra_op.allow_spinning`` / ``session.inter_op.allow_spinning`` = 0): for timing, where an
    idle spinning pool would steal the cores that the other variants are measured on."""
    import onnxruntime as ort
    import torch

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
    """torch.jit.load in eval mode (torch 2.13 marks TorchScript deprecated; the notice is silenced)."""
    import torch

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return torch.jit.load(str(path), map_location=device).eval()


def torch_logits(model, x) -> np.ndarray:
    import torch

    with torch.inference_mode():
        return model(x).float().cpu().numpy()


def compare_logits(reference: np.ndarray, logits: np.ndarray, tau: float, atol: float) -> dict:
    """Parity of exported ``logits`` against the PyTorch ``reference`` at threshold tau (module docstring).

    Masks at tau are [Z >= logit(tau)] (eq:inference-mask)."""
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
    """Run the parity check of the exported files against the PyTorch mask path (module docstring).

    Returns ``{"inputs": ..., "torchscript": {...}, "onnx": {...}}`` (a format's entry is absent when its
    file is not given).  With a CUDA ``device`` also ``"device"``: :func:`device_parity` there (reported,
    not required: the GPU's fp32 is not the CPU's bit for bit).  Does not raise; see :func:`require_parity`.
    """
    import torch

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
    """Parity on the device the model will run on: the fp32 PyTorch mask path there (TF32 off) is the
    reference; compared with it, the TorchScript file on that device and the fast engine
    (pipeline.deploy.cuda_engine, bf16 + CUDA graphs): max |dZ|, masks identical, and ``mask_iou`` =
    mean per-image IoU of the masks at tau (:func:`pipeline.metrics.mask_agreement`).
    TF32 is switched off for the fp32 comparisons: with it (PyTorch's cuDNN default) two fp32 engines
    disagree on about 2 % of a mask's pixels.  Runs on a CPU too (then the fast engine is fp32 eager)."""
    import torch

    dev = torch.device(device)
    x = parity_inputs(resolution)
    z_tau = logit_threshold(tau)
    out: dict = {"device": str(dev)}
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
