"""The switch `swi` (Eq. 8) and the gripper contact, hard and smooth (docs/model.md).

The hard forms are the reference model. The smooth forms have explicit widths (k_F, k_c in N,
eps_delta in m, all parameters so they can be annealed under jit) and tend to the hard forms as the
widths go to 0. `straight_through` runs the hard form forward and differentiates the smooth one.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def _straight_through(hard, smooth):
    return smooth + jax.lax.stop_gradient(hard - smooth)


def switch(p, F, options):
    """swi(F, F_lim): 1 while force control is on (F >= F_lim), else 0."""
    if options.switch == "hard":
        return (F >= p.F_lim).astype(F.dtype)
    smooth = jax.nn.sigmoid((F - p.F_lim) / p.k_F)
    if options.switch in ("smooth", "blend"):
        return smooth
    return _straight_through((F >= p.F_lim).astype(F.dtype), smooth)


def contact_force(p, delta, delta_dot, options):
    """Gripper force on the body from compression delta and its rate (positive pushes)."""
    kelvin = p.K_g * delta + p.R_g * delta_dot
    if options.contact == "bilateral":
        return kelvin
    # Unilateral: it can push, not pull, and only while the tip touches the body.
    hard = jnp.where(delta > 0.0, jnp.maximum(kelvin, 0.0), 0.0)
    if options.switch == "hard":
        return hard
    k_c, eps_delta = p.k_c, p.eps_delta  # shared widths: (B,) broadcasts over a (2, B) block too
    smooth = k_c * jax.nn.softplus(kelvin / k_c) * jax.nn.sigmoid(delta / eps_delta)
    if options.switch in ("smooth", "blend"):
        return smooth
    return _straight_through(hard, smooth)
