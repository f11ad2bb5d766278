"""Deployment of the student's mask path: export, segmentation of image files, CPU efficiency benchmark.

Only the TinyUNet mask path is deployed (paper, eq:inference-mask and the sentence after it: SAM 3,
the SDF head and the skeleton head are absent from deployment).  The deployed function is

    Z = f(x)            x float32 [B,3,H,W], RGB in [0, 1] (normalisation is inside the model)
    M = [sigmoid(Z) >= tau]  <=>  [Z >= logit(tau)]                                (eq:inference-mask)

with tau the validation-calibrated threshold of the exported (method, seed); the threshold rules
(the mask, calibration, which tau wins) are pipeline.thresholds'.

Modules, one concern each (their docstrings hold the decisions they implement):

* :mod:`pipeline.deploy.export`     the mask path as a module, TorchScript / ONNX export, parity;
* :mod:`pipeline.deploy.quantize`   static int8 ONNX model, its calibration images and agreement gate;
* :mod:`pipeline.deploy.bundle`     the deploy bundle (deploy.json; its file layout, one table:
                                     :data:`pipeline.catalog.DEPLOY_BUNDLE`), checkpoint resolution
                                     (weights: pipeline.weights, safetensors + JSON);
* :mod:`pipeline.deploy.engines`    the engine registry (name -> what it runs -> loader -> runner),
                                     shared by the Segmenter and the benchmark; the names and what each
                                     engine reads are the torch-free :mod:`pipeline.engine_table`;
* :mod:`pipeline.deploy.segmenter`  :class:`Segmenter`: a checkpoint or bundle loaded with one engine;
* :mod:`pipeline.deploy.files`      segmenting image files (inputs, outputs, PNGs, skipped.csv);
* :mod:`pipeline.deploy.benchmark`  efficiency variants, timing, peak memory, fast path and verdicts.

The names below are re-exported for the stages and tests.
"""

from __future__ import annotations

from pipeline.deploy.bundle import (DEPLOY_JSON, INT8_FILE, ONNX_FILE, TORCHSCRIPT_FILE,  # noqa: F401
                                    checkpoint_resolution, file_sha256, is_deploy_bundle, read_deploy_info,
                                    write_bundle)
from pipeline.deploy.export import (ONNX_INPUT, ONNX_OUTPUT, ParityError, check_parity,  # noqa: F401
                                    compare_logits, export_module, export_onnx, export_torchscript,
                                    load_torchscript, mask_path_model, onnx_unavailable_reason, ort_session,
                                    parity_inputs, require_parity, torch_logits)
from pipeline.deploy.files import (OUTPUT_SUFFIXES, SegmentResult, discover_images, plan_outputs,  # noqa: F401
                                   segment_files, write_skipped_csv)
from pipeline.deploy.quantize import (CALIBRATION_CHUNK, INT8_CALIBRATIONS, calibration_rows,  # noqa: F401
                                      check_int8_parity, int8_agreement, int8_params, quantize_onnx_int8,
                                      read_calibration_images)
from pipeline.deploy.engines import ENGINES  # noqa: F401
from pipeline.deploy.segmenter import Segmenter, load_segmenter, resolve_engine  # noqa: F401
from pipeline.deploy.benchmark import (BASELINE_VARIANT, VARIANTS, Variant, fastest_within,  # noqa: F401,E402
                                       interleaved_times, measure_variants)
