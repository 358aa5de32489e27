"""A `jax.distributed` sweep that fails in one line.

When a partner process dies or never joins, JAX's coordination service ends the others from native
code (an abort, exit 134, and pages of C++ stack) where Python cannot catch it. So a distributed
`coopjax sweep` runs its work in a child process and watches it: the child's own lines pass through
as they come, XLA's native log and stack lines go to a file beside the output, and a child that dies
from a signal or an abort becomes one line that says what happened and what was kept.

Only the standard library is used here: the parent never starts JAX.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys

ENV = "COOPJAX_SUPERVISED"  # set in the child: it does the work itself
# absl's log lines (E1203 16:00:00.123456 ...), stack frames, and the abort's banners
NATIVE = re.compile(
    r"^([EFW]\d{4} \d\d:\d\d:\d\d|\s*@\s+0x|\*\*\* |Check failed|terminate called|Fatal Python|Aborted|native: )"
)
EXIT_LOST = 75  # the child's code when a collective failed (a partner gone): the parent says it in one line


def is_lost(error: BaseException) -> bool:
    """Whether an exception is a collective that failed because a partner is gone (JAX raises it as
    a JaxRuntimeError or a ValueError, depending on where it surfaces)."""
    text = str(error)
    return any(s in text for s in ("Gloo", "Connection closed", "Connection reset", "coordination service"))


def lost(error: BaseException) -> None:
    """In the child: a collective failed because a partner is gone. Its text goes to the parent as
    details, and the child ends at once (JAX's shutdown would wait for the lost partner)."""
    sys.stderr.write("".join(f"native: {line}\n" for line in str(error).splitlines()))
    sys.stderr.flush()
    os._exit(EXIT_LOST)


def supervised() -> bool:
    """Whether this process is the child that does the work."""
    return os.environ.get(ENV) == "1"


def run(argv: list[str], log_path: str, describe_kept) -> int:
    """Run `coopjax ARGV` as a child and relay it; returns the exit code to give."""
    env = dict(os.environ, **{ENV: "1"})
    # Ctrl-C and SIGTERM go to the child, which answers them in its one line; this process only waits.
    # (The interrupt watcher's wakeup pipe is set aside meanwhile, or it would answer them too.)
    wakeup = signal.set_wakeup_fd(-1)
    child = None

    def forward(signum, frame):
        if child is not None and child.poll() is None:
            child.send_signal(signum)

    previous = {s: signal.signal(s, forward) for s in (signal.SIGINT, signal.SIGTERM)}

    def child_signals():  # the child answers Ctrl-C itself (one line); the parent only waits for it
        for s in (signal.SIGINT, signal.SIGTERM):
            signal.signal(s, signal.SIG_DFL)
        _die_with_parent()

    native: list[str] = []
    try:
        child = subprocess.Popen(
            [sys.executable, "-m", "coopjax.cli", *argv],
            env=env,
            stderr=subprocess.PIPE,
            text=True,
            errors="replace",
            preexec_fn=child_signals,
        )
        for line in child.stderr:
            # After XLA's first native line the child is dying: all but its own lines are details.
            if NATIVE.match(line) or (native and not line.startswith("coopjax:")):
                native.append(line)
            else:
                sys.stderr.write(line)
                sys.stderr.flush()
        code = child.wait()
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        signal.set_wakeup_fd(wakeup)
    if code in (0, 1, 2, 3, 130, 143):  # the child said it itself
        return code
    reason = _reason(native)
    if native:
        try:
            with open(log_path, "a") as f:
                f.writelines(native)
            details = f"; XLA's details are in {log_path}"
        except OSError:
            details = ""
    else:
        details = ""
    kept = describe_kept()
    print(
        f"coopjax: error: the distributed sweep stopped: {reason}" + (f"; {kept}" if kept else "") + details,
        file=sys.stderr,
    )
    return 1


def _die_with_parent() -> None:
    """Linux: the child is killed when the parent is (a kill -9 of the command must end its work)."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _reason(native: list[str]) -> str:
    text = " ".join(native)
    if "Connection closed" in text or "Connection reset" in text:
        return "a partner process was lost"
    if "DEADLINE_EXCEEDED" in text or "Barrier timed out" in text or "timed out" in text.lower():
        return "a partner process did not join, or stopped answering, within --timeout"
    if "heartbeat" in text.lower() or "UNAVAILABLE" in text or "lost" in text.lower():
        return "a partner process was lost"
    return "a process of the sweep ended abnormally (a partner lost, or a crash)"
