"""params.yaml: every knob, grouped per stage, with a profile switch.

Layout::

    profile: demo                # or: paper
    prepare: {...}               # base values (the paper's, unless stated)
    ...
    profiles:
      demo:  {prepare: {...}}    # overrides applied when profile == demo
      paper: {...}

``load_params`` returns the *effective* params: the base sections deep-merged with
``profiles[profile]`` and then with ``--set key.path=value`` overrides.  A stage reads only its own
sections and passes exactly those (canonicalised) to the artifact fingerprint.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any, Iterable, Mapping

import yaml

from pipeline.errors import InputError

DEFAULT_PARAMS = "params.yaml"


def deep_merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict:
    out = copy.deepcopy(dict(base))
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def parse_override(item: str) -> tuple[list[str], Any]:
    """``"train.epochs=3"`` -> (["train", "epochs"], 3); the value is parsed as YAML."""
    if "=" not in item:
        raise InputError(f"--set {item!r}: expected key.path=value")
    key, _, raw = item.partition("=")
    key = key.strip()
    if not key:
        raise InputError(f"--set {item!r}: empty key")
    try:
        value = yaml.safe_load(raw)
    except yaml.YAMLError:
        raise InputError(f"--set {item!r}: value is not valid YAML") from None
    return key.split("."), value


def set_path(d: dict, keys: list[str], value: Any) -> None:
    cur = d
    for k in keys[:-1]:
        nxt = cur.get(k)
        if not isinstance(nxt, dict):
            nxt = cur[k] = {}
        cur = nxt
    cur[keys[-1]] = value


def read_yaml_mapping(path: str | Path, what: str = "params file") -> dict:
    """A YAML file whose top level is a mapping (params, protocol files); InputError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: {what} not found")
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as e:
        raise InputError(f"{path}: invalid YAML ({str(e).splitlines()[0]})") from None
    if not isinstance(raw, dict):
        raise InputError(f"{path}: {what} must be a mapping at the top level")
    return raw


def load_params(path: str | Path = DEFAULT_PARAMS, overrides: Iterable[str] = ()) -> dict:
    """Effective params: base sections + the active profile's overrides + ``--set`` overrides.

    ``--set profile=paper`` switches the profile before the profile overrides are applied.
    """
    raw = read_yaml_mapping(path)
    parsed = [parse_override(o) for o in overrides]
    for keys, value in parsed:
        if keys == ["profile"]:
            raw["profile"] = value
    profiles = raw.pop("profiles", {}) or {}
    profile = raw.get("profile", "demo")
    if profiles and profile not in profiles:
        raise InputError(f"{path}: profile {profile!r} is not one of {sorted(profiles)}")
    eff = deep_merge(raw, profiles.get(profile, {}) or {})
    for keys, value in parsed:
        if keys != ["profile"]:
            set_path(eff, keys, value)
    return eff


def section(params: Mapping[str, Any], name: str) -> dict:
    """One stage's section of the effective params (a copy); InputError if absent."""
    if name not in params or not isinstance(params[name], Mapping):
        raise InputError(f"params: section {name!r} missing")
    return copy.deepcopy(dict(params[name]))


def require(cfg: Mapping[str, Any], key: str, where: str, *, kind: type | tuple = object,
            lo: float | None = None, hi: float | None = None) -> Any:
    """Fetch ``cfg[key]`` and check its type and range; InputError names ``where.key``."""
    if key not in cfg:
        raise InputError(f"params: {where}.{key} missing")
    v = cfg[key]
    if kind is not object and not isinstance(v, kind) or (isinstance(v, bool) and kind in (int, float, (int, float))):
        raise InputError(f"params: {where}.{key}={v!r} has the wrong type")
    if lo is not None and v < lo or hi is not None and v > hi:
        raise InputError(f"params: {where}.{key}={v!r} out of range [{lo}, {hi}]")
    return v
