"""All of this machine's cores for one batch: JAX's CPU backend as one device per core, and the
batch sharded over them.

JAX fixes its CPU device count when its backend starts, so it cannot be changed on import without
changing the user's JAX for them. `use_all_cores()` is the one call that does it, first thing;
`simulate` then shards any batch over the devices, and warns once when a large batch runs on one
core of several.
"""

from __future__ import annotations

import os
import warnings

import jax
import numpy as np

LARGE_BATCH = 1024  # samples: below this, one core is not worth a warning
# Samples per device per dispatch when a batch runs over several devices: the step's working set
# then stays in cache. On this 2-core CPU, at B = 4096 over 2 devices, blocks of 256 ran plain RK4
# 1.8x (float32) and 1.4x (float64) faster than one dispatch of the whole batch, and the
# sliding-mode step 1.3x (measured with `benchmarks/profile_step.py`'s setup, paired runs). The
# sweep runner uses the same block, so its tables do not depend on the chunk size.
BLOCK = 256
_warned = False


def use_all_cores(n: int | None = None) -> int:
    """One XLA CPU device per core (or `n`); call before any JAX computation. Returns the count."""
    n = n or os.cpu_count() or 1
    if n < 1:
        raise ValueError(f"n = {n}: at least one device")
    try:
        jax.config.update("jax_num_cpu_devices", int(n))
    except RuntimeError:
        if jax.device_count() != n:
            raise RuntimeError(
                f"JAX has already started with {jax.device_count()} device(s): call coopjax.use_all_cores() "
                "before anything creates a JAX array (first thing after the imports)"
            ) from None
    return jax.device_count()


def _warn_one_core(batch: int) -> None:
    global _warned
    cores = os.cpu_count() or 1
    if not _warned and batch >= LARGE_BATCH and jax.device_count() == 1 and cores > 1:
        _warned = True
        warnings.warn(
            f"a batch of {batch} runs on 1 of this machine's {cores} cores: call coopjax.use_all_cores() "
            "first thing in your program to shard batches over all of them", stacklevel=3)


def shard(batched):
    """The path without slabs (one device, a traced batch, or more than one batch axis): warn once
    if a large batch runs on one core of several. Returns (params, batch size)."""
    size = int(np.prod(batched.batch_shape))
    if not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(batched)):
        _warn_one_core(size)  # under grad/jit/vmap the caller's transformation decides the layout
    return batched, size


def place(tree, devices=None):
    """Put every leaf on `devices` (default: all), its last (batch) axis split over them."""
    mesh = jax.sharding.Mesh(np.array(devices or jax.devices()), ("batch",))
    return jax.tree_util.tree_map(lambda x: jax.device_put(x, jax.sharding.NamedSharding(mesh, batch_spec(x))), tree)


def slabs(batched, block: int = BLOCK):
    """A concrete batch (last axis of every leaf) as slabs of `devices x block` samples (or one slab
    of the whole batch, padded to a multiple of the device count, if it is smaller), each placed
    split over the devices. The last slab is padded by repeating the last sample, so all slabs share
    one compiled program. Cut on the host: slicing device arrays cost a dispatch per leaf and slab.
    Returns (slabs, original batch size)."""
    leaves, tree = jax.tree_util.tree_flatten(batched)
    host = [np.asarray(x) for x in leaves]
    size, n = host[0].shape[-1], jax.device_count()
    _warn_one_core(size)
    slab = n * block if size > n * block else -(-size // n) * n
    pad = -size % slab
    if pad:
        host = [np.concatenate([x, np.repeat(x[..., -1:], pad, axis=-1)], axis=-1) for x in host]
    return [place(jax.tree_util.tree_unflatten(tree, [x[..., start:start + slab] for x in host]))
            for start in range(0, size + pad, slab)], size


def batch_spec(x) -> jax.sharding.PartitionSpec:
    """Split an array's last (batch) axis over the mesh's "batch" axis; a scalar is replicated."""
    ndim = getattr(x, "ndim", 0)
    return jax.sharding.PartitionSpec(*([None] * (ndim - 1) + ["batch"])) if ndim else jax.sharding.PartitionSpec()


def per_device(fn, devices, out_specs=None):
    """`fn` (params with a batch last axis -> arrays with it) run by each device on its own slice.

    With `shard_map`, nothing crosses devices inside the time loop: a batch-wide test such as the
    sliding-mode step's "does any sample hit in this step" is taken per device. Under GSPMD it was
    an all-reduce per substep, and two devices ran float64 filippov 1.2x faster than one instead of
    1.9x (measured). `out_specs` defaults to the batch last axis on every output leaf.
    """
    mesh = jax.sharding.Mesh(np.array(devices), ("batch",))

    def run(params):
        specs = out_specs if out_specs is not None else jax.tree_util.tree_map(
            batch_spec, jax.eval_shape(fn, params))
        in_specs = jax.tree_util.tree_map(batch_spec, params)
        return jax.shard_map(fn, mesh=mesh, in_specs=(in_specs,), out_specs=specs, check_vma=False)(params)

    return run


def unpad(tree, size: int):
    """Drop the padding `slabs` added (last axis of every array leaf)."""
    return jax.tree_util.tree_map(lambda x: x[..., :size] if getattr(x, "ndim", 0) else x, tree)
