"""Atomic file output and the CSV format of the tables.

A reader never sees a half-written file, and a failed run leaves none. A kill -9 during the final
rename can still leave the temporary file; its name is derived from the target's, so the next
successful write of that target removes it.
"""

from __future__ import annotations

import contextlib
import csv
import glob
import os
import tempfile

import numpy as np


def _temp_prefix(path: str) -> str:
    return f".{os.path.basename(path)}.tmp-"


@contextlib.contextmanager
def atomic_path(path: str):
    """Yield a temporary path in the target's folder; rename it onto `path` only on success."""
    folder = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=_temp_prefix(path), suffix=os.path.splitext(path)[1])
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the file ordinary permissions
        os.replace(tmp, path)
        # Leftovers of this target from a killed earlier run.
        for stale in glob.glob(os.path.join(glob.escape(folder), glob.escape(_temp_prefix(path)) + "*")):
            with contextlib.suppress(OSError):
                os.unlink(stale)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _text(values) -> list[str]:
    v = np.asarray(values)
    if v.dtype.kind == "b":
        return ["1" if x else "0" for x in v.tolist()]
    if v.dtype.kind in "iu":
        return [str(x) for x in v.tolist()]
    if v.dtype.kind == "f":
        return [repr(x) for x in v.astype(np.float64).tolist()]  # shortest string that reads back exactly
    return [str(x) for x in v.tolist()]


def write_csv(path: str, columns: dict) -> None:
    """Columns of equal length, with a header row, at full precision (float64 round-trips exactly)."""
    names = list(columns)
    text = [_text(columns[n]) for n in names]
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="") as f:
            f.write(",".join(names) + "\n")
            f.writelines(",".join(row) + "\n" for row in zip(*text))


def read_csv(path: str, what: str = "table") -> dict[str, np.ndarray]:
    """A CSV with a header row: numeric columns as float64, others as strings. Problems are one
    ValueError that names the file and the line."""
    try:
        with open(path, newline="") as f:
            rows = list(csv.reader(f))
    except UnicodeDecodeError:
        raise ValueError(f"{what} {path!r} is not a text CSV file") from None
    rows = [r for r in rows if r]
    if not rows:
        raise ValueError(f"{what} {path!r} is empty")
    header = [h.strip() for h in rows[0]]
    if any(not h for h in header) or len(set(header)) != len(header):
        raise ValueError(f"{what} {path!r}: the first line must name every column once, got {','.join(header)!r}")
    for line, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise ValueError(f"{what} {path!r}, line {line}: {len(row)} values for {len(header)} columns")
    columns = {}
    for j, name in enumerate(header):
        values = [r[j].strip() for r in rows[1:]]
        try:
            columns[name] = np.array([float(x) for x in values], np.float64)
        except ValueError:
            columns[name] = np.array(values)
    return columns
