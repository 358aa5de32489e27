"""Files: atomic outputs, and the sweep and parameter tables (CSV or Parquet, through pandas).

A reader never sees a half-written file, and a failed run leaves none: every output is written to a
temporary file beside its target and renamed into place only when the whole command succeeded
(`Outputs`). A kill -9 during the final rename can still leave a temporary file; its name is derived
from the target's, so the next successful write of that target removes it.

The temporary files in flight are registered, so that an interrupt (`coopjax.cli.interrupts`) can
remove them before the process exits.
"""

from __future__ import annotations

import contextlib
import csv
import glob
import json
import os
import sys
import tempfile
import threading

import numpy as np

from coopjax.errors import InputError

LOCK = threading.RLock()  # held while temporary files are created, renamed or removed
IN_FLIGHT: set[str] = set()  # temporary files not yet renamed into place
WRITTEN: list[str] = []  # targets renamed into place by this process, in order


def _temp_prefix(path: str) -> str:
    return f".{os.path.basename(path)}.tmp-"


def _remove_stale(path: str) -> None:
    folder = os.path.dirname(os.path.abspath(path))
    for stale in glob.glob(os.path.join(glob.escape(folder), glob.escape(_temp_prefix(path)) + "*")):
        with contextlib.suppress(OSError):
            os.unlink(stale)


def _new_temp(path: str) -> str:
    folder = os.path.dirname(os.path.abspath(path))
    with LOCK:
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=_temp_prefix(path), suffix=os.path.splitext(path)[1])
        os.close(fd)
        IN_FLIGHT.add(tmp)
    return tmp


def _discard(tmp: str) -> None:
    with LOCK:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        IN_FLIGHT.discard(tmp)


def _commit(tmp: str, path: str) -> None:
    umask = os.umask(0)
    os.umask(umask)
    with LOCK:
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the file ordinary permissions
        os.replace(tmp, path)
        IN_FLIGHT.discard(tmp)
        WRITTEN.append(path)
    _remove_stale(path)  # leftovers of this target from a killed earlier run


@contextlib.contextmanager
def atomic_path(path: str):
    """Yield a temporary path in the target's folder; rename it onto `path` only on success."""
    tmp = _new_temp(path)
    try:
        yield tmp
        _commit(tmp, path)
    finally:
        if tmp in IN_FLIGHT:
            _discard(tmp)


class Outputs:
    """Several output files committed together: each is written to its temporary path, and all are
    renamed into place at the end, only if everything succeeded (nothing of a failed run is left).

        with Outputs() as out:
            write_table(out.path("run.csv"), ...)
            plot(..., out.path("fig.png"))
    """

    def __init__(self):
        self.pending: list[tuple[str, str]] = []

    def path(self, target: str) -> str:
        tmp = _new_temp(target)
        self.pending.append((tmp, target))
        return tmp

    def __enter__(self):
        return self

    def __exit__(self, kind, error, tb):
        if kind is None:
            for tmp, target in self.pending:
                _commit(tmp, target)
        for tmp, _ in self.pending:
            if tmp in IN_FLIGHT:
                _discard(tmp)
        return False


# ----------------------------------------------------------------------------------------------
# Tables


def is_parquet(path: str) -> bool:
    return path.lower().endswith(".parquet")


def write_table(path: str, columns: dict) -> None:
    """CSV at full precision (the shortest repr that reads back exactly; booleans as 0/1) or Parquet
    (needs pyarrow), through pandas, atomically."""
    import pandas as pd  # on first use: it takes a second to import, and most commands read no table

    frame = pd.DataFrame({k: np.asarray(v) for k, v in columns.items()})
    with atomic_path(path) as tmp:
        if is_parquet(path):
            frame.to_parquet(tmp, index=False)
        else:
            for name in frame.columns:
                if frame[name].dtype == bool:
                    frame[name] = frame[name].astype(np.int8)
                elif frame[name].dtype == np.float32:  # a float32 value at float64's repr, as a float64 column
                    frame[name] = frame[name].astype(np.float64)
            frame.to_csv(tmp, index=False)


def _check_csv_shape(path: str, what: str) -> None:
    """pandas fills a short row with missing values silently: refuse one, naming its line."""
    csv.field_size_limit(sys.maxsize)
    with open(path, newline="", encoding="utf-8-sig") as f:
        reader = csv.reader(f)
        header = next(reader, None)
        if header is None or not any(h.strip() for h in header):
            raise InputError(f"{what} {path!r} is empty")
        names = [h.strip() for h in header]
        if any(not h for h in names) or len(set(names)) != len(names):
            raise InputError(f"{what} {path!r}: the first line must name every column once, got {','.join(names)!r}")
        for row in reader:
            if row and len(row) != len(names):
                raise InputError(f"{what} {path!r}, line {reader.line_num}: {len(row)} values for {len(names)} columns")


def read_table(path: str, what: str = "table") -> dict[str, np.ndarray]:
    """A sweep or parameter table: numeric columns as float64, others as strings. Any problem with
    the file is one InputError that names it (and the line, for a malformed CSV)."""
    import pandas as pd  # on first use (above)

    if os.path.isdir(path):
        raise InputError(f"{what} {path!r} is a folder, not a file")
    if not os.path.exists(path):
        raise InputError(f"{what} {path!r}: no such file")
    if not os.access(path, os.R_OK):
        raise InputError(f"{what} {path!r} is not readable (permission denied)")
    if os.path.getsize(path) == 0:
        raise InputError(f"{what} {path!r} is empty")
    try:
        if is_parquet(path):
            try:
                frame = pd.read_parquet(path)
            except ImportError:
                raise InputError("reading Parquet needs pyarrow: pip install 'coopjax[sweep]'") from None
            except Exception as error:  # pyarrow raises several types for a damaged file
                raise InputError(f"{what} {path!r} is not a readable Parquet file ({type(error).__name__})") from None
        else:
            _check_csv_shape(path, what)
            frame = pd.read_csv(path, dtype=str, keep_default_na=False, encoding="utf-8-sig", skipinitialspace=True)
            frame.columns = [c.strip() for c in frame.columns]
    except UnicodeDecodeError:
        raise InputError(f"{what} {path!r} is not a text CSV file") from None
    except PermissionError:
        raise InputError(f"{what} {path!r} is not readable (permission denied)") from None
    except pd.errors.ParserError as error:
        raise InputError(f"{what} {path!r} is not a readable CSV file ({str(error).splitlines()[0]})") from None
    if frame.shape[0] == 0 or frame.shape[1] == 0:
        raise InputError(f"{what} {path!r} has no rows")
    return {str(name): _column(frame[name]) for name in frame.columns}


def _column(series) -> np.ndarray:
    """float64 where every value is a number (empty and 'nan' are NaN), else strings."""
    import pandas as pd  # on first use (above)

    if series.dtype.kind in "biuf":
        return series.to_numpy(np.float64)
    text = series.astype(str).str.strip()
    numbers = pd.to_numeric(text.where(text != "", "nan"), errors="coerce")
    unparsed = numbers.isna() & ~text.str.lower().isin(["", "nan"])
    if unparsed.any():
        return text.to_numpy(str)
    return numbers.to_numpy(np.float64)


# ----------------------------------------------------------------------------------------------
# JSON


def json_safe(obj, where: str = "") -> tuple[object, list[str]]:
    """`obj` with every non-finite number replaced by None (standard JSON has no NaN or Infinity),
    and the paths of what was replaced."""
    nulls: list[str] = []

    def walk(x, at):
        if isinstance(x, dict):
            return {k: walk(v, f"{at}.{k}" if at else str(k)) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [walk(v, f"{at}[{i}]") for i, v in enumerate(x)]
        if isinstance(x, np.ndarray):
            return walk(x.tolist(), at)
        if isinstance(x, (np.bool_, bool)):
            return bool(x)
        if isinstance(x, (np.integer,)):
            return int(x)
        if isinstance(x, (float, np.floating)):
            if not np.isfinite(x):
                nulls.append(at)
                return None
            return float(x)
        return x

    return walk(obj, where), nulls


def write_json(path: str, data) -> list[str]:
    """Standard JSON, atomically; a number that is not finite is written as null. Returns where."""
    safe, nulls = json_safe(data)
    with atomic_path(path) as tmp:
        with open(tmp, "w") as f:
            json.dump(safe, f, indent=1, allow_nan=False)
    return nulls


@contextlib.contextmanager
def one_run(path: str, what: str):
    """Hold the output `path` for this process: a second run on it is refused with one line while
    this one lives. The lock is the OS's (`flock` on `.NAME.lock` beside it), so a run killed even
    with -9 leaves no stale lock (its empty file is taken over by the next run); the lock file is
    removed when the run ends, interrupted or not."""
    import fcntl

    lock = os.path.join(os.path.dirname(os.path.abspath(path)), f".{os.path.basename(path)}.lock")
    while True:
        with LOCK:  # an interrupt's exit (which takes LOCK) sees the lock file registered, or not ours
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                holder = os.read(fd, 32).decode(errors="replace").strip() or "another process"
                os.close(fd)
                raise InputError(
                    f"{what} {path}: another coopjax run (pid {holder}) is writing it; wait for it to end, or "
                    "choose another output",
                    "out",
                ) from None
            try:  # the file locked must still be the one at its name (a run that ended may have removed it)
                same = os.fstat(fd).st_ino == os.stat(lock).st_ino
            except FileNotFoundError:
                same = False
            if same:
                IN_FLIGHT.add(lock)  # an interrupt's exit removes it with the temporary files
                break
            os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.write(fd, str(os.getpid()).encode())
        yield
    finally:
        _discard(lock)
        os.close(fd)
