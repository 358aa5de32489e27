"""Strict numerics for verification: float64 everywhere, and no silent rank promotion."""

import os

# The classic XLA CPU emitters for the suite: it is bound by compile time (a hundred programs, most
# run briefly), and they compile this model's programs faster (the suite took 361 s with XLA's
# defaults against 269 s, measured). They change the generated code, so results move by round-off
# only; the library, the CLI and the benchmarks use XLA's defaults (with 512-bit vectors on
# AVX-512), which run the step faster.
# Set before JAX starts; a user's own XLA_FLAGS choice is kept.
# LLVM's optimisation level 0 for the same reason: 13 % off the hard-model gradient test (38 s -> 33 s).
if "xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_use_fusion_emitters=false").strip()
if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0").strip()
# And LLVM's expensive passes off: 16 % off the gradient tests' compiles (44 s -> 37 s on three of them).
if "xla_llvm_disable_expensive_passes" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_llvm_disable_expensive_passes=true").strip()

# One persistent compilation cache per test session, shared by the two workers and by the `coopjax`
# subprocesses that several tests start (same programs, compiled once instead of three or four
# times). It is named after the session's process (a worker's parent), and removed when it ends.
SESSION = os.getppid() if os.environ.get("PYTEST_XDIST_WORKER") else os.getpid()
CACHE = None
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    import tempfile

    CACHE = os.path.join(tempfile.gettempdir(), f"coopjax-tests-{SESSION}")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = CACHE
    # Cache programs that compile in a fifth of a second or more (JAX's default is 1 s): most of the
    # CLI subprocesses' programs are below a second, and each subprocess compiled them again.
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.2")

import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")


@pytest.fixture(autouse=True)
def small_judge_block(monkeypatch):
    """The judge's runs per device per call, at the suite's size. A run's judgings share one block
    (`JUDGE_BLOCK`, 128) so that they share one compiled program; with the suite's unoptimised XLA
    code (above), judging 2 held-out draws in blocks of 128 per device cost 8 s a time. The code
    path is the same at any block."""
    from tuning import judging

    monkeypatch.setattr(judging, "JUDGE_BLOCK", 8)


@pytest.fixture
def with_xla_defaults():
    """`run(code)`: Python `code` in a fresh process with XLA's default flags, as users have them
    (not the suite's, above), and no shared cache; returns its last line of output, read as JSON."""

    def run(code):
        env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_COMPILATION_CACHE_DIR")}
        root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        done = subprocess.run([sys.executable, "-c", code], cwd=root, env=env, capture_output=True, text=True)
        assert done.returncode == 0, done.stderr[-2000:]
        return json.loads(done.stdout.strip().splitlines()[-1])

    return run


@pytest.fixture
def fresh_dir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    return tmp_path


def pytest_sessionfinish(session):
    if CACHE and not os.environ.get("PYTEST_XDIST_WORKER"):
        import shutil

        shutil.rmtree(CACHE, ignore_errors=True)
