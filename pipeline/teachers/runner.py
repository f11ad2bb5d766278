"""Plan, shard, compute and collect teacher answers through the content-addressed cache.

The runner is backend-agnostic: it asks a :class:`~pipeline.teachers.base.Teacher` only for the
(image, prompt, view) answers that are not in the cache, in image batches, and writes each batch's
answers to the cache as soon as they exist (a kill -9 loses at most the batch in flight).

Work units
  For every manifest row in the teacher splits: the K prompts on the image as is (view ``identity``),
  and, when ``vflip_prompt`` is set, that one prompt on the vertically flipped image (view ``vflip``,
  answer flipped back) for the annotation-free-style control.

Sharding (``--shard i/n``, 0 <= i < n)
  Shard i owns the rows at positions i, i+n, i+2n, ... of the teacher-split rows in manifest order
  (round robin: balanced, and the same partition no matter when or where each shard starts or how
  much of the cache is already filled).  Within its rows a shard computes only what is missing.
"""

from __future__ import annotations

import dataclasses
import logging
import re
from typing import Callable, Sequence

import numpy as np

from pipeline.errors import InputError
from pipeline.progress import progress
from pipeline.teachers.base import Teacher, TeacherInput, finalize_answers
from pipeline.teachers.cache import TeacherCache

log = logging.getLogger(__name__)

# row index, view -> TeacherInput (image already in that view)
InputLoader = Callable[[int, str], TeacherInput]


def parse_shard(text: str | None) -> tuple[int, int] | None:
    """``"i/n"`` -> (i, n) with 0 <= i < n; None passes through; InputError names ``--shard`` otherwise."""
    if text is None:
        return None
    m = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", str(text))
    if not m:
        raise InputError(f"--shard {text!r}: expected i/n, e.g. 0/8 (0 <= i < n)")
    i, n = int(m.group(1)), int(m.group(2))
    if n < 1 or not 0 <= i < n:
        raise InputError(f"--shard {text!r}: need n >= 1 and 0 <= i < n")
    return i, n


def shard_rows(rows: Sequence[int], shard: tuple[int, int] | None) -> list[int]:
    """The rows shard (i, n) owns: positions i, i+n, ... of ``rows`` (all rows when shard is None)."""
    rows = list(rows)
    if shard is None:
        return rows
    i, n = shard
    return rows[i::n]


def flip_answer(mask: np.ndarray) -> np.ndarray:
    """Undo the vertical flip of the ``vflip`` view (rows reversed; an involution)."""
    return np.ascontiguousarray(mask[..., ::-1, :])


@dataclasses.dataclass
class RunStats:
    images_computed: int = 0
    answers_computed: int = 0
    cache_hits: int = 0
    cache_corrupt: int = 0


class TeacherRunner:
    """Fill the cache for some rows, then read every row's answers back.

    ``image_sha`` maps a row to its manifest sha256; ``load`` builds the :class:`TeacherInput` of a
    row in a view.  With ``teacher.use_cache`` false (imported masks) the cache is bypassed and
    :meth:`answers` asks the teacher directly.
    """

    def __init__(self, teacher: Teacher, cache: TeacherCache, prompts: Sequence[str],
                 image_sha: Callable[[int], str], load: InputLoader, vflip_prompt: str | None = None,
                 batch_size: int = 1):
        self.teacher = teacher
        self.cache = cache
        self.prompts = list(prompts)
        self.image_sha = image_sha
        self.load = load
        self.vflip_prompt = vflip_prompt
        self.batch_size = max(int(batch_size), 1)
        self.stats = RunStats()

    # ---- planning -----------------------------------------------------------------------------
    def requests(self) -> list[tuple[str, str]]:
        """(prompt, view) pairs answered per image."""
        req = [(p, "identity") for p in self.prompts]
        if self.vflip_prompt is not None:
            req.append((self.vflip_prompt, "vflip"))
        return req

    def missing(self, rows: Sequence[int]) -> dict[str, dict[int, list[str]]]:
        """view -> row -> prompts whose cache entry is absent or corrupt (corrupt ones are removed)."""
        out: dict[str, dict[int, list[str]]] = {"identity": {}, "vflip": {}}
        if not self.teacher.use_cache:
            return out
        for row in progress(rows, desc="teacher: checking cache"):
            sha = self.image_sha(row)
            for prompt, view in self.requests():
                if self.cache.get(self.cache.key(sha, prompt, view)) is None:
                    out[view].setdefault(row, []).append(prompt)
        return out

    # ---- computing ----------------------------------------------------------------------------
    def _compute(self, rows: Sequence[int], prompts: Sequence[str], view: str) -> tuple[np.ndarray, np.ndarray]:
        batch = [self.load(r, view) for r in rows]
        masks, scores = self.teacher.predict(batch, list(prompts))
        masks, scores = finalize_answers(masks, scores)
        if masks.shape[:2] != (len(rows), len(prompts)):
            raise RuntimeError(f"teacher {self.teacher.backend} returned masks {masks.shape} for "
                               f"{len(rows)} images x {len(prompts)} prompts")
        if view == "vflip":
            masks = flip_answer(masks)
        return masks, scores

    def fill(self, rows: Sequence[int]) -> RunStats:
        """Compute and cache every missing answer of ``rows``; returns the run's statistics."""
        if not self.teacher.use_cache:
            return self.stats
        todo = self.missing(rows)
        corrupt = self.cache.stats.corrupt
        n_images = len(set(todo["identity"]) | set(todo["vflip"]))
        log.info("teacher[%s]: %d of %d images need answers (%d cached answers reused, %d corrupt entries "
                 "to recompute)", self.teacher.backend, n_images, len(rows), self.cache.stats.hits, corrupt)
        self.stats.cache_hits += self.cache.stats.hits
        self.stats.cache_corrupt += corrupt
        jobs: list[tuple[str, list[int]]] = []
        for view in ("identity", "vflip"):
            pending = sorted(todo[view])
            jobs += [(view, pending[i:i + self.batch_size]) for i in range(0, len(pending), self.batch_size)]
        for view, batch_rows in progress(jobs, desc=f"teacher[{self.teacher.backend}]"):
            # one forward per batch over the union of the batch's missing prompts; only the missing
            # entries are written, so a cached answer is never overwritten by a recomputation
            prompts = [p for p in (self.prompts if view == "identity" else [self.vflip_prompt])
                       if any(p in todo[view][r] for r in batch_rows)]
            masks, scores = self._compute(batch_rows, prompts, view)
            for b, row in enumerate(batch_rows):
                sha = self.image_sha(row)
                for k, prompt in enumerate(prompts):
                    if prompt in todo[view][row]:
                        self.cache.put(self.cache.key(sha, prompt, view), masks[b, k], float(scores[b, k]))
                        self.stats.answers_computed += 1
        self.stats.images_computed += n_images
        return self.stats

    # ---- collecting ---------------------------------------------------------------------------
    def answers(self, row: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, float | None]:
        """(masks bool [K,H,W], scores float32 [K], vflip mask or None, vflip score or None) of one row.

        Reads the cache; an entry missing here (removed since :meth:`fill`, or a cache-less backend)
        is computed on the spot and cached.
        """
        results: dict[tuple[str, str], tuple[np.ndarray, float]] = {}
        if self.teacher.use_cache:
            sha = self.image_sha(row)
            for prompt, view in self.requests():
                hit = self.cache.get(self.cache.key(sha, prompt, view))
                if hit is not None:
                    results[(prompt, view)] = hit
        for view in ("identity", "vflip"):
            need = [p for p, v in self.requests() if v == view and (p, v) not in results]
            if not need:
                continue
            masks, scores = self._compute([row], need, view)
            for k, prompt in enumerate(need):
                results[(prompt, view)] = (masks[0, k], float(scores[0, k]))
                if self.teacher.use_cache:
                    self.cache.put(self.cache.key(self.image_sha(row), prompt, view), masks[0, k], float(scores[0, k]))
                    self.stats.answers_computed += 1
        masks = np.stack([results[(p, "identity")][0] for p in self.prompts])
        scores = np.array([results[(p, "identity")][1] for p in self.prompts], np.float32)
        if self.vflip_prompt is None:
            return masks, scores, None, None
        vm, vs = results[(self.vflip_prompt, "vflip")]
        return masks, scores, vm, float(vs)
