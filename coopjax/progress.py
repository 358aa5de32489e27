"""A one-line progress bar on stderr for long runs (sweeps, tuning), with its rate and an ETA.

On a terminal it redraws in place; in a log it prints a line every 10 %.
"""

from __future__ import annotations

import sys
import time


class Progress:
    """A one-line progress bar on stderr with its rate and an ETA."""

    def __init__(self, total: int, enabled: bool = True, label: str = "sweep", unit: str = "samples"):
        self.total, self.done, self.enabled = total, 0, enabled
        self.label, self.unit = label, unit
        self.start = time.perf_counter()
        self.tty = sys.stderr.isatty()
        self.last_line = -1.0

    def update(self, count: int) -> None:
        self.done += count
        if not self.enabled:
            return
        elapsed = max(time.perf_counter() - self.start, 1e-9)
        rate = self.done / elapsed
        frac = self.done / self.total
        bar = "#" * int(30 * frac)
        eta = (self.total - self.done) / rate if rate > 0 else float("inf")
        line = (f"{self.label} [{bar:<30}] {self.done}/{self.total} {self.unit}, {rate:,.{0 if rate >= 10 else 2}f} "
                f"{self.unit}/s, eta {eta:,.0f} s")
        if self.tty:
            print("\r" + line, end="" if self.done < self.total else "\n", file=sys.stderr, flush=True)
        elif frac - self.last_line >= 0.1 or self.done == self.total:
            self.last_line = frac
            print(line, file=sys.stderr, flush=True)
