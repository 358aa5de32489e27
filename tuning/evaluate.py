"""The evaluator every tuner shares: a `Query` in, an `Evaluation` out, on the problem's model.

Each kind of evaluation (values, a forward-mode Jacobian, a gradient) and each batch shape is
compiled once, ahead of the first call, and its compile time kept apart from the clock, so that
tuners are compared on the time they spend evaluating. The batch of candidates x masses is split
over every local device inside the compiled program (`coopjax.devices.run`).
"""

from __future__ import annotations

import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from tuning.problem import HOLD_TOLERANCE, Problem, terms
from tuning.tuners import Evaluation, Query


@functools.lru_cache(maxsize=32)
def _function(problem: Problem, derivative, mode, scalar, checkpoint=True):
    """The jitted function of one kind of evaluation: (thetas, masses, base, weights) -> outputs.
    `checkpoint` (the reverse-mode memory policy of `coopjax.simulate`) matters to gradients only."""

    def outputs(thetas, masses, base):
        t = terms(thetas, base, problem, masses)
        m = t.metrics
        return dict(
            f=t.f,
            c=t.c,
            peak=m.peak_grip,
            rms_lag=m.rms_lag,
            min_grip=m.min_grip,
            min_swi=m.min_swi,
            finite=m.finite.astype(thetas.dtype),
        )

    if derivative is None:
        return jax.jit(lambda thetas, masses, base, weights: outputs(thetas, masses, base))

    if derivative == "jacobian":

        def jacobian(thetas, masses, base, weights):
            # The candidates are independent, so one tangent per parameter column gives every
            # candidate's column at once; all n tangents go through one forward pass (vmap).
            n = thetas.shape[1]
            basis = jnp.eye(n, dtype=thetas.dtype)[:, None, :] * jnp.ones_like(thetas)[None]
            out, tangents = jax.vmap(
                lambda v: jax.jvp(lambda th: outputs(th, masses, base), (thetas,), (v,)), out_axes=(None, 0)
            )(basis)
            out["jacobian"] = {k: jnp.moveaxis(tangents[k], 0, -1) for k in ("f", "c", "peak", "rms_lag", "min_swi")}
            return out

        return jax.jit(jacobian)

    def value(th, masses, base, weights):
        t = terms(th, base, problem, masses, checkpoint)
        return scalar(problem, t.f, t.c, weights), t

    def pack(t, L, grad):
        m = t.metrics
        return dict(
            f=t.f,
            c=t.c,
            peak=m.peak_grip,
            rms_lag=m.rms_lag,
            min_grip=m.min_grip,
            min_swi=m.min_swi,
            finite=m.finite,
            value=L,
            gradient=grad,
        )

    if mode == "forward":

        def forward(thetas, masses, base, weights):
            # One tangent per parameter column of every candidate, one after another (`lax.map`):
            # vmapped, these tangents ran 1.8x slower (their working set left the cache).
            n = thetas.shape[1]
            basis = jnp.eye(n, dtype=thetas.dtype)[:, None, :] * jnp.ones_like(thetas)[None]
            L, t = value(thetas, masses, base, weights)
            tangents = jax.lax.map(
                lambda v: jax.jvp(lambda th: value(th, masses, base, weights)[0], (thetas,), (v,))[1], basis
            )
            return pack(t, L, tangents.T)

        return jax.jit(forward)

    def reverse(thetas, masses, base, weights):
        # The candidates are separable (L_c depends on theta_c alone): the gradient of their sum.
        (_, (L, t)), grad = jax.value_and_grad(
            lambda th: (lambda L, t: (L.sum(), (L, t)))(*value(th, masses, base, weights)), has_aux=True
        )(thetas)
        return pack(t, L, grad)

    return jax.jit(reverse)


class Evaluator:
    """Runs queries for one problem and base; counts trajectories and keeps compile time apart."""

    def __init__(self, problem: Problem, base, scalar=None, checkpoint: bool | str = True):
        self.problem, self.base, self.scalar, self.checkpoint = problem, base, scalar, checkpoint
        self.F_lim = float(np.asarray(base.F_lim).min())
        self.compiled: dict = {}
        self.compile_s = 0.0
        self.trajectories = 0

    def _executable(self, query: Query, args):
        key = (query.derivative, query.mode, np.shape(query.thetas), np.shape(query.masses))
        if key not in self.compiled:
            fn = _function(
                self.problem,
                query.derivative,
                query.mode if query.derivative == "gradient" else None,
                self.scalar if query.derivative == "gradient" else None,
                self.checkpoint,
            )
            start = time.perf_counter()
            self.compiled[key] = fn.lower(*args).compile()
            self.compile_s += time.perf_counter() - start
        return self.compiled[key]

    def warm_up(self, query: Query) -> None:
        """Compile for this query's kind and shapes now (not on anyone's clock)."""
        self._executable(query, self._args(query))

    def _args(self, query: Query):
        dtype = jnp.float64
        return (jnp.asarray(query.thetas, dtype), jnp.asarray(query.masses, dtype), self.base, query.weights)

    def __call__(self, query: Query) -> Evaluation:
        args = self._args(query)
        out = jax.device_get(self._executable(query, args)(*args))
        C, M = np.shape(query.thetas)[0], np.shape(query.masses)[0]
        self.trajectories += C * M
        f, c = np.asarray(out["f"]), np.asarray(out["c"]).reshape(C, M)
        # Every run of the candidate did not diverge (`Metrics.finite`), and its objective and constraints are finite.
        valid = np.asarray(out["finite"]).reshape(C, M).all(1) & np.isfinite(f) & np.isfinite(c).all(1)
        min_grip = np.asarray(out["min_grip"]).reshape(C, M)
        holds = valid & (np.nan_to_num(min_grip, nan=-np.inf) >= self.F_lim - HOLD_TOLERANCE).all(1)
        jac = None
        if "jacobian" in out:
            jac = {k: np.asarray(v) for k, v in out["jacobian"].items()}
        return Evaluation(
            f=f,
            c=c,
            peak=np.asarray(out["peak"]).reshape(C, M),
            rms_lag=np.asarray(out["rms_lag"]).reshape(C, M),
            min_grip=min_grip,
            valid=valid,
            holds=holds,
            min_swi=np.asarray(out["min_swi"]).reshape(C, M),
            value=None if "value" not in out else np.asarray(out["value"]),
            gradient=None if "gradient" not in out else np.asarray(out["gradient"]),
            jacobian=jac,
        )
