"""Manifest rows, protocol checks and the bad-input policy.

A dataset source (synthetic generator or a real-dataset adapter) yields a :class:`DatasetSpec`: the
manifest rows (without the decode-time columns width/height/sha256), how to read its masks, and
whether its protocol is spacecraft-disjoint.  Problems found anywhere -- a duplicate image id, a
spacecraft in two splits, a missing/zero-byte/corrupt/unsupported file, a broken symbolic link, a
directory where a file belongs, a mask without an image, several masks for one image, a mask whose
size differs from its image -- go through one policy (:class:`BadInputPolicy`): raise a one-line
:class:`InputError` naming the file, or with ``skip_bad`` leave the row out and record
``(image_id, path, reason)`` for ``skipped_files.parquet``.  Never silent: a file a source finds
and does not use is either an error or a row of that table.  The only files recorded without
being an error are hidden ones (name starting with ``.``, e.g. ``.DS_Store``) and the other files
of a row already left out (:meth:`BadInputPolicy.record`).
"""

from __future__ import annotations

import dataclasses
import logging

import pandas as pd

from pipeline.runtime.errors import SKIP_BAD, InputError, Option, literal
from pipeline.params import SPLITS

log = logging.getLogger(__name__)

MANIFEST_COLUMNS = ("image_id", "dataset", "domain", "split", "group", "spacecraft", "image_path",
                    "mask_path", "part_path", "width", "height", "sha256")
ROW_COLUMNS = MANIFEST_COLUMNS[:9]   # what a source provides; width/height/sha256 come from decoding
SKIPPED_COLUMNS = ("image_id", "path", "reason")


@dataclasses.dataclass
class DatasetSpec:
    """A source's manifest rows plus how to read them.

    rows: DataFrame with at least ``ROW_COLUMNS`` (extra columns are kept in the manifest).
    mask_threshold: foreground = max channel > threshold (None: auto, see loading.mask_from_array).
    part_colors: colour table for colour-coded part masks ``{(r, g, b): label}`` or a
        :class:`pipeline.datasets.loading.ColorTable` (with a tolerance); None = part files
        are label images (synthetic) or there are no part files.
    spacecraft_disjoint: enforce eq:spacecraft-disjoint (SpaceSense-Bench-like protocols).
    protocol: a small dict describing the protocol used (kept in the manifest metadata).
    max_pixels: the pixel limit its files are read under (params ``data.max_pixels``; None: the
        default, :data:`pipeline.datasets.loading.DEFAULT_MAX_PIXELS`), checked on each file's header.
    bit_depth, letterbox: how frames are read and resized (params ``data.bit_depth``, ``data.letterbox``;
        :func:`pipeline.datasets.loading.load_rgb`).
    """

    rows: pd.DataFrame
    mask_threshold: float | None = None
    part_colors: dict | None = None
    spacecraft_disjoint: bool = True
    protocol: dict = dataclasses.field(default_factory=dict)
    max_pixels: int | None = None
    bit_depth: str | int = "auto"
    letterbox: bool = False


#: what a refusal suggests (a template naming ``--skip-bad`` / ``skip_bad=True`` in the caller's terms,
#: pipeline.runtime.errors): both work for prepare and distill (and label, which reads data.skip_bad too)
SKIP_HINT = "pass {}, or set data.skip_bad: true in params.yaml, to leave it out"


class BadInputPolicy:
    """Raise on the first problem, or (``skip_bad``) record it and let the caller drop the row.

    The one bad-file policy of prepare (folder source), label, distill and segment (docs/own-data.md):
    without ``--skip-bad`` the first bad file stops the run with one line naming it and the option;
    with it, bad files are left out, listed with their reason (``skipped_files.parquet`` /
    ``skipped.csv``, columns :data:`SKIPPED_COLUMNS`) and counted in one stderr line
    (:meth:`summary`).  ``hint``: the refusal's suggestion (a command without params: only
    ``--skip-bad``).  ``hint_options``: the options of ``hint``'s ``{}`` (default: ``--skip-bad``),
    spelled in the caller's terms (:class:`pipeline.runtime.errors.InputError`); a hint without options is
    taken as it is."""

    def __init__(self, skip_bad: bool, hint: str = SKIP_HINT, hint_options: tuple[Option, ...] | None = None):
        self.skip_bad = bool(skip_bad)
        self.hint = hint
        self.hint_options = (SKIP_BAD,) if hint_options is None and hint == SKIP_HINT else tuple(hint_options or ())
        self.skipped: list[dict] = []

    def report(self, image_id: str | None, path: str, reason: str, fix: str = "", options: tuple[Option, ...] = ()
               ) -> None:
        """Refuse ``path`` (InputError: ``path: reason (fix; hint)``) or, with ``skip_bad``, list it
        with ``reason``.  ``fix``: a template naming ``options`` that would let the file in (a
        :class:`pipeline.datasets.loading.BadFileError`'s ``fix``)."""
        msg = f"{path}: {reason}" if not reason.startswith(str(path)) else reason
        if not self.skip_bad:
            opts = (*options, *self.hint_options)
            hint = self.hint if self.hint_options else literal(self.hint) if opts else self.hint
            text = literal(msg) if opts else msg
            raise InputError(f"{text} ({fix + '; ' if fix else ''}{hint})", *opts)
        log.info("skipping %s", msg)
        self.skipped.append({"image_id": image_id or "", "path": str(path), "reason": reason})

    def report_error(self, image_id: str | None, error) -> None:
        """:meth:`report` of a :class:`pipeline.datasets.loading.BadFileError` (its path, reason, fix)."""
        self.report(image_id, error.path, error.reason, error.fix, error.options)

    def bad_count(self) -> int:
        """Files left out by :meth:`report` (not the ones merely listed by :meth:`record`)."""
        return sum(1 for r in self.skipped if not r.get("listed_only"))

    def summary(self, command: str, listing) -> str | None:
        """The one stderr line every command prints at its end when bad files were left out: how
        many, the first one, and where all are listed; None when there were none."""
        bad = [r for r in self.skipped if not r.get("listed_only")]
        if not bad:
            return None
        return (f"{command}: skipped {len(bad)} bad file(s) (first: {bad[0]['path']}: {bad[0]['reason']}); "
                f"all are listed with the reason in {listing}")

    def record(self, image_id: str | None, path: str, reason: str) -> None:
        """List a file that is not used without it being an error (hidden files; the other files of a
        row already reported)."""
        log.info("not using %s: %s", path, reason)
        self.skipped.append({"image_id": image_id or "", "path": str(path), "reason": reason, "listed_only": True})

    def table(self) -> pd.DataFrame:
        return pd.DataFrame(self.skipped, columns=list(SKIPPED_COLUMNS)).astype(str)

    def rows(self) -> list[tuple[str, str, str]]:
        """(image_id, path, reason) per listed file: the rows of ``skipped.csv``."""
        return [(r["image_id"], r["path"], r["reason"]) for r in self.skipped]


def drop_duplicate_ids(rows: pd.DataFrame, policy: BadInputPolicy) -> pd.DataFrame:
    """Image ids must be unique (every N-indexed artifact is keyed by them); keep the first."""
    dup = rows["image_id"].duplicated(keep="first")
    for _, r in rows[dup].iterrows():
        first = rows.loc[rows["image_id"] == r["image_id"], "image_path"].iloc[0]
        policy.report(r["image_id"], r["image_path"],
                      f"duplicate image id {r['image_id']!r} (also used by {first})")
    return rows[~dup].reset_index(drop=True)


SPLIT_PRIORITY = {"test": 0, "val": 1, "train": 2}


def spacecraft_split_violations(rows: pd.DataFrame) -> dict[str, list[str]]:
    """eq:spacecraft-disjoint: S_tr ∩ S_ev = ∅ (and val vs test).  Returns {spacecraft: splits} for violators."""
    splits = rows.groupby("spacecraft")["split"].agg(lambda s: sorted(set(s), key=SPLIT_PRIORITY.get))
    return {sc: sp for sc, sp in splits.items() if len(sp) > 1}


def enforce_spacecraft_disjoint(rows: pd.DataFrame, policy: BadInputPolicy) -> pd.DataFrame:
    """Error on a spacecraft in two splits; with skip_bad keep it only in its highest-priority split.

    Priority test > val > train: the evaluation groups are the protocol's fixed sets, so the
    contaminating copies are removed from the split that would otherwise leak them (training).
    """
    bad = spacecraft_split_violations(rows)
    if not bad:
        return rows
    keep = pd.Series(True, index=rows.index)
    for sc, splits in bad.items():
        for split in splits[1:]:
            sel = (rows["spacecraft"] == sc) & (rows["split"] == split)
            for _, r in rows[sel].iterrows():
                policy.report(r["image_id"], r["image_path"],
                              f"spacecraft {sc!r} appears in splits {splits} (violates eq:spacecraft-disjoint)")
            keep &= ~sel
    return rows[keep].reset_index(drop=True)


def check_rows(rows: pd.DataFrame, where: str) -> pd.DataFrame:
    """Columns and split names of a source's rows (a bug or a bad protocol file, never skipped)."""
    missing = [c for c in ROW_COLUMNS if c not in rows.columns]
    if missing:
        raise InputError(f"{where}: manifest rows lack columns {missing}")
    bad = sorted(set(rows["split"]) - set(SPLITS))
    if bad:
        raise InputError(f"{where}: unknown split names {bad} (use {list(SPLITS)})")
    if rows.empty:
        raise InputError(f"{where}: no images found")
    return rows
