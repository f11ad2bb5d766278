"""Tiny training artifacts and the training tests' helpers, shared by several test modules (imported as
``tests.builders.training``; the ``tiny`` and ``stage1_state`` fixtures built from them are in tests/conftest.py).

``build_tiny_artifacts`` writes a self-contained set of tiny artifacts (12 images of 32 px) with
pipeline.artifacts; it does not run any other stage.
"""

from __future__ import annotations

import copy
import subprocess
import sys
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import pandas as pd
import torch
from scipy import ndimage

from pipeline.artifacts.lineage import make_meta
from pipeline.artifacts.store import write_parquet, write_zarr
from pipeline.params import RECIPES, load_params, section

REPO = Path(__file__).resolve().parents[2]
PROMPTS = ["spacecraft", "satellite", "space probe", "space vehicle", "p5", "p6"]


def shape_mask(rng, size):
    """A filled ellipse with a thin bar across it, in a ``size`` x ``size`` boolean image."""
    yy, xx = np.mgrid[:size, :size]
    cy, cx = rng.uniform(size * 0.3, size * 0.7, 2)
    ry, rx = rng.uniform(size * 0.12, size * 0.3, 2)
    m = ((yy - cy) / ry) ** 2 + ((xx - cx) / rx) ** 2 <= 1
    # a thin "panel" bar so the skeleton and boundary are non-trivial
    bar_y = int(cy)
    m[max(bar_y - 1, 0):bar_y + 1, int(max(cx - 2 * rx, 0)):int(min(cx + 2 * rx, size))] = True
    return m


def _sdf(mask):
    if not mask.any():
        return np.zeros(mask.shape, np.float32)
    if mask.all():
        return np.ones(mask.shape, np.float32)
    d = ndimage.distance_transform_edt(mask) - ndimage.distance_transform_edt(~mask)
    s = max(np.quantile(np.abs(d), 0.95), 1.0)
    return np.clip(d / s, -1, 1).astype(np.float32)


def build_tiny_artifacts(root: Path, n_train: int = 8, n_val: int = 4, n_test: int = 2, size: int = 32,
                         seed: int = 0) -> Path:
    """Tiny artifacts in the pipeline's layout: manifest, images, reference, teacher (with vflip),
    consensus, geometry, gates.  Pseudo-masks are perturbed copies of the reference masks."""
    rng = np.random.default_rng(seed)
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    n = n_train + n_val + n_test
    split = ["train"] * n_train + ["val"] * n_val + ["test"] * n_test
    ids = [f"img{i:03d}" for i in range(n)]
    truth = np.stack([shape_mask(rng, size) for _ in range(n)])
    img = rng.integers(0, 40, (n, size, size, 3)).astype(np.uint8)
    img[truth] = rng.integers(150, 255, (int(truth.sum()), 3)).astype(np.uint8)
    K = len(PROMPTS)
    masks = np.empty((n, K, size, size), bool)
    for i in range(n):
        for k in range(K):
            shift = rng.integers(-1, 2, 2)
            masks[i, k] = np.roll(truth[i], tuple(shift), axis=(0, 1))
    scores = rng.uniform(0.3, 0.95, (n, K)).astype(np.float32)
    scores[1, 2:] = 0.0  # an image with only two valid prompts
    vflip = np.roll(truth, 1, axis=2)
    vscores = rng.uniform(0.4, 0.9, n).astype(np.float32)
    valid = scores > 0
    agreement = (masks * valid[:, :, None, None]).sum(1) / np.maximum(valid.sum(1), 1)[:, None, None]
    voted = agreement >= 0.5
    a = voted.reshape(n, -1).mean(1)
    c = np.array([agreement[i][voted[i]].mean() if voted[i].any() else 0.0 for i in range(n)])
    g = rng.uniform(0.2, 1.0, n)
    g[0] = 0.0  # a fully suppressed sample

    def meta(schema, stage):
        return make_meta(schema, stage, "test", {"tiny": True, "seed": seed})

    manifest = pd.DataFrame({
        "image_id": ids, "dataset": "tiny", "domain": "synthetic", "split": split,
        "group": split, "spacecraft": [f"sc{i % 3}" for i in range(n)], "image_path": [f"{i}.png" for i in ids],
        "mask_path": [f"{i}_m.png" for i in ids], "part_path": None, "width": size, "height": size,
        "sha256": "0" * 64})
    write_parquet(root / "manifest.parquet", manifest, meta("manifest", "prepare"))
    attrs = {"image_ids": ids}
    write_zarr(root / "images.zarr", {"image": img}, meta("images", "prepare"), attrs)
    write_zarr(root / "reference.zarr", {"mask": truth, "has_mask": np.ones(n, bool)},
               meta("reference", "prepare"), attrs)
    write_zarr(root / "teacher.zarr", {"masks": masks, "scores": scores, "vflip_masks": vflip,
                                       "vflip_scores": vscores},
               meta("teacher", "teacher"), {**attrs, "prompts": PROMPTS})
    write_zarr(root / "consensus.zarr", {"agreement": agreement.astype(np.float32), "voted": voted,
                                         "n_valid": valid.sum(1).astype(np.int16)},
               meta("consensus", "consensus"), attrs)
    write_zarr(root / "geometry.zarr", {"sdf": np.stack([_sdf(m) for m in voted]),
                                        "skeleton": np.stack([m & (ndimage.distance_transform_edt(m) > 1.5)
                                                              for m in voted])},
               meta("geometry", "geometry"), attrs)
    gates = pd.DataFrame({"image_id": ids, "split": split, "c": c, "v": valid.sum(1) / 6.0, "a": a,
                          "a0": float(np.median(a[:n_train])), "g_conf": g, "g_valid": 1.0,
                          "g_area": 1.0, "g": g, "n_valid": valid.sum(1)})
    write_parquet(root / "gates.parquet", gates, meta("gates", "geometry"))
    return root


def tiny_cfg(**over) -> dict:
    """The repo's train section with tiny-run overrides (fp32, 2 epochs, 1 thread)."""
    cfg = section(load_params(REPO / "params.yaml"), "train")
    cfg.update({"epochs_stage1": 2, "epochs_stage2": 2, "precision": "fp32", "num_threads": 1,
                "batch_size": 4})
    # the paper recipe's other parts (the demo's params.yaml may select another recipe): tests that
    # need a part set it themselves
    cfg.update({k: v for k, v in RECIPES["paper"]["train"].items()
                if k not in ("precision", "epochs_stage1", "epochs_stage2", "batch_size")}, recipe="paper")
    cfg["gabi"] = {**cfg["gabi"], "epochs": 2}
    cfg.update(over)
    return cfg


def load_arrays(art, method_name, cfg):
    """(TrainData, ValData) of a method from the tiny artifacts, opened by the stage's wiring."""
    from pipeline.methods import get_method
    from pipeline.training.inputs import load_inputs

    data, val, _ = load_inputs(art, get_method(method_name), cfg)
    return data, val


def clone_state(model) -> dict:
    """A copy of ``model``'s state dict (to compare weights after more training)."""
    return {k: v.clone() for k, v in model.state_dict().items()}


def assert_same_state(a: dict, b: dict) -> None:
    """Two state dicts hold bit-identical tensors under the same keys."""
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


def train_params_file(tmp_path, runs=None) -> Path:
    """The repo's params file with 1-epoch fp32 training and ``protocol.runs`` (default: plain and
    geodistill for seed 42)."""
    import yaml

    p = yaml.safe_load((REPO / "params.yaml").read_text())
    p["train"].update({"epochs_stage1": 1, "epochs_stage2": 1, "precision": "fp32", "num_threads": 1})
    p["protocol"]["runs"] = {**{m: [] for m in p["protocol"]["runs"]},
                             **(runs or {"plain": [42], "geodistill": [42]})}
    out = tmp_path / "params.yaml"
    out.write_text(yaml.safe_dump(p))
    return out


def train_cli(*args, cwd, env=None):
    """``python -m stages.train`` with ``args`` in a subprocess (quiet, this repository on the path, ``env`` added)."""
    env = {"GEODISTILL_QUIET": "1", "PATH": "/usr/bin:/bin", "PYTHONPATH": str(REPO), **(env or {})}
    return subprocess.run([sys.executable, "-m", "stages.train", *args], cwd=cwd, env=env,
                          capture_output=True, text=True)


class MemoryCheckpointer:
    """Resume state held in memory (a deep copy of the last saved state); the tests' checkpointer (no file).

    Attributes
    ----------
    state : dict or None
        The last saved state (None: nothing saved yet).
    """

    def __init__(self) -> None:
        self.state: dict | None = None

    def load(self, run_key: Mapping[str, Any]) -> dict | None:
        """Load a deep copy of the last saved state, whatever its key.

        Parameters
        ----------
        run_key : Mapping
            The run's key (unread here: :func:`train` compares it with the state's).

        Returns
        -------
        dict or None
            A deep copy of the last saved state, or None when nothing was saved.
        """
        return copy.deepcopy(self.state)

    def save(self, state: dict) -> None:
        """Keep a deep copy of ``state``, replacing the one before.

        Parameters
        ----------
        state : dict
            The resume state after an epoch.
        """
        self.state = copy.deepcopy(state)
