"""Validation of the ``data`` params section (one-line InputError naming ``data.<key>``)."""

from __future__ import annotations

from pipeline.errors import InputError
from pipeline.params import require

SOURCES = ("synthetic", "spacesense", "speedplus", "tango", "folder")
# keys that change where things are cached, not what the stage produces: not fingerprinted
NON_CONTENT_KEYS = ("cache_dir", "contact_sheet_images")


def _range(cfg, key, where):
    v = require(cfg, key, where, kind=list)
    if len(v) != 2 or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v) \
            or not 0 < v[0] < v[1] <= 1:
        raise InputError(f"params: {where}.{key}={v!r} must be [lo, hi] with 0 < lo < hi <= 1")
    return [float(x) for x in v]


def check_data_params(cfg: dict) -> dict:
    """Type/range checks; returns the section with defaults filled in."""
    cfg = dict(cfg)
    cfg.setdefault("cache_dir", ".cache/decode")
    cfg.setdefault("skip_bad", False)
    cfg.setdefault("contact_sheet_images", 16)
    src = require(cfg, "source", "data", kind=str)
    if src not in SOURCES:
        raise InputError(f"params: data.source={src!r} is not one of {list(SOURCES)}")
    require(cfg, "resolution", "data", kind=int, lo=16, hi=4096)
    require(cfg, "seed", "data", kind=int, lo=0)
    require(cfg, "skip_bad", "data", kind=bool)
    require(cfg, "contact_sheet_images", "data", kind=int, lo=0, hi=256)
    if cfg["cache_dir"] is not None:
        require(cfg, "cache_dir", "data", kind=str)
    if src == "synthetic":
        s = require(cfg, "synthetic", "data", kind=dict)
        w = "data.synthetic"
        require(s, "train_spacecraft", w, kind=int, lo=1, hi=10000)
        require(s, "train_views", w, kind=int, lo=1, hi=100000)
        require(s, "val_spacecraft", w, kind=int, lo=0, hi=10000)
        require(s, "val_views", w, kind=int, lo=0, hi=100000)
        groups = require(s, "test_groups", w, kind=list)
        if not all(isinstance(g, str) and g and g.isidentifier() for g in groups) or len(set(groups)) != len(groups):
            raise InputError(f"params: {w}.test_groups={groups!r} must be distinct names (letters, digits, _)")
        require(s, "test_spacecraft_per_group", w, kind=int, lo=0, hi=10000)
        require(s, "test_views", w, kind=int, lo=0, hi=100000)
        for key in ("tiny_probability", "hard_case_probability"):
            if key in s:
                require(s, key, w, kind=(int, float), lo=0, hi=1)
        for key in ("tiny_range", "regular_range"):
            if key in s:
                _range(s, key, w)
        if "background_weights" in s:
            bw = require(s, "background_weights", w, kind=list)
            if len(bw) != 3 or any(not isinstance(x, (int, float)) or x < 0 for x in bw) or sum(bw) <= 0:
                raise InputError(f"params: {w}.background_weights={bw!r} must be 3 non-negative weights (stars, earth, lab)")
    else:
        if not cfg.get("root"):
            raise InputError(f"params: data.root is required for data.source={src!r}")
        require(cfg, "root", "data", kind=str)
        if cfg.get("protocol") is not None:
            require(cfg, "protocol", "data", kind=str)
    return cfg


def fingerprint_params(cfg: dict) -> dict:
    """The part of ``data`` that determines the prepared content (synthetic knobs only for synthetic)."""
    out = {k: v for k, v in cfg.items() if k not in NON_CONTENT_KEYS}
    if cfg.get("source") != "synthetic":
        out.pop("synthetic", None)
    return out
