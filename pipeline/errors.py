"""Error types shared by the library and the stage commands.

`InputError` is the one type for *user* mistakes (a missing file, a bad parameter, a corrupt or
mismatched artifact).  Stage commands turn it into a one-line message and exit code 2; anything
else is a bug and keeps its traceback.
"""

from __future__ import annotations


class InputError(ValueError):
    """Bad input from the user: the message is one line and names the file or parameter."""


class ArtifactError(InputError):
    """An artifact is missing, incomplete, corrupt or of the wrong schema (message names the path)."""


class TrainingDiverged(RuntimeError):
    """A loss became NaN/Inf; the run stops before writing a broken checkpoint."""
