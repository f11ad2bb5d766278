"""Real-dataset readers: a root directory + a protocol file (``data_manifests/*.yaml``) -> manifest rows.

The files are not opened here (layouts: docs/real-data.md; choices: docs/decisions.md, "Dataset readers").
"""

from __future__ import annotations

import csv
import itertools
import json
import logging
import re
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.datasets.loading import ColorTable
from pipeline.datasets.manifest import ROW_COLUMNS, BadInputPolicy, DatasetSpec, relative_id
from pipeline.datasets.scan import scan_inputs
from pipeline.datasets.synthetic import stable_hash
from pipeline.runtime.errors import InputError
from pipeline.params import read_yaml_mapping

__all__ = ["row", "build_source"]

log = logging.getLogger(__name__)

MANIFEST_DIR = Path(__file__).resolve().parents[2] / "data_manifests"
DEFAULT_PROTOCOLS = {
    "spacesense": "spacesense_bench.yaml",
    "spark": "spark.yaml",
    "speedplus": "speedplus.yaml",
    "tango": "tango.yaml",
    "folder": "folder.yaml",
}


def load_protocol(source: str, path: str | None) -> tuple[dict, Path]:
    """Read a protocol YAML (default: ``data_manifests/<source's file>``); InputError naming the file."""
    p = Path(path) if path else MANIFEST_DIR / DEFAULT_PROTOCOLS[source]
    proto = read_yaml_mapping(p, "protocol file")
    declared = proto.get("dataset")
    if declared is not None and declared != source:
        raise InputError(f"{p}: protocol is for dataset {declared!r}, not {source!r}")
    return proto, p


def _get(proto: dict, key: str, where: Path, kind=object):
    if key not in proto:
        raise InputError(f"{where}: protocol key {key!r} missing")
    v = proto[key]
    if kind is not object and not isinstance(v, kind):
        raise InputError(f"{where}: protocol key {key!r}={v!r} has the wrong type")
    return v


def _rng(seed: int, key: str) -> np.random.Generator:
    return np.random.default_rng([int(seed), stable_hash(key)])


def _sample(items: list, k: int | None, seed: int, key: str) -> list:
    """Seeded draw of ``k`` items without replacement, returned in their original order; None = all."""
    if k is None or k >= len(items):
        return list(items)
    idx = np.sort(_rng(seed, key).choice(len(items), size=int(k), replace=False))
    return [items[i] for i in idx]


def _root(cfg: dict) -> Path:
    root = Path(cfg["root"])
    if not root.is_dir():
        raise InputError(f"{root}: dataset root (data.root) not found or not a directory")
    return root


def row(image_id, dataset, domain, split, group, spacecraft, image_path, mask_path=None, part_path=None, **extra):
    """Make one manifest row (the columns :data:`pipeline.datasets.manifest.ROW_COLUMNS`, then ``extra``).

    Parameters
    ----------
    image_id : str
        The row's unique id (every N-indexed artifact is keyed by it).
    dataset : str
        The source's name (``synthetic``, ``spark``, ...).
    domain : str
        The imaging domain (SPEED+: ``lightbox``, ``sunlamp``, ``synthetic``; else the dataset's name).
    split : str
        ``train``, ``val`` or ``test``.
    group : str
        The evaluation group (a test group, or the split's name).
    spacecraft : str
        The spacecraft identity that eq:spacecraft-disjoint keeps within one split.
    image_path : str or Path
        The image file.
    mask_path : str or Path, optional
        The reference mask file (None or empty: none).
    part_path : str or Path, optional
        The part-label file (None or empty: none).
    **extra
        Further columns kept as given (a trajectory, the official split, ...).

    Returns
    -------
    dict
        ``{column: value}``; paths as strings, absent masks and parts as None.
    """
    return {"image_id": image_id, "dataset": dataset, "domain": domain, "split": split, "group": group,
            "spacecraft": spacecraft, "image_path": str(image_path),
            "mask_path": str(mask_path) if mask_path else None,
            "part_path": str(part_path) if part_path else None, **extra}


def _frame(rows: list[dict]) -> pd.DataFrame:
    return pd.DataFrame(rows, columns=None if rows else list(ROW_COLUMNS))


def _parse_colors(proto: dict, where: Path) -> ColorTable | None:
    """Read the protocol's ``part_colors`` ("R,G,B": label), ``color_tolerance`` and ``color_blends``.

    Returns a :class:`~pipeline.datasets.loading.ColorTable`, or None when the table is empty.
    """
    out = {}
    for key, label in (proto.get("part_colors") or {}).items():
        try:
            rgb = tuple(int(v) for v in str(key).replace(" ", "").split(","))
            assert len(rgb) == 3 and all(0 <= v <= 255 for v in rgb) and 0 <= int(label) <= 255
        except (ValueError, AssertionError):
            raise InputError(f"{where}: part_colors entry {key!r}: {label!r} is not 'R,G,B': label") from None
        out[rgb] = int(label)
    tol, blends = proto.get("color_tolerance", 0), proto.get("color_blends", False)
    if isinstance(tol, bool) or not isinstance(tol, int) or not 0 <= tol <= 127:
        raise InputError(f"{where}: color_tolerance={tol!r} must be a whole number in [0, 127]")
    if not isinstance(blends, bool):
        raise InputError(f"{where}: color_blends={blends!r} must be true or false")
    if not out:
        return None
    table = ColorTable(out, tol, blends)
    for a, b in itertools.combinations(table.entries(), 2):
        if max(abs(x - y) for x, y in zip(a, b)) <= 2 * tol:
            raise InputError(f"{where}: part colours {a} and {b} are within 2 x color_tolerance={tol} of "
                             f"each other (a pixel could match both)")
    return table


def _disjoint_plan(found: dict[str, list], splits: dict, where: Path, root: Path, seed: int, name: str
                   ) -> list[tuple[str, str, str, int]]:
    """Plan eq:spacecraft-disjoint ``[(spacecraft, split, group, images)]`` from a protocol's ``splits``.

    Test groups first, then val and train, each of named spacecraft or a seeded draw of ``count`` from the rest.
    """
    groups = _get(splits, "test_groups", where, dict)
    used: set[str] = set()
    plan: list[tuple[str, str, str, int]] = []

    def take(names, split, group, per):
        for n in names:
            if n not in found:
                raise InputError(f"{where}: spacecraft {n!r} ({split}/{group}) not found under {root} "
                                 f"(found: {', '.join(sorted(found))})")
            if n in used:
                raise InputError(f"{where}: spacecraft {n!r} listed in more than one split "
                                 f"(violates eq:spacecraft-disjoint)")
            used.add(n)
            plan.append((n, split, group, per))

    def draw(count, split, group):
        rest = sorted(set(found) - used - named)
        if count > len(rest):
            raise InputError(f"{where}: {group} needs {count} spacecraft, only {len(rest)} unassigned under {root}")
        return _sample(rest, count, seed, f"{name}-{group}-spacecraft")

    per_test = int(splits.get("test_images_per_spacecraft", 20))
    named = {n for v in groups.values() if isinstance(v, list) for n in v}
    for g, names in groups.items():
        if isinstance(names, int) and not isinstance(names, bool):
            names = draw(names, "test", str(g))
        take(list(names or []), "test", str(g), per_test)
    named = set()
    for split in ("val", "train"):
        s = _get(splits, split, where, dict)
        names = s.get("spacecraft")
        if names is None:
            names = draw(int(_get(s, "count", where, int)), split, split)
        take(list(names), split, split, int(_get(s, "images_per_spacecraft", where, int)))
    return plan


def _disjoint_source(name: str, found: dict[str, list[tuple[str, Path, Path]]], cfg: dict, proto: dict,
                     where: Path, root: Path, column: str, mask_threshold: float) -> DatasetSpec:
    """List the rows of a spacecraft-disjoint dataset from ``found`` {spacecraft: [(sub, image, mask)]}.

    Each id is ``<spacecraft>__<sub>__<image stem>``, ``sub`` kept in ``column``; masks on validation and test rows.
    """
    seed = int(cfg["seed"])
    plan = _disjoint_plan(found, _get(proto, "splits", where, dict), where, root, seed, name)
    colors = _parse_colors(proto, where)
    rows = []
    for sc, split, group, per in plan:
        items = _sample(found[sc], per, seed, f"{name}-{sc}")
        if len(items) < per:
            log.warning("%s: spacecraft %s has %d images, protocol asks %d", root, sc, len(items), per)
        labeled = split != "train"
        for sub, img, mask in items:
            rows.append(row(f"{sc}__{sub}__{Path(img).stem}", name, name, split, group, sc, img,
                             mask if labeled else None, mask if labeled and colors else None, **{column: sub}))
    return DatasetSpec(rows=_frame(rows), mask_threshold=mask_threshold, part_colors=colors,
                       spacecraft_disjoint=True,
                       protocol={"name": name, "file": str(where), "plan": [list(p) for p in plan]})


_TIMESTAMP = re.compile(r"^(\d+)_(.+)$")


def spacecraft_identity(folder_name: str) -> str:
    """Satellite folder name minus a leading all-digit timestamp token (never split otherwise)."""
    m = _TIMESTAMP.match(folder_name)
    return m.group(2) if m else folder_name


def scan_spacesense(root: Path) -> dict[str, list[tuple[str, Path, Path]]]:
    """{identity: [(trajectory, image_path, seg_path), ...]} sorted; depth/lidar folders ignored."""
    found: dict[str, list] = {}
    for sat in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")):
        ident = spacecraft_identity(sat.name)
        for img_dir in sorted(sat.rglob("image")):
            if not img_dir.is_dir():
                continue
            traj = img_dir.parent.name
            for f in sorted(img_dir.iterdir()):
                if (f.is_file() or f.is_symlink()) and not f.name.startswith("."):  # broken link: decode reports it
                    found.setdefault(ident, []).append((traj, f, img_dir.parent / "seg" / f.name))
    return found


def spacesense_source(cfg: dict, proto: dict, where: Path) -> DatasetSpec:
    root = _root(cfg)
    found = scan_spacesense(root)
    if not found:
        raise InputError(f"{root}: no SpaceSense-Bench <Satellite>/.../<trajectory>/image/*.png files found")
    return _disjoint_source("spacesense", found, cfg, proto, where, root, "trajectory",
                            int(proto.get("mask_threshold", 0)))


SPARK_COLUMNS = ("Class", "Image name", "Mask name")


def _read_spark_csv(path: Path) -> list[dict]:
    """Read the rows of a SPARK list (columns :data:`SPARK_COLUMNS`, others ignored)."""
    try:
        with path.open(newline="", encoding="utf-8-sig") as f:
            reader = csv.DictReader(f)
            fields = [c.strip() for c in reader.fieldnames or []]
            missing = [c for c in SPARK_COLUMNS if c not in fields]
            if missing:
                raise InputError(f"{path}: SPARK list lacks column(s) {missing} (has {fields})")
            rows = []
            for line, raw in enumerate(reader, start=2):
                r = {(k or "").strip(): (v or "").strip() for k, v in raw.items()}
                if not all(r.get(c) for c in SPARK_COLUMNS):
                    raise InputError(f"{path}: line {line} has an empty cell in {' / '.join(SPARK_COLUMNS)}")
                rows.append(r)
            return rows
    except OSError as e:
        raise InputError(f"{path}: cannot read SPARK list ({e.strerror or e})") from None
    except (csv.Error, UnicodeDecodeError) as e:
        raise InputError(f"{path}: not a readable CSV ({e})") from None


def scan_spark(root: Path, lists: dict[str, str], where: Path) -> dict[str, list[tuple[str, Path, Path]]]:
    """{class: [(official split, image path, mask path), ...]} from the lists (split -> CSV name) that exist."""
    found: dict[str, list] = {}
    present = {str(split): root / str(name) for split, name in lists.items() if (root / str(name)).is_file()}
    if not present:
        raise InputError(f"{root}: none of the SPARK lists {sorted(lists.values())} found (see {where})")
    for split, path in present.items():
        for r in _read_spark_csv(path):
            cls = r["Class"]
            found.setdefault(cls, []).append((split, root / "images" / cls / split / r["Image name"],
                                              root / "mask" / cls / split / r["Mask name"]))
    return found


def spark_source(cfg: dict, proto: dict, where: Path) -> DatasetSpec:
    """SPARK 2024 stream 1: the classes are the spacecraft, re-split spacecraft-disjoint."""
    root = _root(cfg)
    found = scan_spark(root, dict(_get(proto, "lists", where, dict)), where)
    return _disjoint_source("spark", found, cfg, proto, where, root, "spark_split",
                            int(_get(proto, "mask_threshold", where, int)))


def _read_list(path: Path) -> list[str]:
    """File names from a JSON list (of names or of ``{filename: ...}``) or a text file (one per line)."""
    try:
        text = path.read_text()
    except OSError as e:
        raise InputError(f"{path}: cannot read list ({e.strerror or e})") from None
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            raise InputError(f"{path}: invalid JSON ({e.msg} at line {e.lineno})") from None
        if not isinstance(data, list):
            raise InputError(f"{path}: expected a JSON list of image entries")
        names = [item.get("filename") if isinstance(item, dict) else item for item in data]
        bad = next((k for k, name in enumerate(names) if not isinstance(name, str) or not name), None)
        if bad is not None:
            raise InputError(f"{path}: entry {bad} has no 'filename'")
        return names
    return [ln.strip() for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]


def _find_mask(mask_dir: Path, name: str, suffixes=(".png",)) -> Path | None:
    candidates = [mask_dir / name] + [mask_dir / (Path(name).stem + s) for s in suffixes]
    # a broken link is returned: the decode pass reports it
    return next((p for p in candidates if p.is_file() or p.is_symlink()), None)


def _split_pool(names: list[str], masks: dict[str, Path | None], n_train: int, n_val: int | None,
                n_test: int | None, seed: int, key: str) -> list[tuple[str, str]]:
    """Seeded shuffle -> first n_train unlabeled train, then disjoint val/test from the masked rest."""
    order = _rng(seed, key).permutation(len(names))
    shuffled = [names[i] for i in order]
    train = shuffled[:n_train]
    masked_rest = [n for n in shuffled[n_train:] if masks.get(n) is not None]
    val = masked_rest[:n_val] if n_val is not None else masked_rest
    rest = masked_rest[len(val):]
    test = rest[:n_test] if n_test is not None else rest
    return [(n, "train") for n in train] + [(n, "val") for n in val] + [(n, "test") for n in test]


def speedplus_source(cfg: dict, proto: dict, where: Path) -> DatasetSpec:
    root = _root(cfg)
    domain = cfg["domain"] or proto.get("domain")
    domains = _get(proto, "domains", where, list)
    if domain not in domains:
        raise InputError(f"params: data.domain={domain!r} must be one of {domains} for SPEED+")
    ddir = root / domain
    lists = [ddir / f for f in _get(proto, "lists", where, list) if (ddir / f).is_file()]
    if not lists:
        raise InputError(f"{ddir}: none of the SPEED+ lists {proto['lists']} found")
    names = list(dict.fromkeys(n for lst in lists for n in _read_list(lst)))
    mask_dir = ddir / "masks"
    masks = {n: _find_mask(mask_dir, n) for n in names}
    if not any(masks.values()):
        raise InputError(f"{mask_dir}: no masks found for {domain} (validation and test need masks)")
    sc = str(proto.get("spacecraft", "Tango"))
    pool = _split_pool(names, masks, int(_get(proto, "train_images", where, int)), proto.get("val_images"),
                       proto.get("test_images"), int(cfg["seed"]), f"speedplus-{domain}")
    rows = [row(f"{domain}__{Path(n).stem}", "speedplus", domain, split, domain if split == "test" else split, sc,
                 ddir / "images" / n, masks[n] if split != "train" else None) for n, split in pool]
    return DatasetSpec(rows=_frame(rows), mask_threshold=float(proto.get("mask_threshold", 128)),
                       spacecraft_disjoint=False, protocol={"name": "speedplus", "file": str(where), "domain": domain,
                                 "lists": [str(p) for p in lists]})


def tango_source(cfg: dict, proto: dict, where: Path) -> DatasetSpec:
    root = _root(cfg)
    img_dir = root / _get(proto, "images_dir", where, str)
    mask_dir = root / _get(proto, "masks_dir", where, str)
    suffix = str(proto.get("mask_suffix", ".png"))
    lists = {}
    for key in ("train_list", "test_list"):
        p = root / _get(proto, key, where, str)
        if not p.is_file():
            raise InputError(f"{p}: TANGO {key.replace('_', ' ')} not found (see {where})")
        lists[key] = _read_list(p)
    overlap = set(lists["train_list"]) & set(lists["test_list"])
    if overlap:
        raise InputError(f"{where}: {len(overlap)} images in both the official training and test lists "
                         f"(e.g. {sorted(overlap)[0]})")

    def mask_of(n):
        return _find_mask(mask_dir, Path(n).stem + suffix, (suffix,))

    train_names = lists["train_list"]
    masks = {n: mask_of(n) for n in train_names}
    sc = str(proto.get("spacecraft", "TANGO"))
    pool = _split_pool(train_names, masks, int(_get(proto, "train_images", where, int)),
                       int(_get(proto, "val_images", where, int)), 0, int(cfg["seed"]), "tango")
    # the official test set is used unchanged: a missing mask is bad input, not a reason to drop
    pool += [(n, "test") for n in lists["test_list"]]
    rows = [row(f"tango__{Path(n).stem}", "tango", "tango", split, split, sc, img_dir / n,
                 None if split == "train" else masks[n] if split == "val" else
                 mask_of(n) or mask_dir / (Path(n).stem + suffix))
            for n, split in pool]
    return DatasetSpec(rows=_frame(rows), mask_threshold=float(proto.get("mask_threshold", 127)),
                       spacecraft_disjoint=False, protocol={"name": "tango", "file": str(where)})


def _folder_entries(d: Path, policy: BadInputPolicy) -> list[tuple[str, Path]]:
    """List ``(id, path)`` of the image files under ``d`` (:func:`pipeline.datasets.scan.scan_inputs`).

    The id is the posix path relative to ``d`` without its suffix.  Bad entries go through the policy.
    """
    found = scan_inputs(d, keep_broken_links=True)
    policy.report_scan(found)
    return [(relative_id(d, p), p) for p in found.files]


def folder_source(cfg: dict, proto: dict, where: Path, policy: BadInputPolicy | None = None) -> DatasetSpec:
    policy = policy or BadInputPolicy(False)  # what it lists travels in the spec
    root = _root(cfg)
    img_dir = root / str(proto.get("images_dir", "images"))
    masks_name = proto.get("masks_dir", "masks")  # null: no masks at all (distill without --val-masks)
    mask_dir = root / str(masks_name) if masks_name is not None else None
    if not img_dir.is_dir():
        raise InputError(f"{img_dir}: images folder not found")
    entries = _folder_entries(img_dir, policy)
    image_ids = {i for i, _ in entries}
    by_stem: dict[str, list[Path]] = {}
    if mask_dir is not None and mask_dir.is_dir():
        for stem, m in _folder_entries(mask_dir, policy):
            by_stem.setdefault(stem, []).append(m)
    masks: dict[str, Path] = {}
    ambiguous: dict[str, int] = {}
    for stem, ms in by_stem.items():
        if len(ms) > 1:
            ambiguous[stem] = len(ms)
            for m in ms:
                others = ", ".join(o.name for o in ms if o != m)
                policy.report(stem, m, f"{len(ms)} mask files for stem {stem!r} (also {others}): "
                                       f"ambiguous, none is used")
        elif stem not in image_ids:
            policy.report(stem, ms[0], f"mask without an image: no file with stem {stem!r} in {img_dir}")
        else:
            masks[stem] = ms[0]
    for iid, p in entries:
        if iid in ambiguous:
            policy.report(iid, p, f"left out: its mask is ambiguous ({ambiguous[iid]} mask "
                                  f"files for stem {iid!r} in {mask_dir})")
    entries = [(iid, p) for iid, p in entries if iid not in ambiguous]
    sc = str(proto.get("spacecraft") or root.resolve().name)
    val_fraction = float(proto.get("val_fraction", 0.5))
    if not 0 <= val_fraction <= 1:
        raise InputError(f"{where}: val_fraction={val_fraction} must be in [0, 1]")
    labeled = [iid for iid, _ in entries if iid in masks]
    order = _rng(int(cfg["seed"]), "folder-val").permutation(len(labeled))
    val = {labeled[i] for i in order[:int(round(val_fraction * len(labeled)))]}
    splits = {iid: "train" if iid not in masks else "val" if iid in val else "test" for iid, _ in entries}
    rows = [row(iid, "folder", str(proto.get("domain", "folder")), splits[iid], splits[iid], sc, p, masks.get(iid))
            for iid, p in entries]
    if not rows:
        raise InputError(f"{img_dir}: no files")
    return DatasetSpec(rows=_frame(rows), mask_threshold=proto.get("mask_threshold"), spacecraft_disjoint=False,
                       protocol={"name": "folder", "file": str(where)}, skipped=policy.skipped)


ADAPTERS = {"spacesense": spacesense_source, "spark": spark_source, "speedplus": speedplus_source,
            "tango": tango_source, "folder": folder_source}
SCANNING_ADAPTERS = {"folder"}   # adapters that report unused files themselves (take the policy)


def build_source(cfg: dict) -> DatasetSpec:
    """List the rows of the real dataset named by ``data.source`` under ``data.root``, by its protocol file.

    Parameters
    ----------
    cfg : dict
        The validated ``data:`` section (``source``, ``root``, ``protocol``, ``seed``, ``domain``; ``skip_bad``: a
        scanning source, ``folder``, lists unusable entries in :attr:`DatasetSpec.skipped`, else refuses them).

    Returns
    -------
    DatasetSpec
        The rows, the protocol's reading rules (mask threshold, part colours) and what it records.

    Raises
    ------
    InputError
        A missing root, protocol file or list, a protocol key of the wrong type, or an impossible split
        (raised by the source's reader, naming the file).
    """
    source = cfg["source"]
    proto, where = load_protocol(source, cfg.get("protocol"))
    # a scanning source refuses at once, or lists what it leaves out in DatasetSpec.skipped
    scanning = (BadInputPolicy(bool(cfg.get("skip_bad"))),) if source in SCANNING_ADAPTERS else ()
    return ADAPTERS[source](cfg, proto, where, *scanning)
