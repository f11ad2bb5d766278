"""The teacher tests' tiny inputs, shared by several test modules (imported as ``tests.builders.teacher``;
see tests/conftest.py for the folder's rule): drawn 32x32 spacecraft in the pipeline's artifacts and the
teacher stage run on them, teacher inputs for the SIMULATOR, and a folder of synthetic images of several
sizes and encodings with the ``geodistill`` command runner (label, distill, the Python API)."""

from __future__ import annotations

import hashlib
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
from click.testing import CliRunner

from pipeline.artifacts.lineage import make_meta
from pipeline.artifacts.store import write_parquet, write_zarr
from pipeline.teachers.base import TeacherInput
from stages.teacher import main as teacher_main

REPO = Path(__file__).resolve().parents[2]
PARAMS = str(REPO / "params.yaml")
H = W = 32


def scene(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(image, mask, part labels) of one drawn spacecraft at H x W: a body, two panels, an antenna."""
    parts = np.zeros((H, W), np.uint8)
    cy, cx = rng.integers(10, 22, size=2)
    b = int(rng.integers(2, 5))
    parts[cy - b:cy + b, cx - b:cx + b] = 1
    parts[cy - 1:cy + 1, max(cx - b - 7, 0):cx - b] = 2
    parts[cy - 1:cy + 1, cx + b:min(cx + b + 7, W)] = 2
    parts[max(cy - b - 5, 0):cy - b, cx] = 3
    mask = parts > 0
    image = np.full((H, W, 3), 10, np.uint8)
    image[mask] = 170
    return image, mask, parts


def build_artifacts(root: Path, n: int = 6, splits=None, seed: int = 0) -> dict[str, str]:
    """manifest.parquet, images.zarr, reference.zarr with ``n`` drawn spacecraft at 32x32."""
    rng = np.random.default_rng(seed)
    splits = splits or (["train", "train", "val", "test"] * n)[:n]
    images, masks, parts = zip(*[scene(rng) for _ in range(n)])
    ids = [f"img{i:03d}" for i in range(n)]
    df = pd.DataFrame({
        "image_id": ids, "dataset": "synthetic", "domain": "synthetic", "split": splits,
        "group": splits, "spacecraft": [f"sc{i % 3}" for i in range(n)],
        "image_path": [f"{i}.png" for i in ids], "mask_path": None, "part_path": None,
        "width": W, "height": H,
        "sha256": [hashlib.sha256(im.tobytes()).hexdigest() for im in images],
        "background": ["earth" if i % 3 == 0 else "black" for i in range(n)],
        "hard_case": [i % 4 == 3 for i in range(n)],
        "area_fraction": [float(m.mean()) for m in masks],
    })
    paths = {k: str(root / v) for k, v in dict(manifest="manifest.parquet", images="images.zarr",
                                                reference="reference.zarr", out="teacher.zarr",
                                                scores="teacher_scores.parquet").items()}
    write_parquet(paths["manifest"], df, make_meta("manifest", "prepare", "test", {"seed": seed}))
    write_zarr(paths["images"], {"image": np.stack(images)}, make_meta("images", "prepare", "test", {"seed": seed}),
               attrs={"image_ids": ids})
    write_zarr(paths["reference"], {"mask": np.stack(masks), "has_mask": np.ones(n, bool), "parts": np.stack(parts)},
               make_meta("reference", "prepare", "test", {"seed": seed}), attrs={"image_ids": ids})
    return paths


def run_stage(paths: dict[str, str], cache: Path, *extra: str, sets=()):
    """The teacher stage on :func:`build_artifacts`' ``paths`` with its cache in ``cache``."""
    args = ["--params", PARAMS, "--device", "cpu", "--set", f"teacher.cache_dir={cache}"]
    for s in sets:
        args += ["--set", s]
    for k in ("manifest", "images", "reference", "out", "scores"):
        args += [f"--{k}", paths[k]]
    return CliRunner().invoke(teacher_main, args + list(extra), catch_exceptions=False)


def cache_files(cache: Path) -> list[Path]:
    return sorted(cache.rglob("*.tce"))


def teacher_items(n=40, seed=0) -> list[TeacherInput]:
    """``n`` teacher inputs of :func:`scene` with their reference masks and parts (for the SIMULATOR)."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        image, mask, parts = scene(rng)
        out.append(TeacherInput(f"img{i}", f"sha{i}", image, reference={"mask": mask, "parts": parts},
                                extras={"area_fraction": float(mask.mean()), "hard_case": "none",
                                        "background": "stars"}))
    return out


SIZES = [(48, 64), (64, 48), (56, 56), (40, 72)]
FAST = ["--set", "data.resolution=32", "--device", "cpu"]


def make_image_folder(root: Path, n: int = 20, seed: int = 0, masks: bool = True) -> tuple[Path, Path]:
    """``root/images`` with ``n`` synthetic spacecraft-like images (a bright ellipse + a bar on a dark
    noisy background) of four sizes and four encodings -- 8-bit RGB, grey, RGBA, 16-bit RGB -- and
    ``root/masks`` with their 0/255 masks (same names)."""
    img_dir, mask_dir = root / "images", root / "masks"
    img_dir.mkdir(parents=True)
    if masks:
        mask_dir.mkdir()
    rng = np.random.default_rng(seed)
    for i in range(n):
        h, w = SIZES[i % 4]
        m = np.zeros((h, w), np.uint8)
        cy, cx = int(rng.integers(16, h - 16)), int(rng.integers(16, w - 16))
        cv2.ellipse(m, (cx, cy), (int(rng.integers(6, 12)), int(rng.integers(4, 9))), float(rng.integers(0, 180)),
                    0, 360, 1, -1)
        cv2.rectangle(m, (cx - 14, cy - 2), (cx + 14, cy + 2), 1, -1)
        img = rng.normal(20, 8, (h, w, 3))
        img[m > 0] = rng.integers(120, 230, 3) + rng.normal(0, 10, (int(m.sum()), 3))
        bgr = img.clip(0, 255).astype(np.uint8)
        encoded = [bgr, cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), np.dstack([bgr, np.full((h, w), 255, np.uint8)]),
                   bgr.astype(np.uint16) * 257][i % 4]
        cv2.imwrite(str(img_dir / f"img{i:02d}.png"), encoded)
        if masks:
            cv2.imwrite(str(mask_dir / f"img{i:02d}.png"), m * 255)
    return img_dir, mask_dir


def cli(*args):
    """``geodistill`` with ``args`` (str()-ed) through click's runner; exceptions propagate."""
    from pipeline.cli.main import main

    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


def checkpoint_folder(path: Path) -> Path:
    """A folder that passes the SAM 3 checkpoint check (config, weights and tokenizer files present) but
    holds no model: for tests that only write a project (``--no-run``), never load the teacher."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    (path / "config.json").write_text('{"model_type": "sam3"}')
    (path / "model.safetensors").write_bytes(b"")
    (path / "tokenizer.json").write_text("{}")
    return path
