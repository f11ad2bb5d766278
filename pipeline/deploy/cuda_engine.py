"""GPU fast path of the mask path.

CUDA graphs captured per input shape, bf16 autocast with channels_last; on a CPU, eager fp32 channels_last
(numerically the engine ``torch``).
"""

from __future__ import annotations

import torch

from pipeline.runtime.device import autocast
from pipeline.runtime.errors import InputError
from pipeline.model import mask_path_model

__all__ = ["FastStudent"]

#: the precisions :class:`FastStudent` accepts; ``auto`` = bf16 on CUDA, fp32 on a CPU
PRECISIONS = ("auto", "bf16", "fp32")


class FastStudent:
    """The mask path as a fast inference function.

    Parameters
    ----------
    model : TinyUNet
        The student (its mask path is taken).
    device : str or torch.device
        Where it runs.
    precision : str
        One of :data:`PRECISIONS`: ``auto`` = bf16 on CUDA, fp32 on a CPU (the engine table's option).
    cuda_graphs : bool
        Capture and replay a CUDA graph per input shape (on CUDA only).
    compile : bool
        torch.compile the mask path (minutes of compilation: for long jobs).
    """

    def __init__(self, model, device="cuda", *,
                 precision: str = PRECISIONS[0],  # not a param: the engine table's option, not train.precision
                 cuda_graphs: bool = True,
                 compile: bool = False):  # not a param: an engine option, not teacher.compile
        """Put the mask path on the device, channels_last (and compiled when asked).

        Raises
        ------
        InputError
            ``precision`` is not one of :data:`PRECISIONS`.
        """
        self.device = torch.device(device)
        if precision not in PRECISIONS:
            raise InputError(f"precision {precision!r}: expected auto, bf16 or fp32")
        on_cuda = self.device.type == "cuda"
        self.precision = ("bf16" if on_cuda else "fp32") if precision == "auto" else precision
        self.cuda_graphs = bool(cuda_graphs and on_cuda)
        net = mask_path_model(model).to(self.device).to(memory_format=torch.channels_last)
        self.net = torch.compile(net, dynamic=False) if compile else net
        self._graphs: dict[tuple, tuple] = {}      # shape -> (graph, static input, static output)

    def _forward(self, x):
        dtype = torch.bfloat16 if self.precision == "bf16" else None
        with torch.inference_mode(), autocast(self.device, dtype, cache_enabled=False):
            return self.net(x.contiguous(memory_format=torch.channels_last)).float()

    def _graph(self, shape: tuple):
        """(graph, static input, static output) for ``shape``, captured on first use after 3 warm-up calls."""
        key = shape
        if key not in self._graphs:
            static_in = torch.zeros(shape, dtype=torch.float32, device=self.device)

            def body():
                return self._forward(static_in)

            side = torch.cuda.Stream()
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):
                for _ in range(3):
                    body()
            torch.cuda.current_stream().wait_stream(side)
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                static_out = body()
            self._graphs[key] = (graph, static_in, static_out)
        return self._graphs[key]

    def logits(self, x):
        """Run the mask path on float images.

        Parameters
        ----------
        x : torch.Tensor
            float32 [N,3,H,W] RGB in [0, 1], on any device.

        Returns
        -------
        torch.Tensor
            The logits [N,1,H,W] on the device; on CUDA with graphs, the graph's output buffer (overwritten by
            the next call: copy to keep it).
        """
        x = x.to(self.device, non_blocking=True)
        return self._replay(x) if self.cuda_graphs else self._forward(x)

    def _replay(self, x):
        graph, static_in, static_out = self._graph(tuple(x.shape))
        static_in.copy_(x)
        graph.replay()
        return static_out
