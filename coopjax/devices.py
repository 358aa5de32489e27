"""All of this machine's cores for one batch: the one place a batch is put on the devices.

JAX fixes its CPU device count when its backend starts, so it cannot be changed on import without
changing the user's JAX for them. `use_all_cores()` is the one call that does it, first thing. It
also asks XLA for the CPU's widest vectors (`wide_vectors`), which XLA reads at the same moment.

`run(fn, params)` then runs `fn` on a batch (the last axis of every leaf) over every local device:
padding, slabs, `shard_map`, unpadding. `simulate`, the sweeps and the tuner all go through it.
"""

from __future__ import annotations

import concurrent.futures
import functools
import os
import threading
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from coopjax.errors import InputError
from coopjax.traced import is_tracer

LARGE_BATCH = 1024  # samples: below this, one core is not worth a warning
# Samples per device per dispatch when a batch runs over several devices: the step's working set
# then stays in cache. On this 2-core CPU, at B = 4096 over 2 devices, blocks of 256 ran the
# sliding-mode step 1.2x to 1.4x faster than blocks of 64, 1024 or 2048 (docs/speed.md).
BLOCK = 256
# XLA's CPU backend vectorises with 256-bit registers by default (512-bit ones lower the clock of some
# Intel CPUs). On an AVX-512 CPU of this project's machines (AMD Zen 4) 512-bit vectors ran the
# sliding-mode step 1.1x to 1.26x faster, with the same bits (docs/speed.md).
WIDE_VECTORS = "--xla_cpu_prefer_vector_width=512"
_warned = False


@functools.lru_cache(maxsize=1)
def _has_avx512() -> bool:
    try:
        with open("/proc/cpuinfo") as f:
            return any(line.startswith("flags") and " avx512f" in line for line in f)
    except OSError:  # not Linux: XLA's default
        return False


def wide_vectors() -> bool:
    """Ask XLA for 512-bit vectors (`WIDE_VECTORS` in `XLA_FLAGS`) where the CPU has AVX-512. A
    vector width already set in `XLA_FLAGS` is kept. XLA reads it when JAX's backend starts, so it
    acts only if called before that (and in processes started later). Returns whether `XLA_FLAGS`
    now asks for 512-bit vectors."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_prefer_vector_width" in flags:
        return WIDE_VECTORS in flags.split()
    if not _has_avx512():
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {WIDE_VECTORS}".strip()
    return True


def use_all_cores(n: int | None = None) -> int:
    """One XLA CPU device per core (or `n`), and the CPU's widest vectors (`wide_vectors`); call
    before any JAX computation. Returns the device count."""
    request_devices(n)
    return jax.device_count()


def request_devices(n: int | None = None) -> None:
    """`use_all_cores` without starting JAX's backend (the command line starts `jax.distributed`
    after it): the device count and vector width JAX's backend will start with. Raises InputError if
    the backend has already started with another count."""
    global _warned
    n = (os.cpu_count() or 1) if n is None else n
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise InputError(f"n = {n!r}: at least one device", "n")
    wide_vectors()
    try:
        jax.config.update("jax_num_cpu_devices", int(n))
    except RuntimeError:
        if jax.device_count() != n:
            raise InputError(
                f"JAX has already started with {jax.device_count()} device(s): call coopjax.use_all_cores() "
                "before anything creates a JAX array (first thing after the imports)"
            ) from None
    _warned = True  # a device count asked for is not one to warn about


def _warn_one_core(batch: int) -> None:
    global _warned
    cores = os.cpu_count() or 1
    if not _warned and batch >= LARGE_BATCH and jax.device_count() == 1 and cores > 1:
        _warned = True
        warnings.warn(
            f"a batch of {batch} runs on 1 of this machine's {cores} cores: call coopjax.use_all_cores() "
            "first thing in your program to shard batches over all of them",
            stacklevel=4,
        )


def batch_spec(x, batched: bool = True) -> jax.sharding.PartitionSpec:
    """Split an array's last (batch) axis over the mesh's "batch" axis; anything else is replicated."""
    ndim = getattr(x, "ndim", 0)
    if not (batched and ndim):
        return jax.sharding.PartitionSpec()
    return jax.sharding.PartitionSpec(*([None] * (ndim - 1) + ["batch"]))


def _all_batched(out):
    return jax.tree_util.tree_map(lambda x: getattr(x, "ndim", 0) > 0, out)


def _per_device(fn, devices, batched):
    """`fn` run by each device on its own slice of the batch (shard_map): nothing crosses devices
    inside the time loop. Under GSPMD, the sliding-mode step's batch-wide "does any sample hit in
    this step" was an all-reduce per substep, and two devices ran 1.2x faster than one instead of 1.9x."""
    mesh = jax.sharding.Mesh(np.array(devices), ("batch",))

    def apply(params):
        shapes = jax.eval_shape(fn, params)
        out_specs = jax.tree_util.tree_map(batch_spec, shapes, batched(shapes))
        in_specs = jax.tree_util.tree_map(batch_spec, params)
        return jax.shard_map(fn, mesh=mesh, in_specs=(in_specs,), out_specs=out_specs, check_vma=False)(params)

    return apply


@functools.lru_cache(maxsize=64)
def _compiled(fn, n_devices: int, batched, per_device: bool):
    # Through a closure: jit keeps a weak reference to what it compiles, and `fn` may be a NamedTuple.
    if not per_device:
        return jax.jit(lambda params: fn(params))
    return jax.jit(_per_device(lambda params: fn(params), jax.local_devices()[:n_devices], batched))


def _place(tree, n_devices):
    mesh = jax.sharding.Mesh(np.array(jax.local_devices()[:n_devices]), ("batch",))
    return jax.tree_util.tree_map(lambda x: jax.device_put(x, jax.sharding.NamedSharding(mesh, batch_spec(x))), tree)


def pad_batch(leaves, pad, xp):
    """Each leaf with its last (batch) axis lengthened by `pad` copies of its last sample."""
    if not pad:
        return leaves
    return [xp.concatenate([x, xp.repeat(x[..., -1:], pad, axis=-1)], axis=-1) for x in leaves]


def _unpad(out, size, batched):
    return jax.tree_util.tree_map(lambda x, b: x[..., :size] if b else x, out, batched(out))


def run(
    fn,
    params,
    *,
    batched=_all_batched,
    block: int = BLOCK,
    fixed_block: bool = False,
    shard_traced: bool = False,
    devices: int | None = None,
    compile_only: bool = False,
):
    """`fn(params)` on a batch of parameter sets (the last axis of every leaf), over the local devices.

    - A concrete batch over several devices is cut on the host into slabs of `devices x block`
      samples, dispatched one after another without waiting, each device running its own slice; a
      batch smaller than that is one slab padded to a multiple of the device count (with
      `fixed_block`, every slab is `devices x block`, so the compiled program never depends on the
      batch size: the sweeps' tables are bit-identical whatever their chunking). The padding repeats
      the last sample, and is dropped from the results. A batch of several slabs runs in the order
      `fn.batch_order(params)` gives, where `fn` has one (an integrator's: like samples together),
      and comes back in the caller's order.
    - A traced batch (under the caller's `jit` or `grad`) runs as `fn` in the caller's program, or,
      with `shard_traced`, padded and split over the devices inside it.
    - With one device, `fn` is jitted (concrete) or called (traced) as it is; where `fn` orders its
      batch (a step that decides work per batch, `Integrator.batch_order`), a concrete batch larger
      than `block` is cut into equal slabs of at most `block`, as on several devices.

    `fn` must be hashable (it keys the cache of compiled programs) and map a batch to a pytree
    whose leaves, where `batched(out)` says so, carry the batch as their last axis. With
    `compile_only`, a concrete batch's program is compiled (`compiled`) and returned, and nothing
    runs.
    """
    leaves, tree = jax.tree_util.tree_flatten(params)
    shape = np.shape(leaves[0])[-1:] if leaves and np.ndim(leaves[0]) else ()
    size = int(shape[0]) if shape else 1
    n = devices or jax.local_device_count()
    traced = any(is_tracer(x) for x in leaves)
    if traced:
        if not (shard_traced and n > 1 and shape):
            return fn(params)
        pad = -size % n
        padded = jax.tree_util.tree_unflatten(tree, pad_batch(leaves, pad, jnp))
        return _unpad(_per_device(lambda p: fn(p), jax.local_devices()[:n], batched)(padded), size, batched)
    _warn_one_core(size)
    batch_order = getattr(fn, "batch_order", None)  # the integrator's, where it decides work per batch
    ordered = batch_order(params) if batch_order is not None and shape else None
    slabs = ordered is not None
    if not shape or (n == 1 and not fixed_block and (size <= block or not slabs)):
        if compile_only:
            return compiled(_compiled(fn, 1, batched, False), params)
        return _compiled(fn, 1, batched, False)(params)
    if fixed_block or (n > 1 and size > n * block):
        slab = n * block
    elif size > block:  # one device, `slabs`: as even as `block` allows, so the padding stays small
        slab = -(-size // -(-size // block))
    else:
        slab = -(-size // n) * n
    pad = -size % slab
    host = [np.asarray(x) for x in leaves]
    order = ordered if size > slab else None
    if order is not None:
        host = [x[..., order] for x in host]
    host = pad_batch(host, pad, np)
    program = _compiled(fn, n, batched, n > 1)
    place = (lambda t: _place(t, n)) if n > 1 else (lambda t: t)
    parts_in = [
        place(jax.tree_util.tree_unflatten(tree, [x[..., s : s + slab] for x in host]))
        for s in range(0, size + pad, slab)
    ]
    executable = compiled(program, parts_in[0])  # outside the lock: another thread's programs may run meanwhile
    if compile_only:
        return executable
    if n == 1:
        parts = [executable(x) for x in parts_in]
    else:
        with EXCLUSIVE:
            parts = jax.block_until_ready([executable(x) for x in parts_in])
    out = _joined(jax.device_get(parts), size, batched)
    if order is not None:
        back = np.argsort(order)
        out = jax.tree_util.tree_map(lambda x, b: x[..., back] if b else x, out, batched(out))
    return jax.tree_util.tree_map(jax.device_put, out)


def _joined(parts, size, batched):
    """The slabs' outputs as one batch, joined on the host. Joined on the devices, the concatenate
    and the slice of the padding are programs with an all-gather across them, queued behind the
    slabs: on 2 cores their rendezvous could wait for a device thread busy with a slab, and XLA
    aborts a rendezvous after 40 s (seen with 1000 samples)."""
    if len(parts) == 1:
        return _unpad(parts[0], size, batched)
    flags = batched(parts[0])
    out = jax.tree_util.tree_map(lambda b, *xs: np.concatenate(xs, axis=-1) if b else xs[0], flags, *parts)
    return _unpad(out, size, batched)


# One multi-device program at a time in this process. Programs from two threads (the tuner's
# background judging and its selection) could otherwise be queued in opposite orders on two devices
# and wait for each other forever at a collective. Compiling needs no lock; running holds it until
# the outputs are ready.
EXCLUSIVE = threading.RLock()
# Every program compiled ahead of time in this process (`compiled`), as a future: a thread that asks
# for a program another thread is compiling waits for it instead of compiling it again.
_EXECUTABLES: dict[tuple, concurrent.futures.Future] = {}
_COMPILING = threading.Lock()
MAX_EXECUTABLES = 256


def compiled(program, *args, key=None):
    """`program` (a jitted function) compiled ahead of time for these arguments' shapes, dtypes and
    shardings, once per process, whichever thread asks first. `key` names the program (default: the
    function object itself), for callers whose programs are rebuilt from a description."""
    leaves, tree = jax.tree_util.tree_flatten(args)
    signature = (str(tree), tuple((np.shape(x), str(x.dtype), getattr(x, "sharding", None)) for x in leaves))
    key = (program if key is None else key, *signature)
    with _COMPILING:
        future, mine = _EXECUTABLES.get(key), False
        if future is None:
            if len(_EXECUTABLES) >= MAX_EXECUTABLES:  # the oldest goes
                del _EXECUTABLES[next(iter(_EXECUTABLES))]
            future = _EXECUTABLES[key] = concurrent.futures.Future()
            mine = True
    if mine:
        try:
            future.set_result(program.lower(*args).compile())
        except BaseException as error:
            with _COMPILING:  # the next caller tries again (and meets the error itself)
                _EXECUTABLES.pop(key, None)
            future.set_exception(error)
            raise
    return future.result()
