"""A tiny random student (TinyUNet) and what the deploy tests build around it -- its checkpoint, a
thresholds table, tiny artifacts, the export command -- shared by several test modules (imported as
``tests.builders.deploy``; see tests/conftest.py for the folder's rule)."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from click.testing import CliRunner

from pipeline.deploy.mask_path import onnx_unavailable_reason
from pipeline.deploy.quantize import Int8Settings
from pipeline.params import PAPER
from pipeline.artifacts.lineage import make_meta
from pipeline.artifacts.store import write_parquet, write_zarr
from pipeline.evaluation.inference import save_checkpoint
from pipeline.model import TinyUNet

REPO = Path(__file__).resolve().parents[2]
PARAMS = str(REPO / "params.yaml")
RES = 32
HAS_ONNX = onnx_unavailable_reason() is None


def int8_settings(**override) -> Int8Settings:
    """The schema's int8 settings (its defaults, :data:`pipeline.params.PAPER`), ``override`` replacing some."""
    return Int8Settings.from_params({**PAPER.deploy.model_dump(), **override})


def tiny_model(seed: int = 0, geometry: bool = False) -> TinyUNet:
    """A small random TinyUNet whose BN statistics are not the identity (non-trivial logits)."""
    torch.manual_seed(seed)
    m = TinyUNet(channels=(4, 8, 16))
    for mod in m.modules():
        if isinstance(mod, torch.nn.BatchNorm2d):
            mod.running_mean.uniform_(-0.2, 0.2)
            mod.running_var.uniform_(0.5, 1.5)
    if geometry:
        m.add_geometry_heads()
    return m.eval()


def make_checkpoint(path: Path, seed: int = 0, method: str = "geodistill", run_seed: int = 42,
                    geometry: bool = False) -> Path:
    log = pd.DataFrame({"epoch": [1], "stage": [2], "loss": [0.1], "val_iou": [0.5], "val_bf1": [0.5],
                        "lr": [1e-4]})
    meta = make_meta("checkpoint", "train", "test", {"seed": run_seed, "method": method})
    return save_checkpoint(path, tiny_model(seed, geometry), meta, log, method=method, seed=run_seed, stage=2,
                           selected_epoch=1)


def make_thresholds(path: Path, rows) -> Path:
    df = pd.DataFrame(rows, columns=["method", "seed", "tau", "val_iou"])
    write_parquet(path, df, make_meta("thresholds", "calibrate", "test", {}))
    return path


def make_artifacts(root: Path, n: int = 8) -> Path:
    """manifest / images / reference at 32 px: bright boxes on dark backgrounds, half train, half val."""
    rng = np.random.default_rng(0)
    images = np.full((n, RES, RES, 3), 20, np.uint8)
    masks = np.zeros((n, RES, RES), bool)
    for i in range(n):
        y, x = rng.integers(4, 16, size=2)
        masks[i, y:y + 12, x:x + 10] = True
        images[i][masks[i]] = 200
    ids = [f"img{i}" for i in range(n)]
    splits = ["train", "val"] * (n // 2)
    df = pd.DataFrame({"image_id": ids, "dataset": "synthetic", "domain": "synthetic", "split": splits,
                       "group": splits, "spacecraft": "sc", "image_path": [f"{i}.png" for i in ids],
                       "mask_path": None, "part_path": None, "width": RES, "height": RES,
                       "sha256": [hashlib.sha256(im.tobytes()).hexdigest() for im in images]})
    root.mkdir(parents=True, exist_ok=True)
    write_parquet(root / "manifest.parquet", df, make_meta("manifest", "prepare", "test", {}))
    write_zarr(root / "images.zarr", {"image": images}, make_meta("images", "prepare", "test", {}),
               attrs={"image_ids": ids})
    write_zarr(root / "reference.zarr", {"mask": masks, "has_mask": np.ones(n, bool)},
               make_meta("reference", "prepare", "test", {}), attrs={"image_ids": ids})
    return root


def run_export(ckpt, out, *extra):
    args = ["--params", PARAMS, "--device", "cpu", "--set", f"data.resolution={RES}",
            "--checkpoint", str(ckpt), "--out", str(out), *extra]
    return CliRunner().invoke(__import__("stages.export", fromlist=["main"]).main, args)
