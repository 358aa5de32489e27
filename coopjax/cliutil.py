"""Command-line helpers shared by `coopjax` and `coopjax tune`: one home, so imports run one way
(coopjax.cli -> tuning.cli -> coopjax.cliutil).

Any mistake in the input is one line on stderr and exit code 2, with no traceback and no output file.
"""

from __future__ import annotations

import argparse
import math
import os

EXIT_BAD_INPUT = 2
EXIT_DIVERGED = 1


class BadInput(Exception):
    pass


class Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse's own mistakes: one line, exit 2
        raise BadInput(f"{message} (see `{self.prog} --help`)")


def parse_assignment(text: str) -> tuple[str, float]:
    """`NAME=VALUE` -> (NAME, float(VALUE)), with a clear message otherwise."""
    name, sep, value = text.partition("=")
    if not sep or not name or not value:
        raise BadInput(f"--set expects NAME=VALUE, got {text!r}")
    try:
        number = float(value)
    except ValueError:
        raise BadInput(f"--set {name}: {value!r} is not a number") from None
    if not math.isfinite(number):
        raise BadInput(f"--set {name}: {value!r} is not finite")
    return name.strip(), number


def check_output(path: str, what: str, extensions=None) -> None:
    """Refuse, before any work, an output whose folder is missing or whose extension is unknown."""
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise BadInput(f"{what} {path!r}: folder {folder!r} does not exist")
    if os.path.isdir(path):
        raise BadInput(f"{what} {path!r} is a folder, not a file")
    if not os.access(folder, os.W_OK):
        raise BadInput(f"{what} {path!r}: folder {folder!r} is not writable")
    if extensions and path.rsplit(".", 1)[-1].lower() not in extensions:
        raise BadInput(f"{what} {path!r}: the file name must end in one of .{', .'.join(extensions)}")
