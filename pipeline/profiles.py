"""Profiles: named overrides of the schema defaults (docs/pipeline.md).

Only the commands that switch profile read them (``profile``, ``label``, ``distill``, the notebook API), so
editing one marks no DVC stage stale.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable

from pipeline.runtime.errors import InputError
from pipeline.methods import methods_with_role
from pipeline.params import PAPER, PROFILE_KEY, deep_merge, load_params, parse_override, unresolved

__all__ = ["SEEDS", "FIVE_SEEDS", "TEN_SEEDS", "ABLATION_SEED", "MAIN_METHODS", "ABLATIONS", "CONTROLS",
           "full_protocol", "STRONG_STUDY_METHODS", "FULL_PROTOCOL", "PUBLISHED_THREADS", "DEMO_THREADS",
           "DISTILL_BENCHMARK", "PROFILES", "profile_params", "load_profile", "load_params_or_profile"]

SEEDS = [42, 3407, 2026]
FIVE_SEEDS = SEEDS + [7, 11]
TEN_SEEDS = FIVE_SEEDS + [0, 1, 2, 3, 4]
ABLATION_SEED = 42
MAIN_METHODS = methods_with_role("main", "proposed")
ABLATIONS = methods_with_role("ablation")
CONTROLS = methods_with_role("control")


def full_protocol(seeds: list[int]) -> dict:
    """Return the paper's protocol plus the controls: the main methods and the controls at ``seeds``.

    Parameters
    ----------
    seeds : list of int
        The seeds of every main method and control; each ablation runs at :data:`ABLATION_SEED` only.

    Returns
    -------
    dict
        A ``protocol`` section: ``runs`` (method -> seeds) and ``supervised_ceiling``.
    """
    return {"runs": {**{m: list(seeds) for m in MAIN_METHODS + CONTROLS},
                     **{a: [ABLATION_SEED] for a in ABLATIONS}},
            "supervised_ceiling": True}


#: the geometry question at convergence: the two students, the budget-matched control and the ceiling
STRONG_STUDY_METHODS = ["plain", "geodistill", "continuation", "supervised_ceiling"]
FULL_PROTOCOL = full_protocol(SEEDS)
#: torch CPU threads of every profile that publishes numbers: the thread count changes the numerics
PUBLISHED_THREADS = 2
#: the demo's: its ten seeds train in one-thread processes side by side (stages.train --jobs), 1.5x the
#: throughput of one two-thread process on CI's 2 cores (docs/performance.md)
DEMO_THREADS = 1
#: the fp32 baseline and segment's default engine, briefly: no int8, which would be quantised again here
DISTILL_BENCHMARK = {"benchmark_variants": ["fp32_eager_nchw", "onnxruntime_fp32"],
                     "benchmark_warmup": 1, "benchmark_iters": 5, "benchmark_batches": [1]}

PROFILES: dict[str, dict[str, Any]] = {
    "demo": {
        "data": {"resolution": 64,
                 "synthetic": {"train_spacecraft": 6, "train_views": 12, "val_spacecraft": 3, "val_views": 8,
                               "test_spacecraft_per_group": 3, "test_views": 8}},
        "train": {"recipe": "stable", "num_threads": DEMO_THREADS, "epochs_stage1": 10, "epochs_stage2": 5},
        "protocol": {"runs": {"plain": list(TEN_SEEDS), "geodistill": list(TEN_SEEDS),
                              "continuation": list(TEN_SEEDS)}, "seeds_per_stage": len(TEN_SEEDS)},
        "evaluate": {"bootstrap_resamples": 2000},
        "report": {"qualitative_images": 3},
        "deploy": {"benchmark_iters": 10, "benchmark_batches": [1, 4], "int8_calibration_images": 32},
    },
    "reduced": {
        "data": {"resolution": 128},
        "train": {"num_threads": PUBLISHED_THREADS},
        "protocol": full_protocol(FIVE_SEEDS),
        "deploy": {"benchmark_resolution": 384},  # time at the paper's size; IoU at 128
    },
    "paper": {
        "train": {"num_threads": PUBLISHED_THREADS},
        "protocol": FULL_PROTOCOL,
    },
    "reduced-strong": {
        "data": {"resolution": 128},
        "train": {"recipe": "strong", "num_threads": PUBLISHED_THREADS},
        "protocol": {"runs": {m: list(SEEDS) for m in STRONG_STUDY_METHODS}, "supervised_ceiling": True},
        "deploy": {"benchmark_resolution": 384},
    },
    "distill": {
        "teacher": {"vflip_base_prompt": False},  # the flipped view only serves afs_control, not run here
        # the speedrun's winner, stopped at its plateau (docs/student.md), at the CPU's speed: bf16 autocast where
        # the host has bf16 units, fp32 elsewhere, and channels_last (reports/train-speed/); here, not in the
        # recipe, so that the committed progressive reports keep their fp32 numerics
        "train": {"recipe": "progressive", "precision": "auto", "channels_last": True},
        "protocol": {"runs": {"plain": [42], "geodistill": [42]}},
        "deploy": DISTILL_BENCHMARK,
    },
}


def profile_params(name: str) -> dict:
    """Return the schema defaults with the overrides of profile ``name`` merged in (not yet validated).

    Parameters
    ----------
    name : str
        A key of :data:`PROFILES`.

    Returns
    -------
    dict
        The params, ``profile`` naming ``name``; callers validate them.

    Raises
    ------
    InputError
        ``name`` is no profile.
    """
    if name not in PROFILES:
        raise InputError(f"profile {name!r}: expected one of {', '.join(PROFILES)}")
    out = deep_merge(unresolved(PAPER.model_dump(mode="python"), {}), PROFILES[name])
    out[PROFILE_KEY] = name
    return out


def load_profile(name: str, overrides: Iterable[str] = ()) -> dict:
    """Load the validated params of profile ``name`` with ``--set key.path=value`` overrides applied.

    Parameters
    ----------
    name : str
        A key of :data:`PROFILES`.
    overrides : iterable of str
        ``key.path=value`` items (:func:`pipeline.params.parse_override`).

    Returns
    -------
    dict
        The validated params (:func:`pipeline.params.load_params`).
    """
    return load_params(f"profile {name}", overrides, base=profile_params(name))


def load_params_or_profile(params_file: str | Path | None, overrides: Iterable[str], default_profile: str) -> dict:
    """Load the params of a command that switches profile.

    They are ``--set profile=NAME``'s, else ``params_file``'s, else ``default_profile``'s, with the other
    overrides applied.

    Parameters
    ----------
    params_file : str or Path or None
        A params file, read unless ``overrides`` names a profile; None: a profile.
    overrides : iterable of str
        ``key.path=value`` items; ``profile=NAME`` among them picks the profile.
    default_profile : str
        The profile without a params file or a ``profile`` override.

    Returns
    -------
    dict
        The validated params.
    """
    items = list(overrides)
    parsed = [parse_override(i) for i in items]
    named = next((value for keys, value in parsed if keys == [PROFILE_KEY]), None)
    rest = [i for i, (keys, _) in zip(items, parsed) if keys != [PROFILE_KEY]]
    if named is None and params_file is not None:
        return load_params(params_file, rest)
    return load_profile(default_profile if named is None else str(named), rest)
