"""Is a fixed RK4 step stable for this loop? An estimate from the linearisation.

The loop is linearised (`jax.jacfwd` of the vector field, bilateral contact) at the two operating
points every gripping run visits: at rest before contact (switch off, gamma = 1) and at switch-on
(F = F_lim on both grippers, w = 1). RK4 is stable for a mode lambda when |R(lambda dt)| <= 1 with
R(z) = 1 + z + z^2/2 + z^3/6 + z^4/24.

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

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from coopjax import model
from coopjax.params import Params, as_batched, _is_tracer
from coopjax.scenarios import get_scenario


def rk4_amplification(z):
    return np.abs(1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24)


def _jacobians(params: Params, scenario_name: str, options) -> jax.Array:
    scenario = get_scenario(scenario_name)
    options = options._replace(contact="bilateral", switch="hard")

    def jacobian(p, F_op):
        # The operating force comes from a pre-compression delta0 = F_op / K_g.
        p = dataclasses.replace(p, delta0=F_op / p.K_g)
        f = lambda y: model.vector_field(p, y[:, None], 0.0, scenario, options)[0][:, 0]
        return jax.jacfwd(f)(jnp.zeros(model.N_STATE, p.M_b.dtype))

    def per_sample(p):
        p = jax.tree_util.tree_map(lambda x: x[..., None], p)
        return jnp.stack([jacobian(p, jnp.zeros_like(p.F_lim)), jacobian(p, p.F_lim)])

    in_axes = jax.tree_util.tree_map(lambda x: x.ndim - 1, params)
    return jax.vmap(per_sample, in_axes=(in_axes,))(params)


_jacobians_jit = jax.jit(_jacobians, static_argnums=(1, 2))


def fastest_modes(params: Params, config) -> np.ndarray:
    """Eigenvalues (1/s) of the linearised loop, shape (B, 2 operating points, 20)."""
    batched, _ = as_batched(params)
    J = _jacobians_jit(batched, config.scenario, config.options)
    return np.linalg.eigvals(np.asarray(J, np.float64))


def max_stable_dt(eigenvalues: np.ndarray) -> np.ndarray:
    """Largest dt with every mode inside RK4's stability region, per sample (bisection)."""
    lam = eigenvalues.reshape(eigenvalues.shape[0], -1)
    lam = lam[:, :, None]
    lo = np.zeros((lam.shape[0], 1))
    hi = np.full_like(lo, 10.0)
    for _ in range(60):
        mid = (lo + hi) / 2
        ok = (rk4_amplification(lam * mid[:, None]) <= 1 + 1e-9).all(axis=1)
        lo = np.where(ok, mid, lo)
        hi = np.where(ok, hi, mid)
    return lo[:, 0]


def check_step(params: Params, config) -> None:
    """Raise ValueError if config.dt is beyond RK4's stability limit for any sample."""
    if any(_is_tracer(x) for x in jax.tree_util.tree_leaves(params)):
        return
    eig = fastest_modes(params, config)
    limit = max_stable_dt(eig)
    worst = int(np.argmin(limit))
    if config.dt > limit[worst]:
        fastest = np.abs(eig[worst]).max()
        where = f" (sample {worst})" if params.batch_shape else ""
        raise ValueError(
            f"dt = {config.dt:g} s is too large for {config.method} on this loop{where}: its fastest linearised "
            f"mode is {fastest:.3g} 1/s, so its RK4 stages are stable only for dt <= {limit[worst]:.3g} s; "
            f"use dt <= {limit[worst] / 4:.2g} s for accuracy"
        )
