"""The engine registry: each row of :data:`pipeline.engine_table.ENGINE_TABLE` with its loader.

Shared by the Segmenter and the benchmark.  A runner maps x float32 [N,3,H,W] RGB in [0, 1] (CPU) to the
logits Z [N,1,H,W] of the mask path (eq:inference-mask thresholds them), a torch tensor that survives the next
call.
"""

from __future__ import annotations

import contextlib
import dataclasses
import warnings
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import torch

from pipeline.catalog import bundle_file
from pipeline.deploy import openvino_engine
from pipeline.deploy.cuda_engine import FastStudent
from pipeline.deploy.mask_path import ONNX_INPUT, load_torchscript, onnx_unavailable_reason, ort_session
from pipeline.runtime.device import BF16_FLAGS, cpu_supports_bf16
from pipeline.engine_table import ENGINE_TABLE, EngineSpec
from pipeline.model import mask_path_model

__all__ = ["Source", "Runner", "Engine", "LOADERS", "ENGINES", "unavailable"]


@dataclasses.dataclass
class Source:
    """What an engine loads.

    Attributes
    ----------
    model : Any
        The PyTorch TinyUNet (None when only bundle files are used).
    device : torch.device
        The device asked for.
    resolution : int or None
        The working resolution (the traced engines need it).
    files : Mapping
        Bundle file name (a :data:`pipeline.catalog.DEPLOY_BUNDLE` key) -> its path, or None when absent.
    spinning : bool
        ONNX Runtime's idle threads spin (fast for back-to-back calls, busy between them).
    """

    model: Any
    device: torch.device
    resolution: int | None = None
    files: Mapping[str, Path | None] = dataclasses.field(default_factory=dict)
    spinning: bool = True


@dataclasses.dataclass
class Runner:
    """A loaded engine.

    Attributes
    ----------
    run : Callable
        ``run(x float32 [N,3,H,W]) -> logits [N,1,H,W]`` (a torch tensor).
    info : dict
        What it reports about itself (the fast path: its precision and whether it replays CUDA graphs).
    """

    run: Callable
    info: dict = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class Engine:
    """One registry entry.

    Attributes
    ----------
    description : str
        What it runs (the engine table's description).
    load : Callable
        ``load(Source) -> Runner``.
    needs : str
        ``"model"``, or the bundle file it runs.
    requires : Callable
        ``requires() -> str or None``: why it cannot run on this host (a package missing), or None.
    cpu_only : bool
        It runs on the CPU whatever the device asked for.
    cuda_only : bool
        It needs a CUDA device.
    bf16 : bool
        It computes in bf16 whatever the hardware.
    """

    description: str
    load: Callable[[Source], Runner]
    needs: str = "model"
    requires: Callable[[], str | None] = lambda: None  # why it cannot run here
    cpu_only: bool = False
    cuda_only: bool = False
    bf16: bool = False

    def device(self, device: torch.device) -> str:
        """Tell where it runs for a requested ``device``.

        Parameters
        ----------
        device : torch.device
            The device asked for.

        Returns
        -------
        str
            ``"cpu"`` for a CPU-only engine, else ``device``'s type.
        """
        return "cpu" if self.cpu_only else device.type


def _eager(channels_last: bool | str, bf16: bool = False) -> Callable[[Source], Runner]:
    """Build the PyTorch eager loader; ``channels_last``: True, False or ``"cpu"`` (on the CPU only, as calibrate)."""
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
    """Load the mask path traced, frozen and (CPU) optimised for inference here."""
    dev = src.device
    example = torch.zeros(1, src.model.config["in_channels"], src.resolution, src.resolution, device=dev)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ts = torch.jit.freeze(torch.jit.trace(mask_path_model(src.model).to(dev), example, check_trace=False))
        if dev.type == "cpu":
            ts = torch.jit.optimize_for_inference(ts)
    return _eager_module(ts, dev)


def _torchscript_file(file: str) -> Callable[[Source], Runner]:
    return lambda src: _eager_module(load_torchscript(src.files[file], src.device), src.device)


def _eager_module(module, dev: torch.device) -> Runner:
    def run(x):
        with torch.inference_mode():
            return module(x.to(dev)).float()
    return Runner(run)


def _fast(precision: str) -> Callable[[Source], Runner]:
    def load(src: Source) -> Runner:
        fast = FastStudent(src.model, src.device, precision=precision)
        return Runner(lambda x: fast.logits(x).clone(), {"precision": fast.precision, "cuda_graphs": fast.cuda_graphs})
    return load


def _onnxruntime(file: str) -> Callable[[Source], Runner]:
    def load(src: Source) -> Runner:
        sess = ort_session(src.files[file], spinning=src.spinning)

        def run(x):
            return torch.from_numpy(sess.run(None, {ONNX_INPUT: np.ascontiguousarray(x.cpu().numpy(), np.float32)})[0])
        return Runner(run)
    return load


def _openvino(file: str) -> Callable[[Source], Runner]:
    def load(src: Source) -> Runner:
        runner = openvino_engine.OpenVinoRunner(src.files[file])
        return Runner(lambda x: torch.from_numpy(runner(x.cpu().numpy())))
    return load


#: the engine table's ``loader`` -> (factory(bundle file or None, **options) -> loader, why it cannot run here)
LOADERS: dict[str, tuple[Callable[..., Callable[[Source], Runner]], Callable[[], str | None]]] = {
    "eager": (lambda file, **o: _eager(**o), lambda: None),
    "fast": (lambda file, **o: _fast(**o), lambda: None),
    "torchscript_file": (_torchscript_file, lambda: None),
    "torchscript_frozen": (lambda file: _torchscript_frozen, lambda: None),
    "onnxruntime": (_onnxruntime, onnx_unavailable_reason),
    "openvino": (_openvino, lambda: openvino_engine.openvino_unavailable_reason() or onnx_unavailable_reason()),
}


def _engine(spec: EngineSpec) -> Engine:
    factory, requires = LOADERS[spec.loader]
    file = None if spec.reads == "weights" else bundle_file(spec.reads)
    return Engine(spec.description, factory(file, **spec.options), needs=file or "model", requires=requires,
                  cpu_only=spec.cpu_only, cuda_only=spec.cuda_only, bf16=spec.bf16)


#: engine name -> its loaded registry entry, one per row of the engine table
ENGINES: dict[str, Engine] = {name: _engine(spec) for name, spec in ENGINE_TABLE.items()}


def unavailable(name: str, src: Source) -> str | None:
    """Tell why an engine cannot run on a source.

    Parameters
    ----------
    name : str
        An engine of :data:`ENGINES`.
    src : Source
        What it would load, and the device.

    Returns
    -------
    str or None
        Why not (a package, the device, the CPU's flags, a bundle file missing), or None when it can run.
    """
    engine = ENGINES[name]
    if engine.cuda_only and src.device.type != "cuda":
        return "needs a CUDA device (--device cuda)"
    # from the flags, never by a call: emulated bf16 costs up to a minute per 384² image
    if engine.bf16 and engine.device(src.device) == "cpu" and not cpu_supports_bf16():
        return f"bf16 is emulated on this CPU (none of the flags {', '.join(BF16_FLAGS)})"
    reason = engine.requires()
    if reason is None and engine.needs != "model" and src.files.get(engine.needs) is None:
        reason = f"no {engine.needs}"
    return reason
