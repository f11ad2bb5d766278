"""Error types, and the user parameters their messages name.

:class:`InputError` is the one type for user mistakes: one line, exit code 2 from a command, naming each
parameter in the caller's terms (a flag on the command line, a keyword in Python: docs/own-data.md, section 3a);
anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import re
from typing import Any, Iterator

__all__ = ["CLI", "API", "Option", "INPUT", "OUT", "CHECKPOINT", "BACKEND", "IMPORTED_DIR", "REFERENCE_MASKS",
           "VAL_MASKS", "FORMAT", "SKIP_BAD", "OVERWRITE", "MAX_PIXELS", "LABELS", "BIT_DEPTH", "SET", "OPTIONS",
           "caller", "calling", "literal", "InputError", "ArtifactError", "TrainingDiverged"]

#: the two callers a message is rendered for: a command's flags, or the Python API's keywords
CLI, API = "command line", "python"


@dataclasses.dataclass(frozen=True)
class Option:
    """A user parameter as each caller spells it.

    ``OPTION(value)`` binds a value; a ``many`` option takes a list, one item per flag.

    Attributes
    ----------
    flag : str
        Its command-line spelling: ``--max-pixels``, or ``INPUT`` for an argument.
    keyword : str
        Its Python API spelling: ``max_pixels``.
    is_flag : bool
        A boolean flag (``--skip-bad``): spelled without a value.
    many : bool
        Repeatable: the bound value is a list, spelled as one flag per item.
    value : Any
        The bound value (not part of equality).
    bound : bool
        Whether a value is bound (not part of equality).
    """

    flag: str
    keyword: str
    is_flag: bool = False
    many: bool = False
    value: Any = dataclasses.field(default=None, compare=False)
    bound: bool = dataclasses.field(default=False, compare=False)

    def __call__(self, value: Any) -> "Option":
        """Bind ``value`` to a copy of this option.

        Parameters
        ----------
        value : Any
            The value the user gave (a list for a ``many`` option).

        Returns
        -------
        Option
            The same option, bound to ``value``.
        """
        return dataclasses.replace(self, value=value, bound=True)

    def spell(self, caller: str) -> str:
        """Spell the option for ``caller``.

        ``--max-pixels 5`` / ``max_pixels=5``; unbound, ``--max-pixels`` / ``max_pixels=``.

        Parameters
        ----------
        caller : str
            :data:`CLI` or :data:`API`.

        Returns
        -------
        str
            The option (and its value when bound) as that caller writes it.
        """
        if caller == CLI:
            if self.many and self.bound:
                return " ".join(f"{self.flag} {v}" for v in self.value)
            return self.flag if self.is_flag or not self.bound else f"{self.flag} {self.value}"
        if self.many and self.bound:
            return f"{self.keyword}={[str(v) for v in self.value]!r}"
        if self.is_flag:
            return f"{self.keyword}=True"
        if not self.bound:
            return f"{self.keyword}="
        v = self.value
        return f"{self.keyword}={str(v)!r}" if not isinstance(v, (bool, int, float)) else f"{self.keyword}={v!r}"


#: the options the library's errors name; the click options and the API's keywords take their names from here
INPUT = Option("INPUT", "input")
OUT = Option("--out", "out")
CHECKPOINT = Option("--checkpoint", "checkpoint")
BACKEND = Option("--backend", "backend")
IMPORTED_DIR = Option("--imported-dir", "imported_dir")
REFERENCE_MASKS = Option("--reference-masks", "reference_masks")
VAL_MASKS = Option("--val-masks", "val_masks")
FORMAT = Option("--format", "formats")
SKIP_BAD = Option("--skip-bad", "skip_bad", is_flag=True)
OVERWRITE = Option("--overwrite", "overwrite", is_flag=True)
MAX_PIXELS = Option("--max-pixels", "max_pixels")
LABELS = Option("--labels", "labels")
BIT_DEPTH = Option("--bit-depth", "bit_depth")
SET = Option("--set", "overrides", many=True)
OPTIONS = (INPUT, OUT, CHECKPOINT, BACKEND, IMPORTED_DIR, REFERENCE_MASKS, VAL_MASKS, FORMAT, SKIP_BAD, OVERWRITE,
           MAX_PIXELS, LABELS, BIT_DEPTH, SET)

_CALLER: contextvars.ContextVar[str] = contextvars.ContextVar("geodistill_caller", default=API)


def caller() -> str:
    """Tell who reads the library's messages now.

    Returns
    -------
    str
        :data:`CLI` inside :func:`calling`, else :data:`API`.
    """
    return _CALLER.get()


@contextlib.contextmanager
def calling(who: str) -> Iterator[None]:
    """Render messages for ``who`` inside the block.

    Parameters
    ----------
    who : str
        :data:`CLI` or :data:`API`.

    Yields
    ------
    None
        Control, with :func:`caller` returning ``who`` until the block ends.
    """
    token = _CALLER.set(who)
    try:
        yield
    finally:
        _CALLER.reset(token)


def literal(text: Any) -> str:
    """Quote ``text`` as a literal part of an :class:`InputError` template.

    Parameters
    ----------
    text : Any
        The text (its ``str``).

    Returns
    -------
    str
        ``text`` with its braces doubled, so that ``str.format`` leaves it as written.
    """
    return str(text).replace("{", "{{").replace("}", "}}")


class InputError(ValueError):
    """Bad input from the user: one line naming the file or parameter.

    ``InputError(template, *options)``: each ``{}`` is an :class:`Option`, spelled for the caller by
    :meth:`render`; with options, literal text goes through :func:`literal`.

    Parameters
    ----------
    message : str
        The message, or with ``options`` its template (one ``{}`` per option).
    *options : Option
        The parameters the message names, in template order.
    """

    def __init__(self, message: str = "", *options: Option):
        super().__init__(message, *options)
        self.template = message
        self.options = tuple(options)

    def render(self, caller: str = API) -> str:
        """Render the message for ``caller``.

        Parameters
        ----------
        caller : str
            :data:`CLI` or :data:`API`.

        Returns
        -------
        str
            The template with each option spelled as ``caller`` writes it.
        """
        if not self.options:
            return self.template
        return self.template.format(*(o.spell(caller) for o in self.options))

    def __str__(self) -> str:
        """Render the message for the Python API (a command renders it with :meth:`render`)."""
        return self.render(API)

    @classmethod
    def from_line(cls, line: str, known: tuple[Option, ...] = OPTIONS) -> "InputError":
        """Rebuild an error from a command's rendered line (a stage run in a subprocess), its flags options again.

        Parameters
        ----------
        line : str
            The one line the command printed.
        known : tuple of Option
            The options whose flags are recognised in ``line``.

        Returns
        -------
        InputError
            An error whose template holds the flags of ``line`` as options, so that it renders for either caller.
        """
        by_flag = {o.flag: o for o in known if o.flag.startswith("--")}
        if not by_flag:
            return cls(line)
        pattern = re.compile(r"(?<![\w-])(" + "|".join(map(re.escape, by_flag)) + r")(?![\w-])"
                             r"(?: ([A-Za-z_][\w.]*=(?:[^\s`'\"]*[^\s`'\",;:.)])?))?")  # item: no end punctuation
        parts, options, pos = [], [], 0
        for m in pattern.finditer(line):
            option, item = by_flag[m.group(1)], m.group(2)
            end = m.end() if option.many and item is not None else m.end(1)
            parts.append(literal(line[pos:m.start()]) + "{}")
            options.append(option([item]) if option.many and item is not None else option)
            pos = end
        if not options:
            return cls(line)
        return cls("".join(parts) + literal(line[pos:]), *options)


class ArtifactError(InputError):
    """An artifact is missing, incomplete, corrupt or of the wrong schema (message names the path)."""


class TrainingDiverged(RuntimeError):
    """A loss became NaN/Inf; the run stops before writing a broken checkpoint."""
