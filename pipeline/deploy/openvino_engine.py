"""OpenVINO runtime for the exported ONNX mask path: the CPU fast path of the int8 model.

Why (issue 19 item 5): on the 2-core Xeon (AVX-512 VNNI, AMX) the bundle's static int8 QDQ model
(``model.int8.onnx``, pipeline.deploy.quantize) runs faster under OpenVINO's CPU plugin than under ONNX
Runtime -- same file, same quantisation parameters, OpenVINO's low-precision transformations fuse the
QDQ pairs into int8 convolutions.  Measured by ``geodistill benchmark`` (variant ``openvino_int8``,
round-robin against the other variants in the same run); the segment engine ``openvino_int8`` runs it.

Decisions:

* Optional dependency (extra ``openvino``): the wheel is ~40 MB and only this fast path uses it; without
  it the variant is skipped with the reason and the engine is an InputError naming the extra.
* The model is compiled for a static input shape (OpenVINO plans memory per shape): one compiled model
  per (batch, height, width) seen, cached on the runner.
* ``INFERENCE_PRECISION_HINT`` = f32: OpenVINO would otherwise run the float parts in bf16 on AMX CPUs;
  the int8 model's float parts (the input scaling, the sigmoid-free logits) stay fp32 as in ONNX Runtime.
* Threads: torch's intra-op count (the same budget as every other variant), one stream, latency hint;
  no pinning (the machine may be shared).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def openvino_unavailable_reason() -> str | None:
    """None when OpenVINO imports, else a one-line reason naming the extra to install."""
    try:
        import openvino  # noqa: F401
    except Exception:  # noqa: BLE001 -- ImportError or a broken binary wheel
        return "openvino not importable (install the extra: pip install 'geodistill-refine[openvino]')"
    return None


class OpenVinoRunner:
    """``runner(x float32 [B,3,H,W]) -> logits float32 [B,1,H,W]`` for an ONNX file on OpenVINO's CPU
    plugin (module docstring); compiled once per input shape."""

    def __init__(self, path: str | Path, threads: int | None = None):
        import openvino as ov

        if threads is None:
            import torch  # only for the default: a child process that names its threads stays torch-free

            threads = torch.get_num_threads()
        self.path = Path(path)
        self.core = ov.Core()
        self.model = self.core.read_model(str(self.path))
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
        x = np.ascontiguousarray(np.asarray(x), np.float32)
        req = self._request(tuple(x.shape))
        out = req.infer({0: x})
        return np.array(out[0], np.float32, copy=True)  # the request reuses its output buffer
