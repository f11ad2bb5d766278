"""Teacher answers produced elsewhere (e.g. SAM 3 on a GPU cluster) in the layout of docs/real-data.md.

They are already a cache of the real teacher, so this backend bypasses the teacher cache.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np

from pipeline.runtime.errors import InputError
from pipeline.teacher_table import IMPORTED as BACKEND
from pipeline.teachers.base import RegisteredTeacher, TeacherInput, files_digest, finalize_answers

if TYPE_CHECKING:
    import pandas as pd

__all__ = ["MAX_PROMPT_INDEX", "read_mask_png", "ImportedTeacher"]

#: the largest ``prompt_index`` of the scores table (int16, as teacher_scores.parquet stores it)
MAX_PROMPT_INDEX = 32767


def read_mask_png(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """Read an imported mask: any-bit-depth PNG -> bool [H,W] at ``shape``.

    Parameters
    ----------
    path : Path
        The PNG (value > 0: foreground, :func:`pipeline.datasets.loading.read_mask`).
    shape : tuple of int
        (H, W) of the working resolution; a mask of another size is resized (nearest neighbour).

    Returns
    -------
    numpy.ndarray
        bool [H,W].
    """
    import cv2

    from pipeline.datasets.loading import read_mask

    mask = read_mask(path)  # the one mask rule (value > 0); InputError naming the file on bad input
    if mask.shape != tuple(shape):
        mask = cv2.resize(mask.astype(np.uint8), (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST) > 0
    return mask


class ImportedTeacher(RegisteredTeacher):
    """The teacher that reads masks and scores from a folder (layout: docs/real-data.md).

    Attributes
    ----------
    root : Path
        ``teacher.imported_dir``.
    resolution : tuple of int
        (H, W) of the working resolution.
    scores_path : Path
        Its scores table (scores.parquet, else scores.csv).
    table : pandas.DataFrame
        The checked scores table, indexed by (image_id, prompt, view).
    """

    backend = BACKEND

    @classmethod
    def from_params(cls, cfg, resolution: tuple[int, int], device: str = "auto") -> "ImportedTeacher":
        """Build the teacher of a validated ``teacher:`` section.

        Parameters
        ----------
        cfg : Mapping
            The validated ``teacher:`` section: its ``imported_dir`` is read.
        resolution : tuple of int
            (H, W) of the working resolution.
        device : str, optional
            Unused: nothing runs on a device.

        Returns
        -------
        ImportedTeacher
            The teacher.
        """
        return cls(cfg["imported_dir"], resolution=resolution)

    def __init__(self, root: str | Path, resolution: tuple[int, int]):
        """Open ``root`` and check every row of its scores table.

        Parameters
        ----------
        root : str or Path
            The folder (layout: docs/real-data.md).
        resolution : tuple of int
            (H, W) of the working resolution.

        Raises
        ------
        InputError
            ``root`` is not a folder, holds no scores table, or the table is unreadable, lacks a column or has a
            bad row (naming the file and row).
        """
        self.root = Path(root)
        self.resolution = tuple(resolution)
        if not self.root.is_dir():
            raise InputError(f"{self.root}: teacher.imported_dir is not a directory")
        import pandas as pd

        found = [p for p in (self.root / "scores.parquet", self.root / "scores.csv") if p.exists()]
        if not found:
            raise InputError(f"{self.root}: no scores.parquet or scores.csv (layout: docs/real-data.md)")
        p = self.scores_path = found[0]
        try:
            table = pd.read_parquet(p) if p.suffix == ".parquet" else pd.read_csv(p)
        except Exception as e:  # noqa: BLE001 -- any parse failure is a user input problem
            raise InputError(f"{p}: unreadable scores table ({type(e).__name__})") from None
        missing = [c for c in ("image_id", "prompt_index", "prompt", "score") if c not in table.columns]
        if missing:
            raise InputError(f"{self.scores_path}: missing columns {missing}")
        table = self._checked(table.reset_index(drop=True))
        self.table = table.set_index(["image_id", "prompt", "view"])
        self._fp: str | None = None

    def _where(self, i: int, table: pd.DataFrame | None = None) -> str:
        """Name row ``i`` of the scores table: file, row, CSV line and, given ``table``, its image and prompt."""
        line = f", line {i + 2}" if self.scores_path.suffix == ".csv" else ""
        what = f" (image {table.at[i, 'image_id']!r}, prompt {table.at[i, 'prompt']!r})" if table is not None else ""
        return f"{self.scores_path}: row {i}{line}{what}"

    def _refuse_first(self, bad, table: pd.DataFrame | None, why) -> None:
        """Refuse the first row where ``bad`` holds: InputError naming it; ``why(i)`` says what is wrong."""
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InputError(f"{self._where(i, table)}: {why(i)}")

    def _checked(self, table: pd.DataFrame) -> pd.DataFrame:
        """Validate every row; scores -> float (missing = 0), indices -> int (missing = -1)."""
        import pandas as pd

        if "view" not in table.columns:
            table["view"] = "identity"
        for col in ("image_id", "prompt"):
            empty = table[col].isna() | (table[col].astype(str).str.strip() == "")
            self._refuse_first(empty, None, lambda i, col=col: f"empty {col}")
            table[col] = table[col].astype(str)
        table["view"] = table["view"].fillna("identity").astype(str)
        self._refuse_first(~table["view"].isin(["identity", "vflip"]), table,
                           lambda i: f"unknown view {table.at[i, 'view']!r} (identity | vflip)")

        def numeric(col: str) -> pd.Series:
            raw = table[col]
            num = pd.to_numeric(raw.where(raw.map(lambda v: not isinstance(v, bool)), "x"), errors="coerce")
            self._refuse_first(raw.notna() & num.isna(), table, lambda i: f"{col} {raw.iloc[i]!r} is not a number")
            return num.astype(float)

        score = numeric("score")
        self._refuse_first(score.notna() & ~(np.isfinite(score) & (score >= 0) & (score <= 1)), table,
                           lambda i: f"score {score.iloc[i]!r} must be a finite number in [0, 1]")
        score = score.fillna(0.0)
        index = numeric("prompt_index")
        bad = index.notna() & ~(np.isfinite(index) & (index == np.floor(index))
                                & (index >= 0) & (index <= MAX_PROMPT_INDEX))
        self._refuse_first(bad, table, lambda i: f"prompt_index {table['prompt_index'].iloc[i]!r} must be "
                                                 f"an integer in [0, {MAX_PROMPT_INDEX}]")
        self._refuse_first(index.isna() & (score > 0), table,
                           lambda i: "prompt_index missing (score > 0 needs a mask file)")
        table["score"] = score
        table["prompt_index"] = index.fillna(-1).astype(np.int64)
        self._refuse_first(table.duplicated(["image_id", "prompt", "view"]), table,
                           lambda i: "duplicate row for this image, prompt and view")
        valid = table["score"] > 0
        dup = table[valid].duplicated(["image_id", "view", "prompt_index"]).reindex(table.index, fill_value=False)
        self._refuse_first(valid & dup, table, lambda i: f"prompt_index {int(table.at[i, 'prompt_index'])} is used by "
                                                         f"another prompt of this image and view (both would read one "
                                                         f"mask file)")
        return table

    def content_hash(self) -> str:
        """Hash the imported answers: what determines them, computed once.

        Returns
        -------
        str
            The sha256 hex digest over the scores table and every mask file (relative path + bytes), sorted.
        """
        if self._fp is None:
            masks = sorted((self.root / "masks").rglob("*.png")) if (self.root / "masks").is_dir() else []
            self._fp = files_digest(self.root, masks, hashlib.sha256(self.scores_path.read_bytes()))
        return self._fp

    def fingerprint(self) -> dict:
        """Describe what determines the answers (:meth:`pipeline.teachers.base.Teacher.fingerprint`).

        Returns
        -------
        dict
            The backend, :meth:`content_hash` and the resolution.
        """
        return {"backend": BACKEND, "content": self.content_hash(), "resolution": list(self.resolution)}

    def _answer(self, image_id: str, prompt: str, view: str) -> tuple[np.ndarray, float]:
        """Read one answer: (mask, score); InputError naming a missing row or mask file."""
        try:
            row = self.table.loc[(image_id, prompt, view)]
        except KeyError:
            raise InputError(f"{self.scores_path}: no row for image {image_id!r}, prompt {prompt!r}, "
                             f"view {view}") from None
        score = float(row["score"])
        if score <= 0:
            return np.zeros(self.resolution, bool), 0.0
        stem = f"{int(row['prompt_index'])}" if view == "identity" else f"vflip_{int(row['prompt_index'])}"
        path = self.root / "masks" / image_id / f"{stem}.png"
        if not path.exists():
            raise InputError(f"{path}: mask file missing (score {score:.3f} > 0 needs a mask)")
        return read_mask_png(path, self.resolution), score

    def predict(self, batch: Sequence[TeacherInput], prompts: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        """Read the imported answers of ``batch`` (eq:teacher-prediction, computed elsewhere).

        A ``vflip`` mask is stored flipped back, so it is flipped here for the runner to undo.

        Parameters
        ----------
        batch : sequence of TeacherInput
            B images (their ids and views are read).
        prompts : sequence of str
            The K prompts.

        Returns
        -------
        tuple of numpy.ndarray
            Masks bool [B,K,H,W] and scores float32 [B,K] (:func:`pipeline.teachers.base.finalize_answers`).
        """
        masks = np.zeros((len(batch), len(prompts), *self.resolution), bool)
        scores = np.zeros((len(batch), len(prompts)), np.float32)
        for b, item in enumerate(batch):
            for k, prompt in enumerate(prompts):
                m, s = self._answer(item.image_id, prompt, item.view)
                masks[b, k] = m[::-1] if item.view == "vflip" else m
                scores[b, k] = s
        return finalize_answers(masks, scores)
