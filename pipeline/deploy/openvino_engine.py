"""OpenVINO's CPU plugin for the bundle's int8 ONNX model (the optional extra ``openvino``).

It fuses the QDQ pairs into int8 convolutions, faster than ONNX Runtime on the same file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["openvino_unavailable_reason", "OpenVinoRunner"]


def openvino_unavailable_reason() -> str | None:
    """Tell why OpenVINO cannot be used here.

    Returns
    -------
    str or None
        None when OpenVINO imports, else why not (naming the extra to install).
    """
    try:
        import openvino  # noqa: F401
    except Exception:  # noqa: BLE001 -- ImportError or a broken binary wheel
        return "openvino not importable (install the extra: pip install 'geodistill-refine[openvino]')"
    return None


class OpenVinoRunner:
    """The int8 model on OpenVINO's CPU plugin: ``runner(x float32 [B,3,H,W]) -> logits [B,1,H,W]``.

    Compiled once per input shape (static shapes).

    Parameters
    ----------
    path : str or Path
        The ONNX model (the bundle's ``model.int8.onnx``).
    threads : int or None
        Inference threads; None: torch's thread count, like every other variant.
    """

    def __init__(self, path: str | Path, threads: int | None = None):
        import openvino as ov

        if threads is None:
            import torch  # only for the default: a child process that names its threads stays torch-free

            threads = torch.get_num_threads()
        self.path = Path(path)
        self.core = ov.Core()
        self.model = self.core.read_model(str(self.path))
        # torch's thread budget, like every variant; f32 keeps the float parts out of bf16 on AMX CPUs
        self.config = {"INFERENCE_NUM_THREADS": int(threads), "NUM_STREAMS": 1,
                       "PERFORMANCE_HINT": "LATENCY", "INFERENCE_PRECISION_HINT": "f32",
                       "ENABLE_CPU_PINNING": False}
        self._requests: dict[tuple, object] = {}

    def _request(self, shape: tuple):
        req = self._requests.get(shape)
        if req is None:
            model = self.model.clone()
            model.reshape({model.inputs[0].get_any_name(): list(shape)})
            req = self.core.compile_model(model, "CPU", self.config).create_infer_request()
            self._requests[shape] = req
        return req

    def __call__(self, x) -> np.ndarray:
        """Run the model on one batch.

        Parameters
        ----------
        x : array-like
            float32 [B,3,H,W] RGB in [0, 1].

        Returns
        -------
        np.ndarray
            The logits, float32 [B,1,H,W], a copy (the request reuses its output buffer).
        """
        x = np.ascontiguousarray(np.asarray(x), np.float32)
        out = self._request(tuple(x.shape)).infer({0: x})
        return np.array(out[0], np.float32, copy=True)  # the request reuses its output buffer
