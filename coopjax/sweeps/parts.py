"""The parts folder of a resumable sweep: a manifest that identifies the sweep, and one file per
finished chunk, each written atomically."""

from __future__ import annotations

import errno
import io as io_module
import json
import os
import sys

import numpy as np

from coopjax.errors import InputError
from coopjax.io import atomic_path
from coopjax.sweeps.spec import SweepSpec

# Bumped when a chunk file's layout or a column's meaning changes, so --resume never mixes them.
CHUNK_FORMAT = 4


def load_part(parts: str, k: int, rows: int, width: int):
    """A saved chunk, or None (with a note) if it is unreadable or the wrong shape: it is recomputed."""
    path = part_path(parts, k)
    try:
        data = np.load(path, allow_pickle=False)  # data only: a planted file runs no code
        if data.shape == (rows, width):
            return data
    except (OSError, ValueError, EOFError):  # ValueError: also an object array, refused
        pass
    print(f"coopjax: note: {path} is unreadable or incomplete; it is computed again", file=sys.stderr)
    return None


def save_array(path: str, array: np.ndarray) -> None:
    """One .npy file, atomically. Through a buffer: numpy's own file writer reports a short write on
    a full disk without its errno, and Python's says ENOSPC."""
    buffer = io_module.BytesIO()
    np.save(buffer, array)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(buffer.getbuffer())


def part_path(parts: str, k: int) -> str:
    return os.path.join(parts, f"chunk-{k:06d}.npy")


def finished_parts(parts: str) -> int:
    """How many finished chunks a parts folder holds."""
    try:
        return sum(1 for n in os.listdir(parts) if n.startswith("chunk-") and n.endswith(".npy"))
    except OSError:
        return 0


def prepare_parts(parts: str, spec: SweepSpec, chunk: int, resume: bool, n_chunks: int) -> np.ndarray:
    """The parts folder of a sweep: created with its manifest, or checked against it on resume.
    Returns which chunks are already finished."""
    manifest = os.path.join(parts, "manifest.json")
    identity = json.dumps(
        {"spec": json.loads(spec.to_json()), "chunk": chunk, "columns": list(spec.columns), "format": CHUNK_FORMAT},
        sort_keys=True,
    )
    if os.path.exists(manifest):
        if not resume:
            raise InputError(f"{parts} holds an unfinished sweep: resume it (--resume), or delete it", "resume")
        try:
            if not os.access(manifest, os.R_OK):
                raise PermissionError(13, "permission denied")
            with open(manifest) as f:
                saved = f.read()
        except OSError as error:
            raise InputError(
                f"{manifest} is not readable ({error.strerror}): fix its permissions or delete {parts}", "resume"
            ) from None
        if not os.access(parts, os.W_OK):
            raise InputError(f"{parts} is not writable: fix its permissions or delete it", "resume")
        if saved != identity:
            raise InputError(
                f"{parts} belongs to a different sweep (other options or chunk size): "
                "use the same options, or delete it",
                "resume",
            )
        return np.array([os.path.exists(part_path(parts, k)) for k in range(n_chunks)])
    if os.path.exists(parts) and not os.path.isdir(parts):
        raise InputError(f"{parts} exists and is not a folder: remove it", "out")
    try:
        os.makedirs(parts, exist_ok=True)
        if not os.access(parts, os.W_OK | os.X_OK):
            raise PermissionError(13, "Permission denied")
        with atomic_path(manifest) as tmp:
            with open(tmp, "w") as f:
                f.write(identity)
    except OSError as error:
        if error.errno in (errno.ENOSPC, errno.EDQUOT):
            raise  # the command's full-disk line
        raise InputError(
            f"cannot keep the sweep's chunks in {parts} ({error.strerror}): fix its permissions, or choose "
            "another --out",
            "out",
        ) from None
    return np.zeros(n_chunks, bool)
