"""The sliding-mode integrator for the hard switch (SLIDING.md): fixed step, branch-free, batched.

The hard switch makes the field discontinuous on sigma_i = F_i - F_lim = 0. In the carry scenario
both surfaces attract, so the exact solution slides on them (a Filippov sliding mode), and plain RK4
chatters across them and converges only at O(dt). This step reaches the dt -> 0 limit at dt = 1e-3.

"Structure that makes it cheap" (SLIDING.md):
- Each robot's switch w_i enters only its own nine rows, and the body's rows hold no w. So the rate of
  robot i's switching function, sigma_dot_i = K_g delta_dot_i + R_g s_i (a_r,i - a_o), depends on
  w_i alone: one scalar weight per robot.
- sigma is linear in the state while in contact. RK4 keeps linear functionals exactly, so stages
  that all have sigma_dot = 0 keep sigma on the surface to round-off.
- The switch-on field (w = 1) is evaluated with max(F, F_lim) in gamma and dZ/dt (the clamp): gamma
  is unclipped, and just below the surface the controller's denominator can vanish.

"The scheme, per RK4 stage and per robot i": evaluate the rows f0 (w = 0) and f1 (w = 1, clamped),
with switching rates sd0 and sd1, Delta = sd0 - sd1, then
  1. lambda* = clip(sd0 / Delta, 0, 1) if Delta > eps, else H(sd0): the on-surface Filippov weight;
  2. the share theta of the (sub)step of length h spent before reaching the surface, from sigma_n
     at the (sub)step start:
       sigma_n < 0:  theta = clip(-sigma_n / (sd0 h), 0, 1) if sd0 > 0 else 1,  lambda = (1 - theta) lambda*
       sigma_n >= 0: theta = clip(sigma_n / (-sd1 h), 0, 1) if sd1 < 0 else 1,  lambda = theta + (1 - theta) lambda*
  3. robot i's rows are f0 + lambda (f1 - f0); lambda = 0 for a robot out of contact.

"Impacts: split the step at the contact onset": for a robot out of contact (delta <= 0) the contact
time is predicted from delta + delta_dot tau + delta_ddot tau^2 / 2 = 0 (delta_ddot from the
contact-free field). The step is two RK4 substeps: up to the earliest impact with that robot's
contact forced off, then the rest with it forced on (no delta > 0 test). Without an impact the
second substep has zero length, an exact no-op, so the step map stays continuous. The force just
after the first substep is returned for the peak metric (MODEL.md section 7).

Stage times differ per sample within the substeps; commands take them through `Clock.advance`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from coopjax import model
from coopjax.scenarios import Clock

EPS = 1e-9  # N/s: below this the two switching rates are taken as equal (SLIDING.md, step 1)
# Rows that differ between the w = 0 and w = 1 fields; the kinematic rows (x_r, x_v, x_f) do not.
SWITCHED = ("v_r", "v_v", "q_c", "v_f", "Z", "Y_e")


class Contact(NamedTuple):
    """Per-robot contact override for a substep, (2, B) booleans: forced on, forced off."""

    on: jax.Array
    off: jax.Array


class Fields(NamedTuple):
    """Everything one evaluation point gives, before the Filippov weight is chosen."""

    in_contact: jax.Array  # (2, B) bool
    F: jax.Array  # (2, B) contact force, N
    sigma: jax.Array  # (2, B) K_g delta + R_g delta_dot - F_lim while in contact, -F_lim otherwise, N
    sd0: jax.Array  # (2, B) switching rate of the w = 0 field, N/s
    sd1: jax.Array  # (2, B) switching rate of the w = 1 field, N/s
    off: dict  # rows of the w = 0 field
    on: dict  # rows of the w = 1 field (clamped)
    body: dict  # the body's rows
    aux_off: model.Aux
    aux_on: model.Aux


def _broadcast(x, like):
    """A per-sample (B,) value against a (2, B) block or a (B,) row, without rank promotion."""
    return x[None] if like.ndim == x.ndim + 1 else x


def _axpy(st, c, k):
    """st + c k over the state dict; c is per sample (B,)."""
    return {q: st[q] + _broadcast(c, st[q]) * k[q] for q in st}


def fields(p, st, s, clock: Clock, contact: Contact | None, scenario, options) -> Fields:
    """The w = 0 and w = 1 fields at one point, with the contact and the commands they share."""
    delta, delta_dot, kelvin = model.geometry(p, st, s)
    if options.contact == "bilateral":
        in_contact = jnp.ones_like(delta, bool)
        F = kelvin
    else:
        in_contact = delta > 0.0
        if contact is not None:
            in_contact = contact.on | (~contact.off & in_contact)
        F = jnp.where(in_contact, jnp.maximum(kelvin, 0.0), 0.0)
    command = scenario.command(p, clock)
    body = model.body_field(p, st, F)
    off, aux_off = model.robot_field(p, st, s, F, 0.0, command, options)
    clamped = jnp.maximum(F, p.F_lim)  # SLIDING.md: the clamp of the w = 1 field
    on, aux_on = model.robot_field(p, st, s, F, 1.0, command, options, F_gamma=clamped, F_memory=clamped)
    a_o = body["v_o"][None]
    # d/dt (K_g delta + R_g delta_dot) for each field: the body's rows hold no w.
    sd0 = p.K_g * delta_dot + p.R_g * s * (off["v_r"] - a_o)
    sd1 = p.K_g * delta_dot + p.R_g * s * (on["v_r"] - a_o)
    sigma = jnp.where(in_contact, kelvin, 0.0) - p.F_lim
    return Fields(in_contact, F, sigma, sd0, sd1, off, on, body, aux_off, aux_on)


def weight(f: Fields, sigma_n, h):
    """lambda per robot (2, B): SLIDING.md "The scheme", steps 1 and 2, at one stage.

    sigma_n is sigma at the (sub)step start; h the (sub)step length, per sample (B,).
    Divisions are guarded so that a branch that is not taken cannot put a NaN in a gradient.
    """
    sd0, sd1 = f.sd0, f.sd1
    h = _broadcast(h, sd0)
    delta = sd0 - sd1
    sliding = delta > EPS
    lam_star = jnp.where(sliding, jnp.clip(sd0 / jnp.where(sliding, delta, 1.0), 0.0, 1.0), (sd0 >= 0.0).astype(sd0.dtype))

    approach_from_below = sd0 * h > 0.0
    theta_below = jnp.where(
        approach_from_below, jnp.clip(-sigma_n / jnp.where(approach_from_below, sd0 * h, 1.0), 0.0, 1.0), 1.0)
    approach_from_above = -sd1 * h > 0.0
    theta_above = jnp.where(
        approach_from_above, jnp.clip(sigma_n / jnp.where(approach_from_above, -sd1 * h, 1.0), 0.0, 1.0), 1.0)
    lam = jnp.where(sigma_n < 0.0, (1.0 - theta_below) * lam_star, theta_above + (1.0 - theta_above) * lam_star)
    return jnp.where(f.in_contact, lam, 0.0)


def combine(f: Fields, lam):
    """Robot rows f0 + lambda (f1 - f0) (SLIDING.md step 3), with the body's rows."""
    rates = dict(f.off)
    for q in SWITCHED:
        rates[q] = f.off[q] + lam * (f.on[q] - f.off[q])
    rates.update(f.body)
    return rates


def aux(f: Fields, lam) -> model.Aux:
    """Signals at a point: w is the Filippov weight (the share of time the chattering switch is on),
    gamma and v_ref the matching time averages."""
    blend = lambda a, b: a + lam * (b - a)
    return model.Aux(F=f.F, w=lam, gamma=blend(f.aux_off.gamma, f.aux_on.gamma), x_ref=f.aux_off.x_ref,
                     v_ref=blend(f.aux_off.v_ref, f.aux_on.v_ref))


# RK4's tableau for stages 2-4: the stage point y + A h k_prev at t + A h, and the weight B of its rates.
RK4_A = (0.5, 0.5, 1.0)
RK4_B = (2.0, 2.0, 1.0)  # over 6


def substep(p, st, s, clock: Clock, h, contact, scenario, options):
    """RK4 over a (sub)step of per-sample length h (B,), each stage with its Filippov weight.

    Stages 2-4 run as a `lax.scan` over the tableau: one stage body for XLA to compile instead of a
    chain of them. Unrolled, the differentiated step took 28 s to compile (measured), growing faster
    than the chain's length. Returns the new state and the fields at the first stage.
    """
    f1 = fields(p, st, s, clock, contact, scenario, options)
    sigma_n = f1.sigma  # every stage's theta uses sigma at the substep start (SLIDING.md step 2)
    k1 = combine(f1, weight(f1, sigma_n, h))

    def stage(carry, tableau):
        k_prev, total = carry
        a, b = tableau
        f = fields(p, _axpy(st, a * h, k_prev), s, clock.advance(a * h), contact, scenario, options)
        k = combine(f, weight(f, sigma_n, h))
        return (k, {q: total[q] + b * k[q] for q in total}), None

    tableau = (jnp.asarray(RK4_A, h.dtype), jnp.asarray(RK4_B, h.dtype))
    (_, total), _ = jax.lax.scan(stage, (k1, k1), tableau)
    return _axpy(st, h / 6, total), f1


def impact_fraction(p, st, s, a_r_off, a_o, dt):
    """theta_c (B,) and the robots that hit (2, B): SLIDING.md, "Impacts".

    The contact time solves delta + delta_dot tau + delta_ddot tau^2 / 2 = 0, written without
    cancellation as tau = -2 delta / (delta_dot + sqrt(delta_dot^2 - 2 delta_ddot delta)). For a robot
    out of contact the step-start switch-off field is the contact-free one, so delta_ddot comes from
    its tip acceleration a_r_off and the body's a_o.
    """
    delta, delta_dot, _ = model.geometry(p, st, s)
    delta_ddot = s * (a_r_off - a_o[None])
    disc = delta_dot**2 - 2.0 * delta_ddot * delta
    real = (delta <= 0.0) & (disc > 0.0)
    denominator = delta_dot + jnp.sqrt(jnp.where(real, disc, 1.0))
    hits = real & (denominator > 0.0)
    tau = -2.0 * delta / jnp.where(hits, denominator, 1.0)
    hits = hits & (tau <= dt)
    fraction = jnp.where(hits, tau / dt, 1.0)
    theta_c = fraction.min(0)
    first = hits & (fraction <= theta_c[None])  # ties: both robots hit at once (a symmetric squeeze)
    return theta_c, first


def step(params, y, t, dt, scenario, options):
    """y(t) -> (y(t + dt), F and x_ref at t, force just after a located impact): the loop's step protocol."""
    p = params
    st = model.unpack(y)
    s = model.sign(y.ndim - 1, y.dtype)
    clock = Clock.at(t)
    # At the step start the metrics need only F and x_ref, and the impact prediction only the
    # switch-off field: the switch-on field and the weight are left to the stages.
    delta, delta_dot, kelvin = model.geometry(p, st, s)
    F = kelvin if options.contact == "bilateral" else jnp.where(delta > 0.0, jnp.maximum(kelvin, 0.0), 0.0)
    command = scenario.command(p, clock)
    if options.contact == "bilateral":  # no impacts: one RK4 step
        h = jnp.full(y.shape[1:], dt, y.dtype)
        st_new, _ = substep(p, st, s, clock, h, None, scenario, options)
        return model.pack(st_new), F, command[2], None
    off, _ = model.robot_field(p, st, s, F, 0.0, command, options)
    a_o = model.body_field(p, st, F)["v_o"]

    theta_c, hits = impact_fraction(p, st, s, off["v_r"], a_o, dt)
    h1 = theta_c * dt
    h2 = dt - h1  # exactly 0 without an impact
    no = jnp.zeros_like(hits)

    # Up to the impact, the hitting robot's contact is off; after it, on. Both substeps run as one
    # `lax.scan` body, so XLA compiles the stage once (see `substep`).
    def part(st, xs):
        offset, h, forced_on, forced_off = xs
        st_new, start = substep(p, st, s, clock.advance(offset), h, Contact(forced_on, forced_off), scenario, options)
        return st_new, start.F

    xs = (jnp.stack([jnp.zeros_like(h1), h1]), jnp.stack([h1, h2]), jnp.stack([no, hits]), jnp.stack([hits, no]))
    st_new, start_F = jax.lax.scan(part, st, xs)
    return model.pack(st_new), F, command[2], start_F[1]  # F just after the impact: the 2nd substep's start


def observe(params, y, t, dt, scenario, options) -> model.Aux:
    """The signals recorded at (t, y): contact force, Filippov weight, time-averaged gamma."""
    st = model.unpack(y)
    f = fields(params, st, model.sign(y.ndim - 1, y.dtype), Clock.at(t), None, scenario, options)
    return aux(f, weight(f, f.sigma, jnp.full(y.shape[1:], dt, y.dtype)))
