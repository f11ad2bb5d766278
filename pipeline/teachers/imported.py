"""Teacher answers produced elsewhere (e.g. SAM 3 on a GPU cluster), read from a documented layout.

Layout of ``teacher.imported_dir``::

    <dir>/scores.parquet  (or scores.csv)   one row per (image, prompt[, view]):
        image_id      str    the manifest's image_id
        prompt_index  int    names the mask file (any integer; need not match teacher.prompts order)
        prompt        str    the prompt text; answers are matched to teacher.prompts by this text
        score         float  the teacher score s_ik; <= 0 (or NaN) means no candidate -> invalid
        view          str    optional: identity (default) | vflip
    <dir>/masks/<image_id>/<prompt_index>.png          identity view
    <dir>/masks/<image_id>/vflip_<prompt_index>.png    vflip view (base prompt on the vertically
                                                        flipped image, mask already flipped BACK)

Masks are 8- or 16-bit PNGs, grey or colour; any non-zero pixel is foreground.  A mask whose size
differs from the working resolution of images.zarr is resized with nearest-neighbour interpolation.
An invalid answer (score <= 0) needs no PNG.  A requested (image, prompt, view) without a row, or a
valid row without its PNG, is an InputError naming the missing file or row.

The masks are already a cache of the real teacher, so this backend bypasses the content-addressed
cache (``use_cache = False``); its fingerprint hashes the scores table and every mask file.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd

from pipeline.errors import InputError
from pipeline.teachers.base import TeacherInput, finalize_answers

BACKEND = "imported"


def read_mask_png(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """Any-bit-depth PNG -> bool [H,W] at ``shape`` (nearest-neighbour resize when sizes differ)."""
    import cv2

    arr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if arr is None:
        raise InputError(f"{path}: unreadable mask PNG")
    if arr.ndim == 3:
        arr = arr.max(axis=2)
    mask = arr > 0
    if mask.shape != tuple(shape):
        mask = cv2.resize(mask.astype(np.uint8), (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST) > 0
    return mask


class ImportedTeacher:
    """Reads masks and scores from ``root`` in the layout of the module docstring."""

    backend = BACKEND
    needs_reference = False
    use_cache = False

    def __init__(self, root: str | Path, resolution: tuple[int, int]):
        self.root = Path(root)
        self.resolution = tuple(resolution)
        if not self.root.is_dir():
            raise InputError(f"{self.root}: teacher.imported_dir is not a directory")
        table = None
        for name in ("scores.parquet", "scores.csv"):
            p = self.root / name
            if p.exists():
                try:
                    table = pd.read_parquet(p) if p.suffix == ".parquet" else pd.read_csv(p)
                except Exception as e:  # noqa: BLE001 -- any parse failure is a user input problem
                    raise InputError(f"{p}: unreadable scores table ({type(e).__name__})") from None
                self.scores_path = p
                break
        if table is None:
            raise InputError(f"{self.root}: no scores.parquet or scores.csv (see pipeline/teachers/imported.py)")
        missing = [c for c in ("image_id", "prompt_index", "prompt", "score") if c not in table.columns]
        if missing:
            raise InputError(f"{self.scores_path}: missing columns {missing}")
        if "view" not in table.columns:
            table["view"] = "identity"
        table["image_id"] = table["image_id"].astype(str)
        table["view"] = table["view"].fillna("identity").astype(str)
        bad_views = set(table["view"]) - {"identity", "vflip"}
        if bad_views:
            raise InputError(f"{self.scores_path}: unknown view values {sorted(bad_views)} (identity | vflip)")
        dup = table.duplicated(["image_id", "prompt", "view"])
        if dup.any():
            r = table[dup].iloc[0]
            raise InputError(f"{self.scores_path}: duplicate row for image {r.image_id!r}, prompt {r.prompt!r}")
        self.table = table.set_index(["image_id", "prompt", "view"])
        self._fp: str | None = None

    def content_hash(self) -> str:
        """sha256 over the scores table and every mask file (relative path + bytes), sorted."""
        if self._fp is None:
            h = hashlib.sha256(self.scores_path.read_bytes())
            for p in sorted((self.root / "masks").rglob("*.png")) if (self.root / "masks").is_dir() else []:
                h.update(str(p.relative_to(self.root)).encode())
                h.update(p.read_bytes())
            self._fp = h.hexdigest()
        return self._fp

    def fingerprint(self) -> dict:
        return {"backend": BACKEND, "content": self.content_hash(), "resolution": list(self.resolution)}

    def _answer(self, image_id: str, prompt: str, view: str) -> tuple[np.ndarray, float]:
        try:
            row = self.table.loc[(image_id, prompt, view)]
        except KeyError:
            raise InputError(f"{self.scores_path}: no row for image {image_id!r}, prompt {prompt!r}, view {view}") from None
        score = float(row["score"]) if pd.notna(row["score"]) else 0.0
        if score <= 0:
            return np.zeros(self.resolution, bool), 0.0
        stem = f"{int(row['prompt_index'])}" if view == "identity" else f"vflip_{int(row['prompt_index'])}"
        path = self.root / "masks" / image_id / f"{stem}.png"
        if not path.exists():
            raise InputError(f"{path}: mask file missing (score {score:.3f} > 0 needs a mask)")
        return read_mask_png(path, self.resolution), score

    def predict(self, batch: Sequence[TeacherInput], prompts: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        """Imported answers.  For the ``vflip`` view the stored mask is already in the original frame,
        so it is flipped here once more and the runner's flip-back restores it."""
        masks = np.zeros((len(batch), len(prompts), *self.resolution), bool)
        scores = np.zeros((len(batch), len(prompts)), np.float32)
        for b, item in enumerate(batch):
            for k, prompt in enumerate(prompts):
                m, s = self._answer(item.image_id, prompt, item.view)
                masks[b, k] = m[::-1] if item.view == "vflip" else m
                scores[b, k] = s
        return finalize_answers(masks, scores)
