"""The persistent compilation cache (JAX's own, on disk), which is only ever an accelerator: the
command line's, and a Python program's through `coopjax.use_cache()`.

A run of `coopjax tune` spends about 20 s compiling its programs, the same ones every time for the
same options, and a script's `jax.jit(jax.grad(...))` of a run 20 s or more. With JAX's persistent
cache a later run loads them instead. The folder is
`$XDG_CACHE_HOME/coopjax/xla` (`~/.cache/coopjax/xla`); `COOPJAX_CACHE=FOLDER` moves it (a leading
`~` is the home folder) and `COOPJAX_CACHE=` (empty) turns it off. A user who sets JAX's own
`JAX_COMPILATION_CACHE_DIR` keeps it, and its behaviour. JAX keys each entry on the program, the
compile options and the jax and XLA versions, so a changed model or an upgraded jax compiles afresh
rather than loading a stale program. The entries are machine code for this CPU, and a folder may be
shared (a network home, a `jax.distributed` sweep over several machines), so each machine and jax
build gets a subfolder of its own (`machine_tag`).

JAX trusts an entry's content: an entry holding another program (two entries' files swapped, a bad
copy) reaches XLA, which can abort the process. So each subfolder keeps the SHA-256 of every entry
this project wrote (`SUMS`), and before JAX reads anything, an entry whose content is not the one
recorded for its name, or that no run recorded, is deleted (`verify`): it costs a compile, never a
crash. The sums are keyed by the entry's name inside the folder, so a cache copied to another path
(or machine of the same kind) is used there. What JAX would warn about the cache (an unreadable
entry, a full disk while writing) becomes at most one short note for the whole run, printed at its
end, and only by a command that compiled something.
"""

from __future__ import annotations

import atexit
import hashlib
import json
import os
import platform
import warnings

from coopjax.errors import InputError

ENV = "COOPJAX_CACHE"
MAX_BYTES = 2 * 1024**3  # JAX evicts the least recently used entries beyond this
# Cache programs that take a fifth of a second or more to compile (JAX's default is 1 s): a tuning
# run has several such programs besides the large ones.
MIN_COMPILE_S = 0.2


SUMS = "coopjax-sums.json"  # in each machine's subfolder: entry name -> [size, mtime_ns, inode, sha256]
SUFFIX, ATIME = "-cache", "-atime"  # JAX's names for an entry and its access time
_notes: list[str] = []  # what the run should hear about its cache, said once at its end
_compiled = [False]
_listening = [False]
_write_failed = [False]  # JAX could not write an entry this run: what it wrote may be cut short


def location(environ=os.environ) -> tuple[str | None, bool]:
    """(folder, whether the user chose it); folder None: no cache of ours."""
    if environ.get("JAX_COMPILATION_CACHE_DIR"):
        return None, True
    if ENV in environ:
        return (os.path.expanduser(environ[ENV]) or None), True
    base = os.path.expanduser(environ.get("XDG_CACHE_HOME") or "") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "coopjax", "xla"), False


def describe(environ=os.environ) -> str:
    """One line for `coopjax --help`."""
    folder, _ = location(environ)
    if environ.get("JAX_COMPILATION_CACHE_DIR"):
        return f"Compiled programs are kept in JAX's cache, {environ['JAX_COMPILATION_CACHE_DIR']}."
    if folder is None:
        return f"The compile cache is off ({ENV} is empty): every run compiles afresh."
    return (
        f"Compiled programs are kept in {folder} for later runs, a subfolder per machine and jax build "
        f"({ENV}=FOLDER moves the cache, {ENV}= turns it off)."
    )


def machine_tag() -> str:
    """A short hash of what a compiled CPU program depends on beyond its own key: the CPU's
    instruction-set features, the operating system, and the jax and jaxlib builds (their versions
    as imported, not as the package metadata says)."""
    import jax
    import jaxlib.version

    features = platform.processor()
    try:
        with open("/proc/cpuinfo") as f:  # Linux: the features line ("flags" on x86, "Features" on ARM)
            features = next((line for line in f if line.split(":")[0].strip() in ("flags", "Features")), features)
    except OSError:
        pass
    text = "|".join([platform.system(), platform.machine(), features, jax.__version__, jaxlib.version.__version__])
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def enable(environ=os.environ, quiet: bool = True, argument: bool = False) -> str | None:
    """Point JAX's persistent cache at our folder's subfolder for this machine; returns it (None: not
    ours, or off).

    A folder the user named that cannot be used is bad input. The default folder failing (a
    read-only home) costs only speed: one line on stderr, and the run goes on without a cache.
    `quiet` (the command line) gathers what JAX would warn about the cache into one note for the
    run's end (`note`); otherwise JAX's warnings and ours reach the program as warnings. `argument`:
    the folder came as `use_cache`'s argument, and an error names it so.
    """
    shared, chosen = location(environ)
    if shared is None:
        return None
    say = _notes.append if quiet else (lambda text: warnings.warn(f"coopjax: {text}", RuntimeWarning, stacklevel=3))
    try:
        if os.path.exists(shared) and not os.path.isdir(shared):
            raise NotADirectoryError(20, "a file, not a folder")
        folder = os.path.join(shared, machine_tag())
        os.makedirs(folder, exist_ok=True)
        if not os.access(folder, os.W_OK | os.X_OK):
            raise PermissionError(13, "not writable")
    except OSError as error:
        if chosen:
            origin = f"use_cache({shared!r})" if argument else f"{ENV}={shared}"
            off = "" if argument else f", or set {ENV}= (empty) to run without it"
            raise InputError(
                f"{origin}: cannot keep the compile cache there ({error.strerror}); name a writable folder{off}"
            ) from None
        say(f"no compile cache ({shared}: {error.strerror}); every run compiles afresh")
        folder = None
    if quiet:  # once the folder is settled: a refused one installs no hooks
        _listen()
    if folder is None:
        return None
    try:
        verify(folder)
    except OSError as error:  # entries it could neither check nor remove: the run goes without
        say(f"the compile cache in {folder} was not used ({error.strerror})")
        return None
    import jax

    jax.config.update("jax_compilation_cache_dir", folder)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_S)
    jax.config.update("jax_compilation_cache_max_size", MAX_BYTES)
    # XLA's own GPU kernel and autotuning caches would put the folder's path into every program's
    # key (so a copied cache would never hit); they do nothing on a CPU.
    jax.config.update("jax_persistent_cache_enable_xla_caches", "none")
    atexit.register(_record_quietly, folder)
    return folder


def _sha(path: str) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _read_sums(folder: str) -> dict:
    try:
        with open(os.path.join(folder, SUMS)) as f:
            sums = json.load(f)
        return sums if isinstance(sums, dict) else {}
    except (OSError, ValueError):
        return {}


def _write_sums(folder: str, sums: dict) -> None:
    tmp = os.path.join(folder, f".{SUMS}.{os.getpid()}")
    with open(tmp, "w") as f:
        json.dump(sums, f)
    os.replace(tmp, os.path.join(folder, SUMS))


def _stat(path: str) -> list:
    st = os.stat(path)
    return [st.st_size, st.st_mtime_ns, st.st_ino]


def _drop(path: str) -> None:
    """Remove an entry and its access time."""
    for doomed in (path, path[: -len(SUFFIX)] + ATIME):
        try:
            os.unlink(doomed)
        except FileNotFoundError:
            pass


def verify(folder: str) -> list[str]:
    """Delete every entry whose content is not the one recorded for its name (or that nothing
    recorded); returns their names. An entry whose size, time and inode are as recorded is not read
    again. Raises OSError if a bad entry cannot be removed."""
    sums, removed = _read_sums(folder), []
    for name in sorted(os.listdir(folder)):
        if not name.endswith(SUFFIX):
            continue
        path, known = os.path.join(folder, name), sums.get(name)
        try:
            if isinstance(known, list) and len(known) == 4:
                if _stat(path) == known[:3]:
                    continue
                if _sha(path) == known[3]:  # moved or copied, same content
                    sums[name] = _stat(path) + [known[3]]
                    continue
        except OSError:
            pass  # unreadable: removed below
        _drop(path)
        sums.pop(name, None)
        removed.append(name)
    for name in [n for n in sums if not os.path.exists(os.path.join(folder, n))]:  # evicted by JAX
        del sums[name]
    _write_sums(folder, sums)
    return removed


def record(folder: str, trust_new: bool = True) -> None:
    """Add the sums of the entries this run wrote (at its end: JAX writes them as it compiles).
    `trust_new=False` (a write failed this run, so an entry may be cut short): remove them instead."""
    sums = _read_sums(folder)
    for name in os.listdir(folder):
        path = os.path.join(folder, name)
        if name.endswith(SUFFIX) and not (isinstance(sums.get(name), list) and sums[name][:3] == _stat(path)):
            if trust_new:
                sums[name] = _stat(path) + [_sha(path)]
                continue
            _drop(path)
            sums.pop(name, None)
    _write_sums(folder, sums)


def _record_quietly(folder: str) -> None:
    try:
        record(folder, trust_new=not _write_failed[0])
    except OSError:  # a full disk or a vanished folder: the next run checks (and drops) what is unknown
        pass


def _listen() -> None:
    """Turn JAX's cache warnings into one note, and notice whether the run compiled anything (once
    per process: a test, or a program calling `main` again, must not stack the hooks)."""
    import jax

    if _listening[0]:
        return
    _listening[0] = True
    shown = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        text = str(message)
        if "persistent compilation cache" in text:
            what = text.rsplit(": ", 1)[-1][:80]
            note = (
                f"the compile cache could not be read ({what}); those programs were compiled afresh"
                if "reading" in text
                else f"the compile cache could not be written ({what}); a later run compiles those programs again"
            )
            if "reading" not in text:
                _write_failed[0] = True
            if not any(n.startswith("the compile cache could not") for n in _notes):
                _notes.append(note)
            return
        shown(message, category, filename, lineno, file, line)

    warnings.showwarning = show

    def compiled(event, *args, **kwargs):
        if event.startswith("/jax/core/compile") or event.startswith("/jax/compilation_cache"):
            _compiled[0] = True

    jax.monitoring.register_event_duration_secs_listener(compiled)
    jax.monitoring.register_event_listener(compiled)


def use_cache(folder: str | None = None) -> str | None:
    """Keep the programs this process compiles on disk, so that a later run of the same program
    loads them instead of compiling again (a jitted gradient of a run: 20 s or more the first time).

    Call it first, before anything is compiled, as `use_all_cores`. The folder is the command
    line's (`~/.cache/coopjax/xla`, or `$COOPJAX_CACHE`; an empty `COOPJAX_CACHE` turns it off), or
    `folder`; a subfolder per machine and jax build. An entry whose content is not what this project
    recorded for it is deleted and compiled afresh, never loaded. JAX keys each entry on the
    program, so a changed model or jax compiles afresh. A user's own `JAX_COMPILATION_CACHE_DIR`
    wins when no folder is given. Returns the subfolder in use, or None (no cache of ours).

    Raises InputError if `folder` (or `$COOPJAX_CACHE`) cannot hold the cache; a default folder that
    cannot (a read-only home) is a warning, and the program runs without one.
    """
    if folder is not None:
        if not isinstance(folder, (str, os.PathLike)) or not str(folder):
            raise InputError(f"folder is {folder!r}: a folder's path, or None for the default", "folder")
        return enable({ENV: os.fspath(folder)}, quiet=False, argument=True)
    return enable(os.environ, quiet=False)


def note() -> str | None:
    """The run's one note about its cache, if it compiled anything and there is something to say."""
    return "; ".join(_notes) if _notes and _compiled[0] else None
