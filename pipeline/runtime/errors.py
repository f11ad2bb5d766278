"""Error types shared by the library and the stage commands.

`InputError` is the one type for *user* mistakes (a missing file, a bad parameter, a corrupt or
mismatched artifact).  Stage commands turn it into a one-line message and exit code 2; anything
else is a bug and keeps its traceback.

The naming convention of every error (docs/own-data.md): **an error names a parameter in the caller's
terms** -- the flag on the command line (``--max-pixels``, ``--skip-bad``), the keyword argument in
the Python API (``max_pixels=``, ``skip_bad=True``).  The library does not know its caller, so an
error names a parameter through an :class:`Option`, which carries both spellings, and is rendered
where the caller is known: ``stages._common.one_line_errors`` renders :data:`CLI`, ``str(error)`` (what
a Python caller sees) renders :data:`API`.  A message that is not an error (a warning logged by the
library) is rendered for :func:`caller`: :data:`CLI` inside a command (``one_line_errors`` sets it with
:func:`calling`), :data:`API` otherwise.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import re
from typing import Any, Iterator

#: the two callers an error is rendered for (:meth:`InputError.render`)
CLI, API = "command line", "python"


@dataclasses.dataclass(frozen=True)
class Option:
    """A user parameter as each caller spells it: ``flag`` on the command line (``--max-pixels``,
    ``INPUT`` for a positional argument) and ``keyword`` in the Python API (``max_pixels``).

    ``OPTION(value)`` binds the value the caller gave: ``--out run/`` / ``out='run/'``.  A boolean
    ``is_flag`` option is spelled ``--skip-bad`` / ``skip_bad=True``.  A ``many`` option takes a list,
    one item per use of the flag: ``SET(["a=1"])`` is ``--set a=1`` / ``overrides=['a=1']``."""

    flag: str
    keyword: str
    is_flag: bool = False
    many: bool = False
    value: Any = dataclasses.field(default=None, compare=False)
    bound: bool = dataclasses.field(default=False, compare=False)

    def __call__(self, value: Any) -> "Option":
        return dataclasses.replace(self, value=value, bound=True)

    def spell(self, caller: str) -> str:
        """``--max-pixels 5`` / ``max_pixels=5``; unbound ``--max-pixels`` / ``max_pixels=``."""
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


#: the options the library's errors name (one table: the click options of stages/_common.py and the
#: keyword arguments of pipeline/api.py take their names from here)
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
#: the bits a 16-bit frame's sensor fills (params ``data.bit_depth``; label, distill, segment)
BIT_DEPTH = Option("--bit-depth", "bit_depth")
#: a params override: ``--set key=value`` on the command line, ``overrides=["key=value"]`` in Python
SET = Option("--set", "overrides", many=True)
OPTIONS = (INPUT, OUT, CHECKPOINT, BACKEND, IMPORTED_DIR, REFERENCE_MASKS, VAL_MASKS, FORMAT, SKIP_BAD, OVERWRITE,
           MAX_PIXELS, LABELS, BIT_DEPTH, SET)

_CALLER: contextvars.ContextVar[str] = contextvars.ContextVar("geodistill_caller", default=API)


def caller() -> str:
    """Who reads the library's messages now: :data:`CLI` inside :func:`calling` (a command), else :data:`API`."""
    return _CALLER.get()


@contextlib.contextmanager
def calling(who: str) -> Iterator[None]:
    """Render messages for ``who`` (:data:`CLI` or :data:`API`) inside the block."""
    token = _CALLER.set(who)
    try:
        yield
    finally:
        _CALLER.reset(token)


def literal(text: Any) -> str:
    """``text`` as a literal part of a message template (braces doubled)."""
    return str(text).replace("{", "{{").replace("}", "}}")


class InputError(ValueError):
    """Bad input from the user: the message is one line and names the file or parameter.

    ``InputError(template, *options)``: each ``{}`` of ``template`` is an :class:`Option`, spelled
    in the caller's terms by :meth:`render` -- ``InputError("{}: must be >= 1", MAX_PIXELS(0))`` reads
    ``--max-pixels 0: must be >= 1`` on the command line and ``max_pixels=0: must be >= 1`` in
    Python (``str(error)``).  Without options the message is taken as it is (no placeholders); with
    options, literal text goes through :func:`literal`.  Every new error naming a parameter the user
    sets follows this convention (docs/own-data.md)."""

    def __init__(self, message: str = "", *options: Option):
        super().__init__(message, *options)
        self.template = message
        self.options = tuple(options)

    def render(self, caller: str = API) -> str:
        """The message for ``caller`` (:data:`CLI` or :data:`API`)."""
        if not self.options:
            return self.template
        return self.template.format(*(o.spell(caller) for o in self.options))

    def __str__(self) -> str:
        return self.render(API)

    @classmethod
    def from_line(cls, line: str, known: tuple[Option, ...] = OPTIONS) -> "InputError":
        """An error from a command's rendered one line (a stage run in a subprocess): the flags of
        ``known`` it names become options again, so a Python caller reads their keywords; a ``many``
        option's ``key=value`` item after its flag (``--set teacher.score_threshold=0.1``) is bound."""
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
