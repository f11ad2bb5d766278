"""The deploy engines as data: the one list of engine names.

One row per way to run the mask path that gives P = sigmoid(Z) for M^ = [P >= tau] (eq:inference-mask).  Pure
Python, so the params schema, the catalogue and ``segment --help`` read it without starting torch;
:data:`pipeline.deploy.engines.ENGINES` loads them.
"""

from __future__ import annotations

import dataclasses
from typing import Mapping

__all__ = ["EngineSpec", "ENGINE_TABLE", "ENGINE_ALIASES", "AUTO", "SEGMENT_ENGINES", "ENGINE_CHOICES",
           "MODEL_ENGINES", "BENCHMARK_VARIANTS", "engine_name"]


@dataclasses.dataclass(frozen=True)
class EngineSpec:
    """One engine: how :mod:`pipeline.deploy.engines` loads it, the bundle file it runs, where and for whom.

    Attributes
    ----------
    description : str
        What it runs, for ``--help`` and the benchmark's table.
    loader : str
        The loader of :mod:`pipeline.deploy.engines` (its ``LOADERS`` key) that builds it.
    options : Mapping
        The loader's keyword options (``channels_last``, ``bf16``, ``precision``).
    reads : str
        The bundle file it runs (a :data:`pipeline.catalog.DEPLOY_BUNDLE` key); ``"weights"`` runs from a
        checkpoint too.
    cpu_only : bool
        It runs on the CPU only.
    cuda_only : bool
        It needs a CUDA GPU.
    segment : bool
        Offered by ``segment --engine`` and the Segmenter.
    benchmark : bool
        A benchmark variant (:data:`BENCHMARK_VARIANTS`).
    """

    description: str
    loader: str                          # a loader of pipeline.deploy.engines (LOADERS)
    options: Mapping = dataclasses.field(default_factory=dict)
    reads: str = "weights"               # a pipeline.catalog.DEPLOY_BUNDLE key
    cpu_only: bool = False
    cuda_only: bool = False
    segment: bool = False                # offered by segment --engine and the Segmenter
    benchmark: bool = False              # a benchmark variant

    @property
    def bf16(self) -> bool:
        """Whether it computes in bf16 whatever the hardware (``auto`` precision falls back to fp32)."""
        return bool(self.options.get("bf16")) or self.options.get("precision") == "bf16"


#: name -> engine, in the order of segment's choices and of the benchmark's default variants
ENGINE_TABLE: dict[str, EngineSpec] = {
    "torch": EngineSpec("PyTorch eager fp32 (channels_last on a CPU): the fp32 reference", "eager",
                        {"channels_last": "cpu"}, segment=True),
    "torchscript": EngineSpec("the bundle's TorchScript model.ts", "torchscript_file", reads="torchscript", segment=True),
    "fp32_eager_nchw": EngineSpec("PyTorch eager fp32, NCHW (baseline)", "eager", {"channels_last": False},
                                  benchmark=True),
    "fp32_channels_last": EngineSpec("PyTorch eager fp32, channels_last", "eager", {"channels_last": True},
                                     benchmark=True),
    "bf16_autocast": EngineSpec("PyTorch eager, bf16 autocast, NCHW", "eager", {"channels_last": False, "bf16": True},
                                benchmark=True),
    "bf16_channels_last": EngineSpec("PyTorch eager, bf16 autocast, channels_last", "eager",
                                     {"channels_last": True, "bf16": True}, benchmark=True),
    "torchscript_frozen": EngineSpec("TorchScript traced + frozen + optimize_for_inference, fp32", "torchscript_frozen",
                                     benchmark=True),
    "onnxruntime_fp32": EngineSpec("ONNX Runtime CPU fp32 on the bundle's model.onnx (graph optimisations "
                                   "ORT_ENABLE_ALL)", "onnxruntime", reads="onnx", cpu_only=True, segment=True,
                                   benchmark=True),
    "onnxruntime_int8": EngineSpec("ONNX Runtime CPU int8 (static QDQ model.int8.onnx: u8 activations, s8 "
                                   "per-channel weights, ranges calibrated on training images)", "onnxruntime",
                                   reads="int8", cpu_only=True, segment=True, benchmark=True),
    "openvino_int8": EngineSpec("OpenVINO CPU on the same static int8 QDQ model.int8.onnx", "openvino", reads="int8",
                                cpu_only=True, segment=True, benchmark=True),
    "cuda": EngineSpec("GPU fast path: CUDA graphs, bf16 autocast, channels_last (eager fp32 on a CPU)", "fast",
                       {"precision": "auto"}, segment=True),
    "cuda_graph_bf16": EngineSpec("CUDA graphs, bf16 autocast, channels_last (pipeline.deploy.cuda_engine)", "fast",
                                  {"precision": "bf16"}, cuda_only=True, benchmark=True),
}

#: old name -> engine name (docs/decisions.md, "One name per engine")
ENGINE_ALIASES: dict[str, str] = {"onnx": "onnxruntime_fp32", "int8": "onnxruntime_int8"}

#: the ``segment --engine`` choice that picks an engine for the hardware
AUTO = "auto"
#: the engines ``segment --engine`` accepts besides ``auto``
SEGMENT_ENGINES: tuple[str, ...] = tuple(n for n, e in ENGINE_TABLE.items() if e.segment)
ENGINE_CHOICES: tuple[str, ...] = (AUTO, *SEGMENT_ENGINES)
#: segment engines that a checkpoint directory supports too
MODEL_ENGINES: tuple[str, ...] = tuple(n for n in SEGMENT_ENGINES if ENGINE_TABLE[n].reads == "weights")
#: the benchmark's default variants, in the table's order
BENCHMARK_VARIANTS: list[str] = [n for n, e in ENGINE_TABLE.items() if e.benchmark]


def engine_name(name: str) -> str:
    """Resolve an old engine name to the one it stands for (:data:`ENGINE_ALIASES`).

    Parameters
    ----------
    name : str
        An engine name or an alias.

    Returns
    -------
    str
        The engine name; any name that is no alias, unchanged.
    """
    return ENGINE_ALIASES.get(name, name)
