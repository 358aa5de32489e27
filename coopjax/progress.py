"""The progress bars of long work (tqdm), drawn the same way everywhere.

A bar is drawn only on a terminal: in a log file its carriage-return updates would pile up into one
long line, and an interrupt's one-line message would follow the bar's last state on that line.
"""

from __future__ import annotations

import sys

from tqdm.auto import tqdm


def bar(*, total: int | None, desc: str, unit: str, enabled: bool = True, initial: int = 0) -> tqdm:
    """A tqdm bar on stderr; `enabled=False` (or a stderr that is not a terminal) draws nothing."""
    return tqdm(
        total=total,
        initial=initial,
        desc=desc,
        unit=unit,
        disable=None if enabled else True,  # None: tqdm's own rule, drawn only on a terminal
        dynamic_ncols=True,
        mininterval=0.5,
        file=sys.stderr,
    )
