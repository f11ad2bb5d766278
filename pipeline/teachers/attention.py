"""How the SAM 3 teacher's bf16 CPU path runs: where its attention runs, and its fused MLPs (``teacher.engine``).

On a 2-core avx512_bf16 host (no AMX), torch's bf16 flash-attention kernel was bound by its softmax: 52 % of the
default path's time at real size. OpenVINO's CPU plugin runs the same ``ScaledDotProductAttention`` as one fused
node, 2.2-3.1x faster on SAM 3's shapes (docs/performance.md, "The teacher's attention in OpenVINO"). So ``openvino`` runs
every unmasked bf16 attention call of transformers' ``modeling_sam3`` through a small OpenVINO graph (parameters
Q, K, V and the call's mask, one SDPA node, no weights: nothing to convert per checkpoint, nothing to cache on
disk); everything else stays in torch. A causal or dropout call, or an fp32 one, runs transformers' own SDPA.

On a 2-core AMX host the other way round: torch's bf16 kernel beat OpenVINO's on every shape, and what paid was
oneDNN running each MLP's activation inside its first linear layer (``onednn``,
:func:`pipeline.teachers.sam3.fused_mlp_activations`; docs/performance.md, "The teacher on AMX").

The rule of ``auto`` (:func:`pipeline.runtime.device.teacher_cpu_engine`) reads CPU flags, never a timing probe.
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import importlib.util
import logging

import numpy as np

from pipeline.runtime.device import teacher_cpu_engine
from pipeline.runtime.errors import InputError
from pipeline.teacher_table import TEACHER_ENGINES as ENGINES

__all__ = ["OPENVINO_ATTENTION_EVENT", "resolve_teacher_engine", "openvino_version", "onednn_fusion_available",
           "OpenVINOAttention", "attention_engine"]

log = logging.getLogger(__name__)

#: the profiler event of one OpenVINO attention call (benchmarks/bench_teacher.py counts it as attention)
OPENVINO_ATTENTION_EVENT = "openvino::scaled_dot_product_attention"


def openvino_version() -> str | None:
    """Return the installed OpenVINO distribution's version.

    Returns
    -------
    str or None
        The version; None where openvino is not installed.
    """
    if importlib.util.find_spec("openvino") is None:
        return None
    try:
        return importlib.metadata.version("openvino")
    except importlib.metadata.PackageNotFoundError:
        return None


def onednn_fusion_available() -> bool:
    """Say whether torch offers oneDNN's linear layer with a fused activation (``teacher.engine: onednn``).

    Returns
    -------
    bool
        True where torch is built with oneDNN and has ``torch.ops.mkldnn._linear_pointwise``.
    """
    import torch

    return torch.backends.mkldnn.is_available() and hasattr(torch.ops.mkldnn, "_linear_pointwise")


def resolve_teacher_engine(engine: str, device, dtype_name: str) -> tuple[str, str | None]:
    """Resolve ``teacher.engine`` for a teacher on ``device`` with weights in ``dtype_name``.

    ``openvino`` runs the bf16 attention only, ``onednn`` fuses the bf16 MLPs only: with fp32 weights, on CUDA,
    or without openvino installed (a torch without oneDNN's fused linear layer) each resolves to ``torch``, and
    the note says why in one line. ``auto`` follows :func:`pipeline.runtime.device.teacher_cpu_engine` on a CPU;
    CUDA always uses torch.

    Parameters
    ----------
    engine : str
        ``auto``, ``torch``, ``openvino`` or ``onednn``.
    device : str or torch.device
        The teacher's device.
    dtype_name : str
        The resolved weights' dtype, ``fp32`` or ``bf16``.

    Returns
    -------
    tuple of (str, str or None)
        (``"torch"``, ``"openvino"`` or ``"onednn"``, a one-line note where the engine asked is not the one that
        runs).

    Raises
    ------
    InputError
        ``engine`` is none of :data:`pipeline.teacher_table.TEACHER_ENGINES`.
    """
    import torch

    if engine not in ENGINES:
        raise InputError(f"teacher.engine={engine!r}: expected one of {', '.join(ENGINES)}")
    if engine == "torch":
        return "torch", None
    if torch.device(device).type != "cpu":
        return "torch", (None if engine == "auto" else f"teacher.engine {engine}: CPU only; torch runs on "
                         f"{torch.device(device).type}")
    wanted = teacher_cpu_engine(dtype_name) if engine == "auto" else engine
    if wanted == "openvino" and dtype_name != "bf16":
        return "torch", f"teacher.engine {engine}: OpenVINO runs the bf16 attention only; fp32 runs in torch"
    if wanted == "openvino" and openvino_version() is None:
        return "torch", (f"teacher.engine {engine}: openvino is not installed (pip install '.[sam3]'); attention "
                         "runs in torch")
    if wanted == "onednn" and dtype_name != "bf16":
        return "torch", f"teacher.engine {engine}: oneDNN fuses the bf16 MLPs only; fp32 runs in torch"
    if wanted == "onednn" and not onednn_fusion_available():
        return "torch", (f"teacher.engine {engine}: this torch has no oneDNN linear layer with a fused activation; "
                         "the MLPs run in torch")
    return wanted, None


class OpenVINOAttention:
    r"""transformers' attention-function signature, computed by OpenVINO's fused CPU attention for bf16 calls.

    :math:`\mathrm{softmax}(s\,QK^\top)V` per head, as torch's SDPA; Q, K and V are handed over without a
    copy where they are laid out [B, N, H, D] or [B, H, N, D] in memory, and the result is written straight into
    the [B, N, H, D] tensor transformers expects. A mask is a boolean one (True: attend, as torch's) or an additive
    bf16 bias, 4-D and broadcast over Q K^T's [B, H, N, M] (the DETR encoder's text padding, the DETR decoder's box
    bias). One compiled graph per (scale, layout, mask kind), dynamic shapes.

    Parameters
    ----------
    fallback : callable
        transformers' SDPA attention function: every call this class does not take (causal, dropout, not bf16,
        grouped heads, a mask of another kind).
    threads : int
        OpenVINO's inference threads (torch's count); one stream.
    """

    def __init__(self, fallback, threads: int):
        """Keep the fallback; OpenVINO is imported at the first call it takes."""
        self.fallback = fallback
        self.threads = int(threads)
        self._requests: dict[tuple[float, str, str | None], object] = {}

    def _request(self, scale: float, layout: str, mask: str | None):
        """Return the infer request for ``scale``, ``layout`` (``bnhd``, ``bhnd``), ``mask`` (None, bool, bias)."""
        key = (scale, layout, mask)
        if key not in self._requests:
            import openvino as ov
            import openvino.opset13 as ops

            params = [ops.parameter([-1, -1, -1, -1], ov.Type.bf16, name=n) for n in ("query", "key", "value")]
            perm = ops.constant(np.array([0, 2, 1, 3], dtype=np.int64))
            # fp32 in the graph, so that the scale is exact; the bf16 hint runs the fused node in bf16
            qkv = [ops.convert(ops.transpose(p, perm) if layout == "bnhd" else p, ov.Type.f32) for p in params]
            bias = None
            if mask is not None:
                params.append(ops.parameter([-1, -1, -1, -1], ov.Type.boolean if mask == "bool" else ov.Type.bf16,
                                            name="mask"))
                bias = params[-1] if mask == "bool" else ops.convert(params[-1], ov.Type.f32)
            out = ops.scaled_dot_product_attention(*qkv, bias, ops.constant(np.float32(scale)), causal=False)
            model = ov.Model([ops.convert(ops.transpose(out, perm), ov.Type.bf16)], params, "sam3_attention")
            compiled = ov.Core().compile_model(model, "CPU", {"INFERENCE_PRECISION_HINT": "bf16",
                                                              "INFERENCE_NUM_THREADS": self.threads,
                                                              "NUM_STREAMS": 1})
            self._requests[key] = compiled.create_infer_request()
        return self._requests[key]

    def takes(self, query, key, value, attention_mask, dropout: float, is_causal) -> bool:
        """Tell whether a call goes to OpenVINO: bf16, not causal, no dropout, heads alike, a bool or bf16 mask or none.

        Parameters
        ----------
        query, key, value : torch.Tensor
            [B, H, N, D] (N may differ between ``query`` and ``key``/``value``).
        attention_mask : torch.Tensor or None
            A mask of another dtype or rank sends the call to the fallback.
        dropout : float
            Any dropout sends the call to the fallback.
        is_causal : bool or None
            True sends the call to the fallback.

        Returns
        -------
        bool
            Whether OpenVINO computes the call.
        """
        import torch

        mask_ok = attention_mask is None or (attention_mask.dim() == 4
                                             and attention_mask.dtype in (torch.bool, torch.bfloat16))
        return (mask_ok and not dropout and not is_causal
                and all(t.dtype == torch.bfloat16 and t.dim() == 4 for t in (query, key, value))
                and query.shape[1] == key.shape[1] == value.shape[1] and query.shape[-1] == key.shape[-1]
                and min(query.shape[2], key.shape[2]) > 0)

    def __call__(self, module, query, key, value, attention_mask=None, dropout: float = 0.0, scaling=None,
                 is_causal=None, **kwargs):
        """Attend as transformers' ``sdpa_attention_forward`` does, returning ([B, N, H, D] output, None).

        Parameters
        ----------
        module : torch.nn.Module
            The attention module (its ``is_causal`` counts where ``is_causal`` is None).
        query, key, value : torch.Tensor
            [B, H, N, D].
        attention_mask : torch.Tensor or None
            A boolean mask (True: attend) or an additive bias, broadcast over [B, H, N, M].
        dropout : float
            Attention dropout (to the fallback when non-zero).
        scaling : float or None
            The logits' scale; None: :math:`D^{-1/2}`.
        is_causal : bool or None
            Causal attention (to the fallback).
        **kwargs
            Passed to the fallback.

        Returns
        -------
        tuple of (torch.Tensor, None)
            The attention output [B, N, H, D] and no weights.
        """
        import openvino as ov
        import torch

        causal = is_causal if is_causal is not None else getattr(module, "is_causal", False)
        if not self.takes(query, key, value, attention_mask, dropout, causal):
            return self.fallback(module, query, key, value, attention_mask, dropout=dropout, scaling=scaling,
                                 is_causal=is_causal, **kwargs)
        scale = float(scaling) if scaling is not None else query.shape[-1] ** -0.5
        if all(t.transpose(1, 2).is_contiguous() for t in (query, key, value)):
            layout, inputs = "bnhd", [t.transpose(1, 2) for t in (query, key, value)]
        elif all(t.is_contiguous() for t in (query, key, value)):
            layout, inputs = "bhnd", [query, key, value]
        else:
            layout, inputs = "bnhd", [t.transpose(1, 2).contiguous() for t in (query, key, value)]
        b, h, n, _ = query.shape
        out = torch.empty((b, n, h, value.shape[-1]), dtype=torch.bfloat16)

        def wrap(t):  # OpenVINO reads and writes the torch tensor's memory (no copy); numpy has no bf16
            if t.dtype == torch.bool:
                return ov.Tensor(t.numpy(), ov.Shape(list(t.shape)), ov.Type.boolean)
            return ov.Tensor(t.view(torch.int16).numpy(), ov.Shape(list(t.shape)), ov.Type.bf16)

        mask = None
        if attention_mask is not None:
            mask = "bool" if attention_mask.dtype == torch.bool else "bias"
            inputs.append(attention_mask.contiguous())
        request = self._request(scale, layout, mask)
        with torch.profiler.record_function(OPENVINO_ATTENTION_EVENT):
            for i, t in enumerate(inputs):
                request.set_input_tensor(i, wrap(t))
            request.set_output_tensor(0, wrap(out))
            request.infer()
        return out, None


@contextlib.contextmanager
def attention_engine(attention: OpenVINOAttention | None):
    """Route transformers' ``sdpa`` attention through ``attention`` inside the context (restored after).

    transformers' attention modules look their function up by name at each call
    (``ALL_ATTENTION_FUNCTIONS.get_interface``); the context overrides the ``sdpa`` name on that shared interface,
    as :func:`pipeline.teachers.sam3.exact_savings` swaps module functions: one teacher calls the model per process.

    Parameters
    ----------
    attention : OpenVINOAttention or None
        The function to run; None: a no-op (the torch engine).

    Yields
    ------
    None
    """
    if attention is None:
        yield
        return
    from transformers.modeling_utils import ALL_ATTENTION_FUNCTIONS

    before = ALL_ATTENTION_FUNCTIONS["sdpa"]
    ALL_ATTENTION_FUNCTIONS["sdpa"] = attention
    try:
        yield
    finally:
        ALL_ATTENTION_FUNCTIONS["sdpa"] = before
