"""Ctrl-C (and SIGTERM) at any moment: one line, nothing half-written, what was finished kept.

A KeyboardInterrupt raised wherever the main thread happens to be is not safe here: raised inside a
garbage-collection callback of JAX it is swallowed (the run goes on and writes its files), and raised
while XLA's threads compile it unwinds into an interpreter teardown that can crash (exit 139). So
the signal is not turned into an exception at all. Python's C-level handler writes it to a wakeup
pipe; a watcher thread, blocked on that pipe, wakes at once (even while the main thread is inside
XLA), removes the temporary files in flight under the output lock (`coopjax.io`), says in one line
what was kept, and ends the process with `os._exit`, skipping the teardown.

Only the standard library is imported here: this is installed before JAX is.
"""

from __future__ import annotations

import os
import signal
import sys
import threading

EXIT = {signal.SIGINT: 130, signal.SIGTERM: 143}
_report = [lambda: None]  # the running command's account of what is kept (a sentence, or None)
_installed = [False]


def report_with(describe) -> None:
    """Set the function that says what an interrupted run keeps (called once, at the interrupt)."""
    _report[0] = describe


def account() -> str | None:
    """What a stopped run keeps, in a few words: the command's own account, else the files written."""
    text = _report[0]()
    io = sys.modules.get("coopjax.io")
    if text is None and getattr(io, "WRITTEN", None):
        # Only what is still there: a run removes some of its own files (a checkpoint, merged parts).
        written = [path for path in dict.fromkeys(io.WRITTEN) if os.path.exists(path)]
        if written:
            text = f"{', '.join(written)} {'was' if len(written) == 1 else 'were'} written before it"
    return text


def line_start() -> str:
    """What starts the one line of an interrupt: on a terminal, a return that erases what the line
    held (a progress bar, or the ^C the terminal echoed)."""
    try:
        return "\r\x1b[K" if os.isatty(2) else ""
    except (OSError, ValueError):
        return ""


def _stop(signum: int) -> None:
    text = None
    try:
        io = sys.modules.get("coopjax.io")
        lock = getattr(io, "LOCK", None)  # None while the module is still being imported: nothing in flight
        if lock is not None:
            with lock:  # no rename is half done; nothing new starts
                for tmp in list(io.IN_FLIGHT):
                    try:
                        os.unlink(tmp)
                    except OSError:
                        pass
                    io.IN_FLIGHT.discard(tmp)
                text = account()
    except Exception as error:  # say so rather than nothing
        text = f"what was kept is unknown ({type(error).__name__})"
    finally:
        name = "interrupted" if signum == signal.SIGINT else "terminated"
        # Straight to the file descriptor: the main thread may be inside sys.stderr (a progress bar),
        # and a second writer there raises instead of writing.
        try:
            os.write(2, f"{line_start()}coopjax: {name}; {text or 'nothing was written'}\n".encode())
        finally:
            os._exit(EXIT.get(signum, 128 + signum))


def _watch(fd: int) -> None:
    while True:
        try:
            data = os.read(fd, 1)
        except InterruptedError:
            continue
        if not data:
            return
        signum = data[0]
        if signum in EXIT:
            _stop(signum)


def install() -> None:
    """Route SIGINT and SIGTERM to the watcher. Call first thing in the process's entry point."""
    if _installed[0] or threading.current_thread() is not threading.main_thread():
        return
    read, write = os.pipe()
    os.set_blocking(write, False)
    signal.set_wakeup_fd(write, warn_on_full_buffer=False)
    for signum in EXIT:
        if signal.getsignal(signum) is signal.SIG_IGN:
            continue  # started with it ignored (nohup, a background job): keep it so
        # A Python-level handler is needed for the C-level one (and the wakeup pipe) to be active;
        # it does nothing itself: the watcher acts.
        signal.signal(signum, lambda s, f: None)
    threading.Thread(target=_watch, args=(read,), name="coopjax-interrupts", daemon=True).start()
    _installed[0] = True
