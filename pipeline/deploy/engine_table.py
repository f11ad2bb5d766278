"""The deploy engines as data: one row per engine, the one list of engine names and their old names.

An engine is one way to run the deployed mask path Z = f(x) (eq:inference-mask).  Each row says what
it is (``description``), how :mod:`pipeline.deploy.engines` loads it (``loader`` and its ``options``),
which file of the deploy bundle it runs (``reads``: a key of :data:`pipeline.catalog.DEPLOY_BUNDLE`;
``weights`` = the PyTorch model, which a checkpoint directory holds too), where it runs (``cpu_only``,
``cuda_only``) and which commands offer it: ``segment --engine`` / :class:`pipeline.Segmenter`
(``segment``) and the efficiency benchmark's ``deploy.benchmark_variants`` (``benchmark``).

This module is pure Python and imports nothing of the project, so the params schema (the variants'
default and check), the catalogue (which engine reads each bundle file) and ``segment --help`` read it
without starting torch.  The registry that loads the engines is :data:`pipeline.deploy.engines.ENGINES`,
built from this table; every other list of engine names below is derived from it.  Old names
(:data:`ENGINE_ALIASES`) are accepted wherever an engine name is, through :func:`engine_name`.
"""

from __future__ import annotations

import dataclasses
from typing import Mapping


@dataclasses.dataclass(frozen=True)
class EngineSpec:
    """One engine (module docstring)."""

    description: str
    loader: str                          # a loader of pipeline.deploy.engines (LOADERS)
    options: Mapping = dataclasses.field(default_factory=dict)  # its keyword arguments
    reads: str = "weights"               # the bundle file it runs (pipeline.catalog.DEPLOY_BUNDLE key)
    cpu_only: bool = False
    cuda_only: bool = False
    segment: bool = False                # offered by segment --engine and the Segmenter
    benchmark: bool = False              # a benchmark variant (deploy.benchmark_variants)

    @property
    def bf16(self) -> bool:
        """Computes in bf16 whatever the hardware (``auto`` precision falls back to fp32 instead)."""
        return bool(self.options.get("bf16")) or self.options.get("precision") == "bf16"


#: name -> engine.  The order is the order of segment's choices and of the benchmark's default variants.
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

#: what ``auto`` stands for (pipeline.deploy.segmenter.resolve_engine)
AUTO = "auto"
#: the engines ``segment --engine`` (and :class:`pipeline.Segmenter`) accepts, besides ``auto``
SEGMENT_ENGINES: tuple[str, ...] = tuple(n for n, e in ENGINE_TABLE.items() if e.segment)
#: every choice of ``segment --engine``
ENGINE_CHOICES: tuple[str, ...] = (AUTO, *SEGMENT_ENGINES)
#: segment engines that run the PyTorch model, so a checkpoint directory supports them too
MODEL_ENGINES: tuple[str, ...] = tuple(n for n in SEGMENT_ENGINES if ENGINE_TABLE[n].reads == "weights")
#: the benchmark's variants, in the default order of ``deploy.benchmark_variants``
BENCHMARK_VARIANTS: list[str] = [n for n, e in ENGINE_TABLE.items() if e.benchmark]


def engines_reading(key: str) -> tuple[str, ...]:
    """The engines that run bundle file ``key`` (a :data:`pipeline.catalog.DEPLOY_BUNDLE` key)."""
    return tuple(n for n, e in ENGINE_TABLE.items() if e.reads == key)


def engine_name(name: str) -> str:
    """The engine name that ``name`` stands for: an old name's new one (:data:`ENGINE_ALIASES`), else ``name``."""
    return ENGINE_ALIASES.get(name, name)
