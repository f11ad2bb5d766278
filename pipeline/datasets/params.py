"""The ``data`` params section: validation (the schema) and its fingerprinted part."""

from __future__ import annotations

from pipeline.params import PAPER, validate_section

__all__ = ["check_data_params", "fingerprint_params"]

# not fingerprinted: where things are cached, and a guard whose effect shows in the content digest
NON_CONTENT_KEYS = ("cache_dir", "contact_sheet_images", "max_pixels")


def check_data_params(cfg: dict) -> dict:
    """Validate the ``data`` section against the params schema (:mod:`pipeline.params`), defaults filled in.

    Parameters
    ----------
    cfg : dict
        The ``data:`` section as written.

    Returns
    -------
    dict
        The validated section.
    """
    return validate_section("data", cfg)


def fingerprint_params(cfg: dict) -> dict:
    """Select the part of ``data`` that determines the prepared content (synthetic knobs only for synthetic).

    Keys added after artifacts were first published (``bit_depth``, ``letterbox``) enter only when they differ
    from their schema default, so that older artifacts keep their fingerprints.

    Parameters
    ----------
    cfg : dict
        The validated ``data:`` section.

    Returns
    -------
    dict
        The fingerprinted subset of ``cfg``.
    """
    out = {k: v for k, v in cfg.items() if k not in NON_CONTENT_KEYS}
    for key, default in (("bit_depth", PAPER.data.bit_depth), ("letterbox", PAPER.data.letterbox)):  # keys added later: in it when set
        if out.get(key, default) == default:
            out.pop(key, None)
    if cfg.get("source") != "synthetic":
        out.pop("synthetic", None)
    return out
