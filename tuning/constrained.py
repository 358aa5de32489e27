"""An augmented Lagrangian on top of optax, for inequality constraints g(x) <= 0.

optax has no constrained optimiser. This is the Powell-Hestenes-Rockafellar form: for multipliers
lambda >= 0 and a penalty rho > 0,

    L(x; lambda, rho) = f(x) + 1 / (2 rho) * sum_i (max(0, lambda_i + rho g_i(x))^2 - lambda_i^2),

minimised over x by any optax optimiser for a few steps; then `update` moves the multipliers,

    lambda_i <- max(0, lambda_i + rho g_i(x)),

and multiplies rho by `growth` when the worst violation did not shrink by `shrink` since the last
update. A feasible x with g_i < 0 adds nothing; an active constraint adds lambda_i g_i. Batched over
any leading axes (independent problems side by side, e.g. the tuner's K starts).
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import optax


class Multipliers(NamedTuple):
    lam: jax.Array  # (..., m), >= 0
    rho: jax.Array  # (...,), > 0
    violation: jax.Array  # (...,): worst max(0, g) at the last update (inf before the first)


def init(shape, rho: float = 1.0, dtype=jnp.float64) -> Multipliers:
    """Multipliers for constraints of `shape` = (..., m), with zero lambdas."""
    return Multipliers(jnp.zeros(shape, dtype), jnp.full(shape[:-1], rho, dtype), jnp.full(shape[:-1], jnp.inf, dtype))


def lagrangian(f, g, mult: Multipliers):
    """The augmented Lagrangian of objective values f (...) and constraint values g (..., m)."""
    rho = mult.rho[..., None]
    shifted = jnp.maximum(0.0, mult.lam + rho * g)
    return f + ((shifted**2 - mult.lam**2) / (2.0 * rho)).sum(-1)


def update(mult: Multipliers, g, growth: float = 10.0, shrink: float = 0.25, rho_max: float = 1e6) -> Multipliers:
    """The multiplier step, and a larger penalty where the violation did not fall fast enough."""
    lam = jnp.maximum(0.0, mult.lam + mult.rho[..., None] * g)
    violation = jnp.maximum(g, 0.0).max(-1)
    slow = violation > shrink * mult.violation
    rho = jnp.where(slow & (violation > 0), jnp.minimum(mult.rho * growth, rho_max), mult.rho)
    return Multipliers(lam, rho, violation)


def solve(
    fun: Callable, x0, optimizer: optax.GradientTransformation, outer: int = 20, inner: int = 100, rho: float = 1.0
) -> tuple[jax.Array, Multipliers]:
    """Minimise f subject to g <= 0, where fun(x) -> (f, g) with g of shape (m,). For small problems.

    Each outer iteration runs `inner` optimiser steps on L, then updates the multipliers.
    """
    x0 = jnp.asarray(x0)
    f0, g0 = fun(x0)
    mult = init(jnp.shape(g0), rho, x0.dtype)

    def loss(x, mult):
        f, g = fun(x)
        return lagrangian(f, g, mult)

    @jax.jit
    def outer_step(carry, _):
        x, state, mult = carry

        def inner_step(carry, _):
            x, state = carry
            grad = jax.grad(loss)(x, mult)
            updates, state = optimizer.update(grad, state, x)
            return (optax.apply_updates(x, updates), state), None

        (x, state), _ = jax.lax.scan(inner_step, (x, state), None, length=inner)
        return (x, state, update(mult, fun(x)[1])), None

    (x, _, mult), _ = jax.lax.scan(outer_step, (x0, optimizer.init(x0), mult), None, length=outer)
    return x, mult
