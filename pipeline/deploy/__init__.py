"""Deployment of the student's mask path: export, segmentation of image files, CPU efficiency benchmark.

Only the TinyUNet mask path is deployed (paper, eq:inference-mask and the sentence after it: SAM 3,
the SDF head and the skeleton head are absent from deployment).  The deployed function is

    Z = f(x)            x float32 [B,3,H,W], RGB in [0, 1] (normalisation is inside the model)
    M = [sigmoid(Z) >= tau]  <=>  [Z >= logit(tau)]                                (eq:inference-mask)

with tau the validation-calibrated threshold of the exported (method, seed); the threshold rules
(the mask, calibration, which tau wins) are pipeline.thresholds'.

Modules, one concern each (their docstrings hold the decisions they implement):

* :mod:`pipeline.deploy.mask_path`     the mask path as a module, TorchScript / ONNX export, parity;
* :mod:`pipeline.deploy.quantize`   static int8 ONNX model, its calibration images and agreement gate;
* :mod:`pipeline.deploy.bundle`     the deploy bundle (deploy.json; its file layout, one table:
                                     :data:`pipeline.catalog.DEPLOY_BUNDLE`), checkpoint resolution
                                     (weights: pipeline.artifacts.weights, safetensors + JSON);
* :mod:`pipeline.deploy.engines`    the engine registry (name -> what it runs -> loader -> runner),
                                     shared by the Segmenter and the benchmark; the names and what each
                                     engine reads are the torch-free :mod:`pipeline.deploy.engine_table`;
* :mod:`pipeline.deploy.segmenter`  :class:`Segmenter`: a checkpoint or bundle loaded with one engine;
* :mod:`pipeline.deploy.files`      segmenting image files (inputs, outputs, PNGs, skipped.csv);
* :mod:`pipeline.deploy.benchmark`  efficiency variants, timing, peak memory, fast path and verdicts.
"""
