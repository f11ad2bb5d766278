"""Manifest rows (:class:`DatasetSpec`), protocol checks and the one bad-input policy (:class:`BadInputPolicy`).

A bad file is a one-line :class:`InputError`, or with ``skip_bad`` a listed ``(image_id, path, reason)``.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Iterable

import pandas as pd

from pipeline.artifacts.atomic import write_csv
from pipeline.runtime.errors import SKIP_BAD, InputError, Option, literal
from pipeline.params import SPLITS

__all__ = ["ROW_COLUMNS", "DatasetSpec", "BadInputPolicy", "write_skipped_csv", "drop_duplicate_ids", "relative_id",
           "enforce_spacecraft_disjoint", "check_rows", "check_manifest"]

log = logging.getLogger(__name__)

MANIFEST_COLUMNS = ("image_id", "dataset", "domain", "split", "group", "spacecraft", "image_path",
                    "mask_path", "part_path", "width", "height", "sha256")
ROW_COLUMNS = MANIFEST_COLUMNS[:9]   # what a source provides; width/height/sha256 come from decoding
SKIPPED_COLUMNS = ("image_id", "path", "reason")


@dataclasses.dataclass
class DatasetSpec:
    """A source's manifest rows plus what its protocol says about reading them.

    How a frame file is read from the params (bit depth, letterbox, pixel limit) is not here:
    :class:`pipeline.datasets.params.FrameSettings`.

    Attributes
    ----------
    rows : pandas.DataFrame
        At least :data:`ROW_COLUMNS`; extra columns are kept.
    mask_threshold : float or None
        Foreground = max channel > threshold (None: the loader's rule, > 0).
    part_colors : dict or ColorTable or None
        The colour table of colour-coded part masks (None: label images, or none).
    spacecraft_disjoint : bool
        Whether the protocol requires eq:spacecraft-disjoint (checked, and enforced under ``skip_bad``).
    protocol : dict
        What the protocol records, kept in the manifest metadata.
    skipped : list of dict
        What a scanning source left out or did not use (:attr:`BadInputPolicy.skipped` entries), listed first.
    """

    rows: pd.DataFrame
    mask_threshold: float | None = None
    part_colors: dict | None = None
    spacecraft_disjoint: bool = True
    protocol: dict = dataclasses.field(default_factory=dict)
    skipped: list[dict] = dataclasses.field(default_factory=list)


#: what a refusal suggests, ``{}`` naming ``--skip-bad`` / ``skip_bad=True`` in the caller's terms
SKIP_HINT = "pass {}, or set data.skip_bad: true in params.yaml, to leave it out"


class BadInputPolicy:
    """The one bad-file policy (docs/own-data.md).

    Raise on the first problem, or (``skip_bad``) list it with its reason and let the caller drop the row.

    Parameters
    ----------
    skip_bad : bool
        List bad files instead of refusing them (``data.skip_bad``).
    hint : str
        The refusal's suggestion, ``{}`` naming ``hint_options`` in the caller's terms.
    hint_options : tuple of Option, optional
        The options of the hint's ``{}``; None with the default hint: ``--skip-bad`` / ``skip_bad=True``.
    """

    def __init__(self, skip_bad: bool, hint: str = SKIP_HINT, hint_options: tuple[Option, ...] | None = None):
        self.skip_bad = bool(skip_bad)
        self.hint = hint
        self.hint_options = (SKIP_BAD,) if hint_options is None and hint == SKIP_HINT else tuple(hint_options or ())
        self.skipped: list[dict] = []

    def report(self, image_id: str | None, path: str, reason: str, fix: str = "", options: tuple[Option, ...] = ()
               ) -> None:
        """Refuse ``path`` (``path: reason (fix; hint)``) or, with ``skip_bad``, list it with ``reason``.

        Parameters
        ----------
        image_id : str or None
            The row the file belongs to (None: none yet).
        path : str
            The file.
        reason : str
            Why it is bad.
        fix : str
            What would let the file in, naming ``options``; empty: nothing.
        options : tuple of Option
            The options ``fix`` names.

        Raises
        ------
        InputError
            Without ``skip_bad``: one line naming the file, the reason, the fix and the hint.
        """
        msg = f"{path}: {reason}" if not reason.startswith(str(path)) else reason
        if not self.skip_bad:
            opts = (*options, *self.hint_options)
            hint = self.hint if self.hint_options else literal(self.hint) if opts else self.hint
            text = literal(msg) if opts else msg
            raise InputError(f"{text} ({fix + '; ' if fix else ''}{hint})", *opts)
        log.info("skipping %s", msg)
        self.skipped.append({"image_id": image_id or "", "path": str(path), "reason": reason})

    def report_error(self, image_id: str | None, error, row_files: Iterable[str] = ()) -> None:
        """:meth:`report` a :class:`pipeline.datasets.loading.BadFileError` (its path, reason, fix).

        With ``skip_bad`` its row is left out, so the row's other files that exist are then :meth:`record`-ed as
        not used.

        Parameters
        ----------
        image_id : str or None
            The row the file belongs to.
        error : BadFileError
            The refusal to report.
        row_files : iterable of str
            The files of the row (image, mask, part); empty: the file alone is reported.

        Raises
        ------
        InputError
            Without ``skip_bad`` (:meth:`report`).
        """
        self.report(image_id, error.path, error.reason, error.fix, error.options)
        for other in row_files:
            if other != error.path and (Path(other).exists() or Path(other).is_symlink()):
                self.record(image_id, other, f"not used: image {image_id!r} was left out "
                                             f"({Path(error.path).name}: {error.reason})")

    def report_scan(self, found) -> None:
        """:meth:`report` a folder scan's bad entries and :meth:`record` its unused files.

        Parameters
        ----------
        found : pipeline.datasets.scan.FolderScan
            The scan; each entry is named by its id in ``found.root`` (:func:`relative_id`).

        Raises
        ------
        InputError
            A bad entry, without ``skip_bad`` (:meth:`report`).
        """
        for tell, entries in ((self.report, found.skipped), (self.record, found.unused)):
            for path, reason in entries:
                tell(relative_id(found.root, path), path, reason)

    def _bad(self) -> list[dict]:
        return [r for r in self.skipped if not r.get("listed_only")]

    def bad_count(self) -> int:
        """Count the files left out by :meth:`report` (not the ones merely listed by :meth:`record`).

        Returns
        -------
        int
            How many.
        """
        return len(self._bad())

    def summary(self, command: str, listing) -> str | None:
        """Write the one stderr line a command prints at its end when bad files were left out.

        Parameters
        ----------
        command : str
            The command's name, opening the line.
        listing : str or Path
            Where every skipped file is listed with its reason.

        Returns
        -------
        str or None
            The line; None when no file was left out.
        """
        bad = self._bad()
        if not bad:
            return None
        return (f"{command}: skipped {len(bad)} bad file(s) (first: {bad[0]['path']}: {bad[0]['reason']}); "
                f"all are listed with the reason in {listing}")

    def record(self, image_id: str | None, path: str, reason: str) -> None:
        """List a file that is not used without it being an error (hidden files, a dropped row's other files).

        Parameters
        ----------
        image_id : str or None
            The row the file belongs to.
        path : str
            The file.
        reason : str
            Why it is not used.
        """
        log.info("not using %s: %s", path, reason)
        self.skipped.append({"image_id": image_id or "", "path": str(path), "reason": reason, "listed_only": True})

    def table(self) -> pd.DataFrame:
        """Tabulate every listed file, as skipped_files.parquet holds them.

        Returns
        -------
        pandas.DataFrame
            Columns ``image_id``, ``path``, ``reason`` (strings), in the order listed.
        """
        return pd.DataFrame(self.skipped, columns=list(SKIPPED_COLUMNS)).astype(str)

    def rows(self) -> list[tuple[str, str, str]]:
        """List ``(image_id, path, reason)`` per listed file: the rows of ``skipped.csv``.

        Returns
        -------
        list of tuple
            One per listed file, in the order listed.
        """
        return [(r["image_id"], r["path"], r["reason"]) for r in self.skipped]


def write_skipped_csv(path: str | Path, skipped: Iterable[tuple[str, str, str]]) -> Path:
    """Write ``skipped.csv`` (the columns of skipped_files.parquet).

    Parameters
    ----------
    path : str or Path
        The file, written atomically.
    skipped : iterable of tuple
        ``(image_id, path, reason)`` rows (:meth:`BadInputPolicy.rows`).

    Returns
    -------
    Path
        The file written.
    """
    return write_csv(path, list(SKIPPED_COLUMNS), skipped)


def drop_duplicate_ids(rows: pd.DataFrame, policy: BadInputPolicy) -> pd.DataFrame:
    """Keep the first row of each image id: ids are unique, since every N-indexed artifact is keyed by them.

    Parameters
    ----------
    rows : pandas.DataFrame
        Manifest rows.
    policy : BadInputPolicy
        Refuses each later duplicate, or lists it.

    Returns
    -------
    pandas.DataFrame
        The rows kept, re-indexed.
    """
    dup = rows["image_id"].duplicated(keep="first")
    for _, r in rows[dup].iterrows():
        first = rows.loc[rows["image_id"] == r["image_id"], "image_path"].iloc[0]
        policy.report(r["image_id"], r["image_path"],
                      f"duplicate image id {r['image_id']!r} (also used by {first})")
    return rows[~dup].reset_index(drop=True)


def relative_id(root: Path, path: str | Path) -> str:
    """Name the image id of ``path``: its posix path relative to ``root`` without the suffix.

    Parameters
    ----------
    root : Path
        The folder the ids are relative to.
    path : str or Path
        A file.

    Returns
    -------
    str
        The id; the file's stem when it is outside ``root``.
    """
    try:
        return Path(path).relative_to(root).with_suffix("").as_posix()
    except ValueError:
        return Path(path).stem


SPLIT_PRIORITY = {"test": 0, "val": 1, "train": 2}


def spacecraft_split_violations(rows: pd.DataFrame) -> dict[str, list[str]]:
    """eq:spacecraft-disjoint: S_tr ∩ S_ev = ∅ (and val vs test).  Returns {spacecraft: splits} for violators."""
    splits = rows.groupby("spacecraft")["split"].agg(lambda s: sorted(set(s), key=SPLIT_PRIORITY.get))
    return {sc: sp for sc, sp in splits.items() if len(sp) > 1}


def enforce_spacecraft_disjoint(rows: pd.DataFrame, policy: BadInputPolicy) -> pd.DataFrame:
    """Enforce eq:spacecraft-disjoint, S_tr ∩ S_ev = ∅ (and val against test).

    A spacecraft in two splits is refused; with ``skip_bad`` it is kept only in its highest-priority split
    (test > val > train: the evaluation groups are the protocol's fixed sets).

    Parameters
    ----------
    rows : pandas.DataFrame
        Manifest rows.
    policy : BadInputPolicy
        Refuses a violating row, or lists it.

    Returns
    -------
    pandas.DataFrame
        The rows kept, re-indexed.
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
    """Check the columns and split names of a source's rows (a bug or a bad protocol file, never skipped).

    Parameters
    ----------
    rows : pandas.DataFrame
        A source's rows.
    where : str
        What the error names (``data.source=...``, a protocol file).

    Returns
    -------
    pandas.DataFrame
        ``rows``, unchanged.

    Raises
    ------
    InputError
        A missing column of :data:`ROW_COLUMNS`, an unknown split name, or no rows.
    """
    missing = [c for c in ROW_COLUMNS if c not in rows.columns]
    if missing:
        raise InputError(f"{where}: manifest rows lack columns {missing}")
    bad = sorted(set(rows["split"]) - set(SPLITS))
    if bad:
        raise InputError(f"{where}: unknown split names {bad} (use {list(SPLITS)})")
    if rows.empty:
        raise InputError(f"{where}: no images found")
    return rows


def check_manifest(spec: DatasetSpec, policy: BadInputPolicy, where: str = "manifest") -> pd.DataFrame:
    """Check a source's rows: columns, splits, unique image ids, and eq:spacecraft-disjoint where required.

    Parameters
    ----------
    spec : DatasetSpec
        The source's rows; ``spec.spacecraft_disjoint`` says whether its protocol requires the split rule.
    policy : BadInputPolicy
        Takes over what the source listed (``spec.skipped``); refuses a duplicate id or a spacecraft in two splits,
        or (``skip_bad``) lists it and drops the row.
    where : str
        What the refusals name (``data.source=...``).

    Returns
    -------
    pandas.DataFrame
        The rows kept.

    Raises
    ------
    InputError
        Missing columns, unknown split names or no rows (never skipped), or a refused row.
    """
    policy.skipped.extend(spec.skipped)
    rows = check_rows(spec.rows, where)
    rows = drop_duplicate_ids(rows, policy)
    if spec.spacecraft_disjoint:
        rows = enforce_spacecraft_disjoint(rows, policy)
    return rows

