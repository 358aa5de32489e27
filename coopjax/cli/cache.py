"""The command line's persistent compilation cache (JAX's own, on disk).

A run of `coopjax tune` spends about 20 s compiling its programs, the same ones every time for the
same options. With JAX's persistent cache a later run loads them instead. The folder is
`$XDG_CACHE_HOME/coopjax/xla` (`~/.cache/coopjax/xla`); `COOPJAX_CACHE=FOLDER` moves it and
`COOPJAX_CACHE=` (empty) turns it off. A user who sets JAX's own `JAX_COMPILATION_CACHE_DIR` keeps it.
JAX keys each entry on the program, the compile options and the jax and XLA versions, so a changed
model or an upgraded jax compiles afresh rather than loading a stale program. The entries are
machine code for this CPU, and a folder may be shared (a network home, a `jax.distributed` sweep
over several machines), so each machine and jax build gets a subfolder of its own (`machine_tag`):
no process loads a program built for another CPU's instruction set, or by another jaxlib (which
XLA's loader rejects at best, and which can crash it).
"""

from __future__ import annotations

import hashlib
import os
import platform
import sys

from coopjax.errors import InputError

ENV = "COOPJAX_CACHE"
MAX_BYTES = 2 * 1024**3  # JAX evicts the least recently used entries beyond this
# Cache programs that take a fifth of a second or more to compile (JAX's default is 1 s): a tuning
# run has several such programs besides the large ones.
MIN_COMPILE_S = 0.2


def location(environ=os.environ) -> tuple[str | None, bool]:
    """(folder, whether the user chose it); folder None: no cache of ours."""
    if environ.get("JAX_COMPILATION_CACHE_DIR"):
        return None, True
    if ENV in environ:
        return (environ[ENV] or None), True
    base = environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
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


def enable(environ=os.environ) -> str | None:
    """Point JAX's persistent cache at our folder's subfolder for this machine; returns it (None: not
    ours, or off).

    A folder the user named that cannot be used is bad input. The default folder failing (a
    read-only home) costs only speed: one line on stderr, and the run goes on without a cache.
    """
    shared, chosen = location(environ)
    if shared is None:
        return None
    try:
        if os.path.exists(shared) and not os.path.isdir(shared):
            raise NotADirectoryError(20, "a file, not a folder")
        folder = os.path.join(shared, machine_tag())
        os.makedirs(folder, exist_ok=True)
        if not os.access(folder, os.W_OK | os.X_OK):
            raise PermissionError(13, "not writable")
    except OSError as error:
        if chosen:
            raise InputError(
                f"{ENV}={shared}: cannot keep the compile cache there ({error.strerror}); name a "
                f"writable folder, or set {ENV}= (empty) to run without it"
            ) from None
        print(
            f"coopjax: note: no compile cache ({shared}: {error.strerror}); every run compiles afresh", file=sys.stderr
        )
        return None
    import jax

    jax.config.update("jax_compilation_cache_dir", folder)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_S)
    jax.config.update("jax_compilation_cache_max_size", MAX_BYTES)
    return folder
