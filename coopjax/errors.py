"""The one exception type for a caller's mistake.

The library raises `InputError` for anything the caller asked for that cannot be done: an unknown
name, a value out of range, an unreadable file. It is raised before any work starts, in the terms
of the Python API. Anything else that escapes is a bug and keeps its traceback.
"""

from __future__ import annotations


class InputError(ValueError):
    """A mistake in the input. `field` is the argument at fault (an API name such as "dt" or
    "K_GP_L") when there is one; the command line names its own flag for it."""

    def __init__(self, message: str, field: str | None = None):
        super().__init__(message)
        self.field = field
