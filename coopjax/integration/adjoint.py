"""How a run is differentiated: the adjoint.

A run's derivative along a few parameters is cheapest in forward mode here: the state is 20 numbers
per sample and the horizon thousands of steps, so reverse mode through the time loop holds the step
three times (the pass, the step recomputed from its checkpoint, and its transpose) and compiles a
program twice the size of forward mode's. With `"forward"`, a run is a `jax.custom_jvp` whose rule
computes the Jacobian of every output along each differentiated parameter component by forward
mode (one tangent per component: copies of a small batch side by side, or one vmapped pass over
a large one; `COPIES_UP_TO`), and returns the tangent as that Jacobian times
the input's tangent. That product is linear in the tangent and cheap to transpose, so `jax.grad`
and `jax.vjp` pull back through it and never transpose the time loop: reverse mode compiles and
runs what forward mode does, once per component.

Samples are independent (no sample's answer depends on another's parameters), so one tangent per
component, the same for every sample of the batch, gives every sample's Jacobian at once.

One difference from the loop's transpose: a loss that takes in an output whose value is NaN but
does not move with the parameters (a metric whose window the run never reached) has a NaN value
and, through the Jacobian, a NaN derivative (0 times NaN); the transpose skips that output and
gives a number.

Under forward mode itself (`jax.jvp`, `jax.jacfwd`) the rule is the plain tangent: one direction,
whatever the number of components. Under reverse mode, `"auto"` takes the forward Jacobian when at
most `MAX_FORWARD` components are differentiated (its run time grows with their number) and
otherwise the plain tangent, which reverse mode transposes through the loop, as `"reverse"` always
does.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

from coopjax.traced import pulled_back

ADJOINTS = ("auto", "forward", "reverse")
# Above this many differentiated components, reverse mode through the loop is faster at run time
# than the Jacobian (the sliding-mode step, 256 bodies, float32: 16.6 s by the Jacobian against
# 15.5 s through the loop at 8 components, 35.2 against 16.0 s at 16; docs/speed.md).
MAX_FORWARD = 8
# Up to this many samples in all (components x batch), the components run as copies of the batch
# (`tangents_on_copies`: the plain jvp's program, the fastest to compile; its primal runs once per
# copy). Above it, a vmap of the jvp over the components carries them through one primal pass.
COPIES_UP_TO = 256


def differentiate(fn, params, batched, adjoint: str = "auto"):
    """`fn(params)` (a batch: every leaf's last axis) with derivatives by `adjoint`.

    `fn` is hashable; `batched(out)` flags the outputs that carry the batch as their last axis (the
    others must not depend on the parameters, as a record's times do not)."""
    if adjoint == "reverse":
        return fn(params)
    return _run(fn, batched, adjoint == "forward", params)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2))
def _run(fn, batched, always, params):
    return fn(params)


def _jvp(fn, batched, always, primals, tangents):
    (params,), (dparams,) = primals, tangents
    leaves, tree = jax.tree_util.tree_flatten(params)
    dleaves = tree.flatten_up_to(dparams)
    active = [
        i
        for i, (x, d) in enumerate(zip(leaves, dleaves))
        if not isinstance(d, SymbolicZero) and jnp.issubdtype(jnp.result_type(x), jnp.inexact)
    ]
    batch = np.shape(leaves[0])[-1:] if leaves and np.ndim(leaves[0]) else ()
    sizes = [math.prod(np.shape(leaves[i])[: np.ndim(leaves[i]) - len(batch)]) for i in active]
    values = tuple(leaves[i] for i in active)
    with_active = _replacing(fn, tree, leaves, active)

    if not batch or not pulled_back(dleaves) or (not always and sum(sizes) > MAX_FORWARD):
        return jax.jvp(with_active, values, tuple(dleaves[i] for i in active))

    # One direction per component of every differentiated leaf, the same for every sample.
    n = sum(sizes)
    directions, start = [None] * len(leaves), 0
    for i, m in zip(active, sizes):
        lead = np.shape(leaves[i])[: np.ndim(leaves[i]) - len(batch)]
        rows = jnp.eye(n, m, -start, dtype=leaves[i].dtype).reshape((n,) + lead + (1,) * len(batch))
        directions[i] = jnp.broadcast_to(rows, (n,) + np.shape(leaves[i]))
        start += m
    if n * math.prod(batch) <= COPIES_UP_TO:
        out, jac = tangents_on_copies(fn, params, jax.tree_util.tree_unflatten(tree, directions), batched)
    else:
        out, jac = jax.vmap(lambda *d: jax.jvp(with_active, values, d), out_axes=(None, 0))(
            *(directions[i] for i in active)
        )
    # The input's tangent per component and sample: (n, *batch).
    coef = jnp.concatenate([jnp.reshape(dleaves[i], (m,) + batch) for i, m in zip(active, sizes)])

    def contract(y, j, flag):
        if not jnp.issubdtype(jnp.result_type(y), jnp.inexact):
            return np.zeros(np.shape(y), jax.dtypes.float0)
        if not flag:
            return jnp.zeros_like(y)
        lead = np.ndim(y) - len(batch)
        return (j * coef.reshape((n,) + (1,) * lead + batch).astype(j.dtype)).sum(0)

    return out, jax.tree_util.tree_map(contract, out, jac, batched(out))


def tangents_on_copies(fn, params, directions, batched):
    """`fn(params)` and its tangents along n directions at once: (out, tangents), each tangent leaf
    with a leading axis n. `directions` has the structure of `params`, each leaf (n, *leaf.shape) or
    None (no tangent).

    The samples are independent, so the n directions run as n copies of the batch side by side:
    one `jax.jvp` of `fn` on a batch n times as long. That is the plain jvp's program; a `vmap`
    over the directions compiles half as long again (the README's gradient: 5.6 s against 10.2 s
    of XLA compile). It recomputes the primal per copy, which a batch too small to fill the cores
    does not notice."""
    leaves, tree = jax.tree_util.tree_flatten(params)
    dleaves = tree.flatten_up_to(directions)
    n = next(np.shape(d)[0] for d in dleaves if d is not None)
    copies = [jnp.concatenate([x] * n, axis=-1) for x in leaves]
    # Copy r of the batch carries direction r: (n, ..., B) -> (..., n * B), copy-major.
    flat = lambda d: jnp.moveaxis(d, 0, -2).reshape(np.shape(d)[1:-1] + (-1,))
    moving = [i for i, d in enumerate(dleaves) if d is not None]
    on_copies = _replacing(fn, tree, copies, moving)
    out, tangents = jax.jvp(on_copies, tuple(copies[i] for i in moving), tuple(flat(dleaves[i]) for i in moving))
    split = lambda y: jnp.moveaxis(jnp.reshape(y, np.shape(y)[:-1] + (n, -1)), -2, 0)
    flags = batched(out)
    first = jax.tree_util.tree_map(lambda y, b: split(y)[0] if b else y, out, flags)
    tangents = jax.tree_util.tree_map(
        lambda t, b: split(t) if b and t.dtype != jax.dtypes.float0 else t, tangents, flags
    )
    return first, tangents


def _replacing(fn, tree, leaves, indices):
    """`fn` of these leaves with those at `indices` taken as its arguments (what jvp differentiates)."""

    def at(*values):
        new = list(leaves)
        for i, v in zip(indices, values):
            new[i] = v
        return fn(jax.tree_util.tree_unflatten(tree, new))

    return at


_run.defjvp(_jvp, symbolic_zeros=True)
