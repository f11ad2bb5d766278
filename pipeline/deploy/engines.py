"""The engine registry: every way this project runs the deployed mask path Z = f(x), once.

An engine is a name -> (what it needs, a loader that returns the runner).  :class:`Segmenter`
(``segment --engine``, pipeline.deploy.segmenter) and the efficiency benchmark (``deploy.benchmark_variants``,
pipeline.deploy.benchmark) both look their names up in :data:`ENGINES`; :data:`SEGMENT_ENGINES` are
the names segment accepts, the params schema lists the benchmark's (``BENCHMARK_VARIANTS``).

A runner takes x float32 [N,3,H,W] RGB in [0, 1] (a CPU tensor) and returns the logits [N,1,H,W] as a
torch tensor (on the engine's device; a CUDA-graph output buffer is copied, so it survives the next call).

``needs``: ``model`` (the PyTorch mask path: a checkpoint or a bundle), or the bundle file it runs
(``model.ts``, ``model.onnx``, ``model.int8.onnx``).  ``requires``: why it cannot run here (a missing
optional package) or None.  ``cpu_only``: runs on the CPU whatever the device (ONNX Runtime,
OpenVINO); ``cuda_only``: needs a CUDA device.
"""

from __future__ import annotations

import contextlib
import dataclasses
import warnings
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import torch

from pipeline.deploy import openvino_engine
from pipeline.deploy.bundle import INT8_FILE
from pipeline.deploy.cuda_engine import FastStudent
from pipeline.deploy.export import ONNX_INPUT, load_torchscript, onnx_unavailable_reason, ort_session
from pipeline.model import mask_path_model

ONNX_FILE = "model.onnx"
TORCHSCRIPT_FILE = "model.ts"


@dataclasses.dataclass
class Source:
    """What an engine is loaded from: the PyTorch model (CPU; None when only files are used), the
    device, the working resolution, and the bundle files found (file name -> path, None if absent).
    ``spinning``: ONNX Runtime's idle threads spin (segment) or sleep (benchmark timing)."""

    model: Any
    device: torch.device
    resolution: int | None = None
    files: Mapping[str, Path | None] = dataclasses.field(default_factory=dict)
    spinning: bool = True


@dataclasses.dataclass
class Runner:
    """A loaded engine: ``run(x) -> logits`` and what it reports about itself (``info``)."""

    run: Callable
    info: dict = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class Engine:
    """One registry entry (module docstring)."""

    description: str
    load: Callable[[Source], Runner]
    needs: str = "model"
    requires: Callable[[], str | None] = lambda: None
    cpu_only: bool = False
    cuda_only: bool = False

    def device(self, device: torch.device) -> str:
        """Where it runs for a requested ``device``."""
        return "cpu" if self.cpu_only else device.type


# --------------------------------------------------------------------------------------------------
# Loaders
# --------------------------------------------------------------------------------------------------
def _eager(channels_last: bool | str, bf16: bool = False) -> Callable[[Source], Runner]:
    """PyTorch eager mask path on the source's device; ``channels_last``: True, False or ``"cpu"``
    (on the CPU only: the layout calibrate ran with); ``bf16``: under bf16 autocast."""
    def load(src: Source) -> Runner:
        dev = src.device
        cl = channels_last is True or (channels_last == "cpu" and dev.type == "cpu")
        m = mask_path_model(src.model).to(dev)
        if cl:
            m = m.to(memory_format=torch.channels_last)

        def run(x):
            x = x.to(dev, non_blocking=True)
            if cl:
                x = x.contiguous(memory_format=torch.channels_last)
            with torch.inference_mode(), (torch.autocast(dev.type, dtype=torch.bfloat16) if bf16
                                          else contextlib.nullcontext()):
                return m(x).float()
        return Runner(run)
    return load


def _torchscript_frozen(src: Source) -> Runner:
    """The mask path traced, frozen and (CPU) optimised for inference here (not the bundle's file)."""
    dev = src.device
    example = torch.zeros(1, src.model.config["in_channels"], src.resolution, src.resolution, device=dev)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ts = torch.jit.freeze(torch.jit.trace(mask_path_model(src.model).to(dev), example, check_trace=False))
        if dev.type == "cpu":
            ts = torch.jit.optimize_for_inference(ts)
    return _eager_module(ts, dev)


def _torchscript_file(src: Source) -> Runner:
    """The bundle's model.ts on the source's device."""
    return _eager_module(load_torchscript(src.files[TORCHSCRIPT_FILE], src.device), src.device)


def _eager_module(module, dev: torch.device) -> Runner:
    def run(x):
        with torch.inference_mode():
            return module(x.to(dev)).float()
    return Runner(run)


def _fast(precision: str) -> Callable[[Source], Runner]:
    """pipeline.deploy.cuda_engine.FastStudent (CUDA graphs + channels_last; eager fp32 on a CPU)."""
    def load(src: Source) -> Runner:
        fast = FastStudent(src.model, src.device, precision=precision)
        return Runner(lambda x: fast.logits(x).clone(), {"precision": fast.precision, "cuda_graphs": fast.cuda_graphs})
    return load


def _onnxruntime(file: str) -> Callable[[Source], Runner]:
    """ONNX Runtime (CPU, all graph optimisations) on a bundle file."""
    def load(src: Source) -> Runner:
        sess = ort_session(src.files[file], spinning=src.spinning)

        def run(x):
            return torch.from_numpy(sess.run(None, {ONNX_INPUT: np.ascontiguousarray(x.cpu().numpy(), np.float32)})[0])
        return Runner(run)
    return load


def _openvino(src: Source) -> Runner:
    runner = openvino_engine.OpenVinoRunner(src.files[INT8_FILE])
    return Runner(lambda x: torch.from_numpy(runner(x.cpu().numpy())))


def _openvino_reason() -> str | None:
    return openvino_engine.openvino_unavailable_reason() or onnx_unavailable_reason()


_ORT_INT8 = ("ONNX Runtime CPU int8 (static QDQ model.int8.onnx: u8 activations, s8 per-channel weights, ranges "
             "calibrated on training images)")

#: name -> engine: segment's engines and the benchmark's variants, one registry
ENGINES: dict[str, Engine] = {
    "torch": Engine("PyTorch eager fp32 (channels_last on a CPU): the fp32 reference", _eager("cpu")),
    "cuda": Engine("GPU fast path: CUDA graphs, bf16 autocast, channels_last (eager fp32 on a CPU)", _fast("auto")),
    "torchscript": Engine("the bundle's TorchScript model.ts", _torchscript_file, needs=TORCHSCRIPT_FILE),
    "onnx": Engine("ONNX Runtime CPU fp32 on the bundle's model.onnx", _onnxruntime(ONNX_FILE), needs=ONNX_FILE,
                   requires=onnx_unavailable_reason, cpu_only=True),
    "int8": Engine(_ORT_INT8, _onnxruntime(INT8_FILE), needs=INT8_FILE, requires=onnx_unavailable_reason,
                   cpu_only=True),
    "openvino_int8": Engine("OpenVINO CPU on the same static int8 QDQ model.int8.onnx", _openvino, needs=INT8_FILE,
                            requires=_openvino_reason, cpu_only=True),
    "fp32_eager_nchw": Engine("PyTorch eager fp32, NCHW (baseline)", _eager(False)),
    "fp32_channels_last": Engine("PyTorch eager fp32, channels_last", _eager(True)),
    "bf16_autocast": Engine("PyTorch eager, bf16 autocast, NCHW", _eager(False, bf16=True)),
    "bf16_channels_last": Engine("PyTorch eager, bf16 autocast, channels_last", _eager(True, bf16=True)),
    "torchscript_frozen": Engine("TorchScript traced + frozen + optimize_for_inference, fp32", _torchscript_frozen),
    "onnxruntime_fp32": Engine("ONNX Runtime CPU fp32, graph optimisations ORT_ENABLE_ALL", _onnxruntime(ONNX_FILE),
                               needs=ONNX_FILE, requires=onnx_unavailable_reason, cpu_only=True),
    "onnxruntime_int8": Engine(_ORT_INT8, _onnxruntime(INT8_FILE), needs=INT8_FILE, requires=onnx_unavailable_reason,
                               cpu_only=True),
    "cuda_graph_bf16": Engine("CUDA graphs, bf16 autocast, channels_last (pipeline.deploy.cuda_engine)", _fast("bf16"),
                              cuda_only=True),
}
#: the engines ``segment --engine`` (and :class:`Segmenter`) accepts, besides ``auto``
SEGMENT_ENGINES = ("torch", "torchscript", "onnx", "int8", "openvino_int8", "cuda")
#: engines that run the PyTorch model, so a checkpoint directory supports them too
MODEL_ENGINES = tuple(n for n in SEGMENT_ENGINES if ENGINES[n].needs == "model")


def unavailable(name: str, src: Source) -> str | None:
    """Why engine ``name`` cannot run on ``src`` (a package, the device, a file), or None."""
    engine = ENGINES[name]
    if engine.cuda_only and src.device.type != "cuda":
        return "needs a CUDA device (--device cuda)"
    reason = engine.requires()
    if reason is None and engine.needs != "model" and src.files.get(engine.needs) is None:
        reason = f"no {engine.needs}"
    return reason
