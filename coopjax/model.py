"""The closed loop (docs/model.md): two robots on free-floating bases gripping one body.

State layout (20 rows, batch on the last axis): rows 0-17 are nine per-robot quantities, each a
(2, B) block with robot L first, in the order of `ROBOT_STATES`; rows 18 and 19 are the body's
x_o and v_o. Everything is a pure function of (params, state, t).

The robot-level functions (`geometry`, `controller`, `robot_field`) are elementwise: they take
either both robots as (2, B) blocks (with `sign`, as the linear analysis does) or one robot's (B,)
rows (with `robot_params` and a scalar sign, as `vector_field` and the integrators do). The rows
are the fast layout on CPU: (2, B) blocks cost a reshape and a stack per field evaluation, which
split XLA's fusions and made the step 3.5x slower (README, "Measured speed").
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from coopjax import surrogates
from coopjax.errors import InputError
from coopjax.params import Params, per_robot_names
from coopjax.scenarios import Clock, Scenario

ROBOT_STATES = ("x_r", "v_r", "x_v", "v_v", "q_c", "x_f", "v_f", "Z", "Y_e")
BODY_STATES = ("x_o", "v_o")
N_STATE = 2 * len(ROBOT_STATES) + len(BODY_STATES)
STATE_NAMES = tuple(f"{q}_{r}" for q in ROBOT_STATES for r in "LR") + BODY_STATES


def sign(batch_ndim: int, dtype):
    """s_i: +1 for robot L (pushes in +x), -1 for robot R, shaped to broadcast over (2, B)."""
    return jnp.array([1.0, -1.0], dtype).reshape((2,) + (1,) * batch_ndim)


SIGNS = (1.0, -1.0)  # s_i for robot L and robot R, in the robot-row layout


def robot_params(p: Params, i: int) -> Params:
    """Robot i's view of the parameters: its per-robot leaves (B,) and the shared ones."""
    return p.with_leaves(**{n: getattr(p, n)[i] for n in per_robot_names()})


def robots(params):
    """Both robots' views, (robot_params(p, 0), robot_params(p, 1)); a pair already split passes.

    The integration loop splits once, before the time loop: split inside it, reverse mode would
    scatter each stage's parameter cotangents back into (2, B) arrays (44 pads and adds per field
    evaluation, which made the tuner's gradient 2x slower, measured).
    """
    return params if isinstance(params, tuple) else (robot_params(params, 0), robot_params(params, 1))


def split(y):
    """(20, B) -> one dict of (B,) rows per robot, each with the body's x_o and v_o.

    `lax.split` rather than 20 slices: its transpose is one concatenate, where the slices' would be
    20 pads and adds of the whole state per call.
    """
    rows = [r[0] for r in jax.lax.split(y, [1] * y.shape[0], axis=0)]
    body = {"x_o": rows[-2], "v_o": rows[-1]}
    return tuple({**{q: rows[2 * j + i] for j, q in enumerate(ROBOT_STATES)}, **body} for i in range(2))


def join(rates, body) -> jax.Array:
    """Per-robot rate dicts and the body's rates -> (20, B), in `STATE_NAMES` order."""
    return jnp.stack([rates[i][q] for q in ROBOT_STATES for i in range(2)] + [body["x_o"], body["v_o"]])


def unpack(y):
    """(20, B) -> dict of (2, B) per-robot blocks plus (B,) body rows."""
    blocks = y[: 2 * len(ROBOT_STATES)].reshape((len(ROBOT_STATES), 2) + y.shape[1:])
    out = dict(zip(ROBOT_STATES, blocks))
    out["x_o"], out["v_o"] = y[-2], y[-1]
    return out


def pack(d) -> jax.Array:
    robot = jnp.stack([d[q] for q in ROBOT_STATES]).reshape((2 * len(ROBOT_STATES),) + d["x_o"].shape)
    return jnp.concatenate([robot, jnp.stack([d["x_o"], d["v_o"]])])


def init_state(params: Params) -> jax.Array:
    """All states start at 0: positions are displacements from the initial configuration."""
    return jnp.zeros((N_STATE,) + params.batch_shape, params.M_b.dtype)


class Options(NamedTuple):
    """Static modelling choices (not arrays). Changing one retraces."""

    switch: str = "hard"  # "hard" | "smooth" | "blend" | "straight_through"
    contact: str = "unilateral"  # "unilateral" | "bilateral"
    gamma_min: float | None = None  # optional floor on gamma; the paper leaves gamma unclipped


SWITCHES = ("hard", "smooth", "blend", "straight_through")
CONTACTS = ("unilateral", "bilateral")


def check_options(options: Options) -> None:
    if options.switch not in SWITCHES:
        raise InputError(f"unknown switch {options.switch!r}; choose one of: {', '.join(SWITCHES)}", "switch")
    if options.contact not in CONTACTS:
        raise InputError(f"unknown contact {options.contact!r}; choose one of: {', '.join(CONTACTS)}", "contact")
    if options.gamma_min is not None and not (
        isinstance(options.gamma_min, (int, float)) and np.isfinite(options.gamma_min)
    ):
        raise InputError(f"gamma_min is {options.gamma_min!r}: a finite number, or None for no floor", "gamma_min")


class Aux(NamedTuple):
    """Signals at one instant that are not states but that users and metrics want."""

    F: jax.Array  # gripper force on the body, (2, B), N
    w: jax.Array  # swi(F, F_lim), (2, B)
    gamma: jax.Array  # compensation gain (Eq. 8), (2, B)
    x_ref: jax.Array  # reference position, (2, B), m
    v_ref: jax.Array  # augmented reference velocity (Eq. 11), (2, B), m/s


def controller(p: Params, v_ref, a_ref, v_meas, q_c, x_f, v_f, gamma, f_ext, base_coupling):
    """Impedance controller with the virtual foundation in the controller domain (Eq. 4).

    Solves exactly, per robot, the small linear system in (e_c, a_r, a_f):

        err  = v_ref - v_meas - (1 - gamma) beta_H v_f
        e_c  = M_c (a_ref - a_meas - (1 - gamma) beta_H a_f) + R_c err + K_c q_c
        M_f a_f = e_c - R_f v_f - K_f x_f,     M_r a_r = mu_H e_c + f_ext

    `base_coupling` is (1 - alpha_b) mu_H / M_v: how much of the base's reaction the measured
    acceleration picks up (0 with full base compensation or a fixed base).
    Returns (err, e_c, a_r, a_f); err is dq_c/dt.
    """
    g = (1.0 - gamma) * p.beta_H
    err = v_ref - v_meas - g * v_f
    D = p.M_c * a_ref + p.R_c * err + p.K_c * q_c
    h = p.R_f * v_f + p.K_f * x_f
    numerator = D - p.M_c * f_ext / p.M_r + p.M_c * g * h / p.M_f
    denominator = 1.0 + p.M_c * p.mu_H / p.M_r + p.M_c * base_coupling + p.M_c * g / p.M_f
    e_c = numerator / denominator
    a_f = (e_c - h) / p.M_f
    a_r = (p.mu_H * e_c + f_ext) / p.M_r
    return err, e_c, a_r, a_f


def _like(body_row, robot):
    """A body row (B,) against a robot quantity: a (2, B) block or a (B,) row."""
    return body_row[None] if robot.ndim == body_row.ndim + 1 else body_row


def geometry(p: Params, st, s):
    """Gripper compression delta_i, its rate, and the Kelvin-Voigt force K_g delta + R_g delta_dot.

    The Kelvin-Voigt force is linear in the state; the contact force is it, clipped, while in contact.
    """
    x_o, v_o = _like(st["x_o"], st["x_r"]), _like(st["v_o"], st["x_r"])
    delta = p.delta0 + s * (st["x_r"] - x_o)
    delta_dot = s * (st["v_r"] - v_o)
    return delta, delta_dot, p.K_g * delta + p.R_g * delta_dot


def vector_field(params: Params, y: jax.Array, t, scenario: Scenario, options: Options):
    """dy/dt of the full model and the auxiliary signals at (t, y). y is (20, B); t a time or a Clock.
    `params` may also be the pair `robots(params)`, split once outside a time loop.

    Each robot runs on its own (B,) rows; the signals in `Aux` are stacked to (2, B) for users.
    """
    clock = t if isinstance(t, Clock) else Clock.at(t)
    ps = robots(params)  # ps[0] also carries the shared parameters
    commands = scenario.command(ps[0], clock)
    st = split(y)
    F = []
    for i in range(2):
        delta, delta_dot, _ = geometry(ps[i], st[i], SIGNS[i])
        F.append(surrogates.contact_force(ps[i], delta, delta_dot, options))
    rates, auxes = [], []
    for i in range(2):
        r, a = _one_robot_field(ps[i], st[i], SIGNS[i], F[i], commands[i], options)
        rates.append(r)
        auxes.append(a)
    aux = Aux(*(jnp.stack(pair) for pair in zip(*auxes)))
    return join(rates, body_field(ps[0], st[0], F[0], F[1])), aux


def _one_robot_field(p, st, s, F, command, options):
    """One robot's rates and signals under the configured switch."""
    w = surrogates.switch(p, F, options)
    if options.switch != "blend":
        return robot_field(p, st, s, F, w, command, options)
    # Blend: the convex combination of the switch-off and switch-on fields, weighted by the smooth
    # switch. The field is nonlinear in w (gamma sits in the controller's denominator, and a_ref has a
    # (1 - w)^2 term), so substituting a fractional w ("smooth") slides along F = F_lim differently
    # from the hard switch. The convex combination keeps the Filippov sliding motion that the hard
    # model's chatter averages to, as the width k_F goes to 0. The switch-on field is only meaningful
    # for F >= F_lim (far below it gamma would exceed 1 and the controller's denominator can vanish),
    # so within the sigmoid's tail below F_lim it is taken at the surface value of gamma.
    off, aux_off = robot_field(p, st, s, F, 0.0, command, options)
    on, aux_on = robot_field(p, st, s, F, 1.0, command, options, F_gamma=jnp.maximum(F, p.F_lim))
    rates = {q: off[q] + w * (on[q] - off[q]) for q in ROBOT_STATES}
    aux = jax.tree_util.tree_map(lambda a, b: a + w * (b - a), aux_off, aux_on)
    return rates, aux._replace(F=F, w=w)


def _times(w, x):
    """w * x, written out at trace time when w is the number 0 or 1 (the sliding-mode rows), so the
    compiled step does not carry multiplications by a constant 0."""
    if isinstance(w, (int, float)):
        return 0.0 if w == 0 else x if w == 1 else w * x
    return w * x


def robot_field(p: Params, st, s, F, w, command, options: Options, F_gamma=None, F_memory=None, f_env=None):
    """Robot i's nine rates (each (2, B)) once its contact force F and switch value w are known.

    `w` may be an array (the hard or smooth switch) or the number 0 or 1 (the two fields the
    sliding-mode integrator combines). `F_gamma` and `F_memory` are the forces that modulate gamma
    (Eq. 8) and drive the memory Z (Eq. 9); both default to F. The switch-on field of the
    sliding-mode integrator clamps them at F_lim (integration/filippov.py, "What makes it cheap").
    `f_env` is an external force on each tip along +x (the input of the linear analysis; None in runs).
    Returns (rates, Aux); `rates["v_r"]` is the tip acceleration a_r.
    """
    v_cmd, a_cmd, x_ref = command
    off = 1.0 - w
    F_gamma = F if F_gamma is None else F_gamma
    F_memory = F if F_memory is None else F_memory
    # Gain modulation, Eq. 8 and 9 (the -(1-w) rho Z term realises the restart at each switch-on).
    Z = st["Z"]
    gamma = 1.0 - _times(w, p.K_ini + p.K_GP * (F_gamma - p.F_lim) + p.K_GI * Z)
    if options.gamma_min is not None:
        gamma = jnp.maximum(gamma, options.gamma_min)
    dZ = _times(w, F_memory - p.F_lim) - p.tau * Z - _times(off, p.rho * Z)

    # Amnesia recovery, Eq. 10 and 11: only while force control is off.
    Y_e = st["Y_e"]
    dY_e = _times(off, x_ref - st["x_r"]) - p.tau_e * Y_e - _times(w, p.rho * Y_e)
    v_ref = v_cmd + _times(off, p.G_e * Y_e)
    a_ref = a_cmd + _times(off, p.G_e * dY_e)

    v_meas = st["v_r"] - (1.0 - p.alpha_b) * st["v_v"]
    base_coupling = (1.0 - p.alpha_b) * p.mu_H / p.M_v
    f_ext = -s * F if f_env is None else f_env - s * F
    err, e_c, a_r, a_f = controller(
        p, v_ref, a_ref, v_meas, st["q_c"], st["x_f"], st["v_f"], gamma, f_ext, base_coupling
    )
    a_v = -p.mu_H * e_c / p.M_v  # reaction of the actuator on the free-floating base
    rates = dict(x_r=st["v_r"], v_r=a_r, x_v=st["v_v"], v_v=a_v, q_c=err, x_f=st["v_f"], v_f=a_f, Z=dZ, Y_e=dY_e)
    w_array = jnp.full_like(F, w) if isinstance(w, (int, float)) else w
    return rates, Aux(F=F, w=w_array, gamma=jnp.broadcast_to(gamma, F.shape), x_ref=x_ref, v_ref=v_ref)


def body_field(p: Params, st, F_L, F_R):
    """The body's rates: it feels only the two gripper forces (no switch acts on it)."""
    return dict(x_o=st["v_o"], v_o=(F_L - F_R) / p.M_b)


def momentum(params: Params, y: jax.Array) -> jax.Array:
    """Total linear momentum sum_i (M_v v_v + M_r v_r) + M_b v_o; conserved with no external force."""
    st = unpack(y)
    return (params.M_v * st["v_v"] + params.M_r * st["v_r"]).sum(0) + params.M_b * st["v_o"]


# A single robot on a fixed base pushed by a constant environment effort, with gamma frozen:
# the harness of the paper's section 2 (Eq. 4-7). It reuses `controller`, the code the full model runs.


def ground_robot_field(params: Params, y, e_env, alpha):
    """dy/dt for y = (x_r, v_r, q_c, x_f, v_f) of robot L, v_ref = 0, gamma = alpha.

    Parameters are robot L's (index 0). The base is fixed, so the measured velocity is v_r.
    """
    p = robot_params(params, 0)
    x_r, v_r, q_c, x_f, v_f = y
    zero = jnp.zeros_like(v_r)
    err, _, a_r, a_f = controller(p, zero, zero, v_r, q_c, x_f, v_f, alpha, e_env, 0.0)
    return jnp.stack([v_r, a_r, err, v_f, a_f])
