"""The ``data`` params section: validation (the schema) and its fingerprinted part."""

from __future__ import annotations

import dataclasses
from typing import Literal, Mapping

from pipeline.params import BIT_DEPTHS, PAPER, validate_section

__all__ = ["check_data_params", "fingerprint_params", "FrameSettings"]

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


@dataclasses.dataclass(frozen=True)
class FrameSettings:
    """How the reader turns a frame file into a working image: the ``data`` params of the same names.

    Read once from the validated section and handed down to the reader
    (:func:`pipeline.datasets.loading.load_rgb`) as one value.  No defaults and no bounds here: both are the
    schema's (:class:`pipeline.params.DataParams`), which every instance is checked against.

    Attributes
    ----------
    bit_depth : str or int
        ``data.bit_depth``: the bits a 16-bit frame's sensor fills (one of :data:`pipeline.params.BIT_DEPTHS`).
    letterbox : bool
        ``data.letterbox``: pad each frame (and its masks) to a square before resizing, instead of squashing it.
    max_pixels : int
        ``data.max_pixels``: a file above this many pixels, read from its header, is refused before decoding.

    Raises
    ------
    InputError
        A value the schema refuses, naming ``params: data.<key>``.
    """

    bit_depth: Literal[BIT_DEPTHS]
    letterbox: bool
    max_pixels: int

    def __post_init__(self):  # noqa: D105 -- the check the class docstring's Raises names
        validate_section("data", dataclasses.asdict(self))  # the schema's rules, the only ones

    @classmethod
    def from_params(cls, cfg: Mapping) -> FrameSettings:
        """Read the frame settings of a validated ``data`` section.

        Parameters
        ----------
        cfg : Mapping
            The validated ``data:`` section.

        Returns
        -------
        FrameSettings
            Its ``bit_depth``, ``letterbox`` and ``max_pixels``.
        """
        return cls(**{f.name: cfg[f.name] for f in dataclasses.fields(cls)})
