"""Is a fixed RK4 step stable for this loop? An estimate from the linearisation.

The loop is linearised (`jax.jacfwd` of the vector field, bilateral contact) at the two operating
points every gripping run visits: at rest before contact (switch off, gamma = 1) and at switch-on
(F = F_lim on both grippers, just above it: w = 1). RK4 is stable for a mode lambda when
|R(lambda dt)| <= 1 with R(z) = 1 + z + z^2/2 + z^3/6 + z^4/24.

The sliding-mode integrator evaluates exactly these two fields (w = 0, and w = 1 with the clamp,
which is the hard field for F >= F_lim) and runs RK4 stages over substeps no longer than dt, so the
same check covers it. Its stages blend the two with a state-dependent weight; a blend with the weight
frozen is not a meaningful operating point (at K_GP = 5 the frozen half-and-half blend has a slowly
growing mode, +0.04 1/s, that the state-dependent weight does not have), so it is not checked.

This is an estimate either way: the hard switch adds nonlinear effects that no linearisation sees
(caught by the per-sample divergence flag), and a run may never dwell where the fastest linearised
mode lives (at K_GP = 5 the carry ran finite at 4x the limit, with either integrator).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from coopjax import devices, model, scenarios
from coopjax.errors import InputError
from coopjax.status import Status
from coopjax.integration import INTEGRATORS, max_stable_dt, rk4_amplification
from coopjax.params import Params, as_batched
from coopjax.traced import is_traced

MIN_PRACTICAL_DT = 1e-9  # s: a loop that needs a finer step than this has a parameter wrong
CHUNK = 256  # samples per call of the linearisation (one program for every batch size)
ULPS_ABOVE_F_LIM = 64  # the switch-on operating point's force, in units of round-off above F_lim


def _jacobians(params: Params, scenario_name: str, options) -> jax.Array:
    scenario = scenarios.get(scenario_name)
    options = options._replace(contact="bilateral", switch="hard")

    def jacobian(p, F_op):
        # The operating force comes from a pre-compression delta0 = F_op / K_g.
        p = p.with_leaves(delta0=F_op / p.K_g)
        f = lambda y: model.vector_field(p, y[:, None], 0.0, scenario, options)[0][:, 0]
        return jax.jacfwd(f)(jnp.zeros(model.N_STATE, p.M_b.dtype))

    def per_sample(p):
        p = jax.tree_util.tree_map(lambda x: x[..., None], p)
        # Switch-on a few units of round-off above F_lim, on the switch-on field's side of the kink
        # (w = 1, the clamp max(F, F_lim) passing F through), as `analysis.linearize(..., "limit")`
        # takes it. At F_lim itself, the round-off of K_g (F_lim / K_g) put each sample on either
        # side, or on it: the limit moved up to 20x between float32 and float64 near Table 1.
        above = p.F_lim + ULPS_ABOVE_F_LIM * jnp.finfo(p.F_lim.dtype).eps * jnp.abs(p.F_lim)
        return jnp.stack([jacobian(p, jnp.zeros_like(p.F_lim)), jacobian(p, above)])

    in_axes = jax.tree_util.tree_map(lambda x: x.ndim - 1, params)
    return jax.vmap(per_sample, in_axes=(in_axes,))(params)


_jacobians_jit = jax.jit(_jacobians, static_argnums=(1, 2))


def fastest_modes(params: Params, config) -> np.ndarray:
    """Eigenvalues (1/s) of the linearised loop, shape (B, 2 operating points, 20)."""
    batched, _ = as_batched(params)
    size = batched.batch_shape[-1]
    # In chunks of `CHUNK` (the last padded by repeating its last sample): one compiled program
    # serves every batch size, where each new size compiled its own (1 to 2 s each).
    leaves, tree = jax.tree_util.tree_flatten(batched)
    leaves = devices.pad_batch([np.asarray(x, np.float64) for x in leaves], -size % CHUNK, np)
    chunks = []
    with jax.enable_x64(True):  # float64 whatever the run uses: the limit must not depend on it
        for s in range(0, size, CHUNK):
            chunk = jax.tree_util.tree_unflatten(tree, [x[..., s : s + CHUNK] for x in leaves])
            chunks.append(np.asarray(_jacobians_jit(chunk, config.scenario, config.options)))
    return np.linalg.eigvals(np.concatenate(chunks)[:size])


def stable_dt(params: Params, config) -> tuple[np.ndarray, np.ndarray]:
    """Per sample: the largest stable step of the configured integrator, and the largest growth rate."""
    eig = fastest_modes(params, config)
    return INTEGRATORS[config.method].stable_dt(eig), growing_mode(eig)


def growing_mode(eigenvalues):
    """Per sample, the largest growth rate Re lambda (1/s) of the linearised loop, beyond round-off.
    NumPy or (traced) JAX eigenvalues."""
    xp = jnp if isinstance(eigenvalues, jax.Array) else np
    lam = eigenvalues.reshape(eigenvalues.shape[0], -1)
    scale = xp.abs(lam).max(axis=1)
    growth = lam.real.max(axis=1)
    return xp.where(growth > 1e-9 * scale + 1e-9, growth, 0.0)


def step_status(params: Params, config) -> jax.Array:
    """Per sample (traceable: under jit, vmap and differentiation), `Status.UNSTABLE_LOOP` where the
    loop itself is unstable, `STEP_BEYOND_LIMIT` where config.dt is beyond the integrator's
    stability limit, else `OK`. The linearisation is traced (its inputs without derivatives), and so
    are the eigenvalues, in float64 whatever the run uses, as `check_step` takes them: no host
    callback, so the program that contains it can be kept in JAX's persistent compilation cache (a
    program with a callback never is)."""
    batched, _ = as_batched(jax.tree_util.tree_map(jax.lax.stop_gradient, params))
    J = _jacobians(batched, config.scenario, config.options)
    with jax.enable_x64(True):
        eig = jnp.linalg.eigvals(J.astype(jnp.float64).reshape((-1,) + J.shape[-3:]))
        unstable = growing_mode(eig) > 0
        beyond = config.dt > INTEGRATORS[config.method].stable_dt(eig)
    code = jnp.where(unstable, Status.UNSTABLE_LOOP, jnp.where(beyond, Status.STEP_BEYOND_LIMIT, Status.OK))
    return code.astype(jnp.int32).reshape(params.batch_shape)


def beyond_limit(params: Params, config) -> jax.Array:
    """Per sample, whether the loop is unstable or config.dt beyond its limit (`step_status`)."""
    return step_status(params, config) != Status.OK


def check_step(params: Params, config) -> None:
    """Raise InputError if config.dt is beyond the integrator's stability limit for any sample."""
    if is_traced(params):
        return
    eig = fastest_modes(params, config)
    growth = growing_mode(eig)
    where = lambda i: f" (sample {i})" if params.batch_shape else ""
    if (growth > 0).any():
        worst = int(np.argmax(growth))
        raise InputError(
            f"these parameters make the loop unstable{where(worst)}: its linearisation has a mode growing at "
            f"{growth[worst]:.3g} 1/s, so no step size helps; check the signs and sizes of the gains "
            "(e.g. K_GP, F_lim, masses)",
            "params",
        )
    limit = INTEGRATORS[config.method].stable_dt(eig)
    worst = int(np.argmin(limit))
    if limit[worst] < MIN_PRACTICAL_DT:
        raise InputError(
            f"these parameters make the loop extremely stiff{where(worst)}: its fastest linearised mode is "
            f"{np.abs(eig[worst]).max():.3g} 1/s, which a fixed step resolves only below {limit[worst]:.3g} s; "
            "check the parameters (a tiny mass or a huge gain?)",
            "params",
        )
    if config.dt > limit[worst]:
        fastest = np.abs(eig[worst]).max()
        raise InputError(
            f"dt = {config.dt:g} s is too large for {config.method} on this loop{where(worst)}: its fastest linearised "
            f"mode is {fastest:.3g} 1/s, so its stages are stable only for dt <= {limit[worst]:.3g} s; "
            f"use dt <= {limit[worst] / 4:.2g} s for accuracy",
            "dt",
        )


__all__ = ["check_step", "fastest_modes", "growing_mode", "max_stable_dt", "rk4_amplification", "stable_dt"]
