"""The sliding-mode integrator for the hard switch (docs/model.md, "The sliding-mode step"): fixed step, branch-free, batched.

The hard switch makes the field discontinuous on sigma_i = F_i - F_lim = 0. In the carry scenario
both surfaces attract, so the exact solution slides on them (a Filippov sliding mode), and plain RK4
chatters across them and converges only at O(dt). This step reaches the dt -> 0 limit at dt = 1e-3.

What makes it cheap:
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
after the first substep is returned for the peak metric (docs/model.md, "Metrics").

Stage times differ per sample within the substeps; commands take them through `Clock.advance`.

Layout: the state is a `Rows` pytree, one dict of (B,) rows per robot and the body's rows, and each
robot's fields are evaluated on its own rows (model.py, module docstring: the fast layout).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from coopjax import model
from coopjax.integration.base import Integrator, register
from coopjax.scenarios import Clock

EPS = 1e-9  # N/s: below this the two switching rates are taken as equal (the on-surface weight, step 1 below)
# Rows that differ between the w = 0 and w = 1 fields; the kinematic rows (x_r, x_v, x_f) do not.
SWITCHED = ("v_r", "v_v", "q_c", "v_f", "Z", "Y_e")


class Rows(NamedTuple):
    """The state as rows: robot L's and robot R's nine (B,) rows, and the body's x_o, v_o."""

    robots: tuple
    body: dict

    @classmethod
    def of(cls, y) -> "Rows":
        L, R = model.split(y)
        strip = lambda st: {q: st[q] for q in model.ROBOT_STATES}
        return cls((strip(L), strip(R)), {"x_o": L["x_o"], "v_o": L["v_o"]})

    def robot(self, i):
        """Robot i's rows with the body's, as `model.geometry` and `model.robot_field` take them."""
        return {**self.robots[i], **self.body}

    def array(self) -> jax.Array:
        return model.join(self.robots, self.body)


class Contact(NamedTuple):
    """Per-robot contact override for a substep, each a pair of (B,) booleans (L, R)."""

    on: tuple
    off: tuple


class Fields(NamedTuple):
    """Everything one evaluation point gives for one robot, before its Filippov weight is chosen."""

    in_contact: jax.Array  # (B,) bool
    F: jax.Array  # (B,) contact force, N
    sigma: jax.Array  # (B,) K_g delta + R_g delta_dot - F_lim while in contact, -F_lim otherwise, N
    sd0: jax.Array  # (B,) switching rate of the w = 0 field, N/s
    sd1: jax.Array  # (B,) switching rate of the w = 1 field, N/s
    off: dict  # rows of the w = 0 field
    on: dict  # rows of the w = 1 field (clamped)
    aux_off: model.Aux
    aux_on: model.Aux


def _contacts(ps, rows: Rows, options, contact: Contact | None = None):
    """Per robot (in_contact, F, kelvin, delta, delta_dot), with the substep's override if any."""
    out = []
    for i in range(2):
        delta, delta_dot, kelvin = model.geometry(ps[i], rows.robot(i), model.SIGNS[i])
        if options.contact == "bilateral":
            out.append((jnp.ones_like(delta, bool), kelvin, kelvin, delta, delta_dot))
            continue
        in_contact = delta > 0.0
        if contact is not None:
            in_contact = contact.on[i] | (~contact.off[i] & in_contact)
        out.append((in_contact, jnp.where(in_contact, jnp.maximum(kelvin, 0.0), 0.0), kelvin, delta, delta_dot))
    return out


def fields(ps, rows: Rows, clock: Clock, contact: Contact | None, scenario, options):
    """Both robots' w = 0 and w = 1 fields at one point (a pair of `Fields`) and the body's rates.
    `ps` is `model.robots(params)`; ps[0] also carries the shared parameters.

    The contact forces come first: the body's acceleration needs both, and neither depends on w.
    """
    commands = scenario.command(ps[0], clock)
    touch = _contacts(ps, rows, options, contact)
    body = model.body_field(ps[0], rows.body, touch[0][1], touch[1][1])
    out = []
    for i in range(2):
        p, st, s = ps[i], rows.robot(i), model.SIGNS[i]
        in_contact, F, kelvin, _, delta_dot = touch[i]
        off, aux_off = model.robot_field(p, st, s, F, 0.0, commands[i], options)
        clamped = jnp.maximum(F, p.F_lim)  # the clamp of the w = 1 field (module docstring)
        on, aux_on = model.robot_field(p, st, s, F, 1.0, commands[i], options, F_gamma=clamped, F_memory=clamped)
        # d/dt (K_g delta + R_g delta_dot) for each field: the body's rows hold no w.
        sd0 = p.K_g * delta_dot + p.R_g * s * (off["v_r"] - body["v_o"])
        sd1 = p.K_g * delta_dot + p.R_g * s * (on["v_r"] - body["v_o"])
        sigma = jnp.where(in_contact, kelvin, 0.0) - p.F_lim
        out.append(Fields(in_contact, F, sigma, sd0, sd1, off, on, aux_off, aux_on))
    return tuple(out), body


def weight(f: Fields, sigma_n, h):
    """lambda of one robot (B,): steps 1 and 2 of the scheme (module docstring), at one stage.

    sigma_n is sigma at the (sub)step start; h the (sub)step length, per sample (B,).
    Divisions are guarded so that a branch that is not taken cannot put a NaN in a gradient.
    """
    sd0, sd1 = f.sd0, f.sd1
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
    """One robot's rows f0 + lambda (f1 - f0) (step 3 of the scheme)."""
    rates = dict(f.off)
    for q in SWITCHED:
        rates[q] = f.off[q] + lam * (f.on[q] - f.off[q])
    return rates


def aux(f: Fields, lam) -> model.Aux:
    """Signals at a point: w is the Filippov weight (the share of time the chattering switch is on),
    gamma and v_ref the matching time averages."""
    blend = lambda a, b: a + lam * (b - a)
    return model.Aux(F=f.F, w=lam, gamma=blend(f.aux_off.gamma, f.aux_on.gamma), x_ref=f.aux_off.x_ref,
                     v_ref=blend(f.aux_off.v_ref, f.aux_on.v_ref))


def _rates(fs, body, sigma_n, h) -> Rows:
    return Rows(tuple(combine(f, weight(f, s_n, h)) for f, s_n in zip(fs, sigma_n)), body)


def _axpy(rows: Rows, c, k: Rows) -> Rows:
    """rows + c k; c is per sample (B,)."""
    return jax.tree_util.tree_map(lambda a, b: a + c * b, rows, k)


# RK4's tableau: stage j is evaluated at y + A_j h k_{j-1}, t + A_j h, and weighted B_j / 6.
RK4_A = (0.0, 0.5, 0.5, 1.0)
RK4_B = (1.0, 2.0, 2.0, 1.0)


def substep(ps, rows: Rows, clock: Clock, h, contact, scenario, options):
    """RK4 over a (sub)step of per-sample length h (B,), each stage with its Filippov weights.

    The four stages run as a `lax.scan` over the tableau (the first at A = 0, from k = 0): one
    stage body for XLA to compile instead of a chain of them. Unrolled, the differentiated step took
    28 s to compile (measured), growing faster than the chain's length, and the forward step ran no
    faster. Returns the new state and both robots' contact forces at the first stage.
    """
    # Every stage's theta uses sigma at the substep start (step 2 of the scheme): the contact alone.
    sigma_n = tuple(jnp.where(c[0], c[2], 0.0) - p.F_lim for c, p in zip(_contacts(ps, rows, options, contact), ps))

    def stage(carry, tableau):
        k_prev, total = carry
        a, b = tableau
        fs, body = fields(ps, _axpy(rows, a * h, k_prev), clock.advance(a * h), contact, scenario, options)
        k = _rates(fs, body, sigma_n, h)
        return (k, jax.tree_util.tree_map(lambda x, y: x + b * y, total, k)), (fs[0].F, fs[1].F)

    tableau = (jnp.asarray(RK4_A, h.dtype), jnp.asarray(RK4_B, h.dtype))
    # 0 x rows rather than zeros: under jvp and vmap the stage scan's carry then has its tangents and
    # batch axes from the start, and the scan is traced once instead of until they settle.
    zero = jax.tree_util.tree_map(lambda x: 0.0 * x, rows)
    (_, total), F = jax.lax.scan(stage, (zero, zero), tableau)
    return _axpy(rows, h / 6, total), (F[0][0], F[1][0])


def impact_fraction(p, st, s, a_r_off, a_o, dt):
    """One robot's share of the step before its contact onset (1 if none), and whether it hits.

    The contact time solves delta + delta_dot tau + delta_ddot tau^2 / 2 = 0, written without
    cancellation as tau = -2 delta / (delta_dot + sqrt(delta_dot^2 - 2 delta_ddot delta)). For a robot
    out of contact the step-start switch-off field is the contact-free one, so delta_ddot comes from
    its tip acceleration a_r_off and the body's a_o. See "Impacts" in the module docstring.
    """
    delta, delta_dot, _ = model.geometry(p, st, s)
    delta_ddot = s * (a_r_off - a_o)
    disc = delta_dot**2 - 2.0 * delta_ddot * delta
    real = (delta <= 0.0) & (disc > 0.0)
    denominator = delta_dot + jnp.sqrt(jnp.where(real, disc, 1.0))
    hits = real & (denominator > 0.0)
    tau = -2.0 * delta / jnp.where(hits, denominator, 1.0)
    hits = hits & (tau <= dt)
    return jnp.where(hits, tau / dt, 1.0), hits


def step(params, y, t, dt, scenario, options):
    """y(t) -> (y(t + dt), the signals at t, the force just after a located impact)."""
    rows = Rows.of(y)
    ps = model.robots(params)
    clock = Clock.at(t)
    # At the step start the metrics see the signals, and the impact prediction needs the switch-off
    # field. Signals no metric uses (the Filippov weight, gamma) are dead code that XLA removes.
    fs, body = fields(ps, rows, clock, None, scenario, options)
    h_full = jnp.full(y.shape[1:], dt, y.dtype)
    aux_start = model.Aux(*(jnp.stack(pair) for pair in zip(*(aux(f, weight(f, f.sigma, h_full)) for f in fs))))
    F = aux_start.F
    if options.contact == "bilateral":  # no impacts: one RK4 step
        new, _ = substep(ps, rows, clock, h_full, None, scenario, options)
        return new.array(), aux_start, None
    a_o = body["v_o"]
    fraction, hits = [], []
    for i in range(2):
        f_i, hits_i = impact_fraction(ps[i], rows.robot(i), model.SIGNS[i], fs[i].off["v_r"], a_o, dt)
        fraction.append(f_i)
        hits.append(hits_i)
    theta_c = jnp.minimum(*fraction)
    first = tuple(hits[i] & (fraction[i] <= theta_c) for i in range(2))  # ties: both hit at once
    h1 = theta_c * dt
    h2 = dt - h1  # exactly 0 without an impact
    no = jnp.zeros_like(first[0])

    # Up to the impact, the hitting robot's contact is off; after it, on. Both substeps run as one
    # `lax.scan` body, so XLA compiles the stage once (see `substep`). A substep of zero length for
    # every sample (the second, in a step where no sample of the batch hits: most steps) is an exact
    # no-op for a finite state and is skipped: 1.8x faster, measured. Its start force then stands in
    # as the step-start force, which the peak metric sees anyway.
    def run(rows, xs):
        offset, h, forced_on, forced_off = xs
        new, start_F = substep(ps, rows, clock.advance(offset), h, Contact(forced_on, forced_off), scenario, options)
        return new, jnp.stack(start_F)

    def part(rows, xs):
        # One predicate for the whole batch; under `vmap` the cond becomes a select and both run.
        return jax.lax.cond((xs[1] > 0.0).any(), run, lambda rows, xs: (rows, F), rows, xs)

    pairs = lambda a, b: tuple(jnp.stack([a[i], b[i]]) for i in range(2))
    xs = (jnp.stack([jnp.zeros_like(h1), h1]), jnp.stack([h1, h2]), pairs((no, no), first), pairs(first, (no, no)))
    new, start_F = jax.lax.scan(part, rows, xs)
    return new.array(), aux_start, start_F[1]  # F just after the impact: the 2nd substep's start


def observe(params, y, t, dt, scenario, options) -> model.Aux:
    """The signals recorded at (t, y): contact force, Filippov weight, time-averaged gamma."""
    rows = Rows.of(y)
    fs, _ = fields(model.robots(params), rows, Clock.at(t), None, scenario, options)
    h = jnp.full(y.shape[1:], dt, y.dtype)
    auxes = [aux(f, weight(f, f.sigma, h)) for f in fs]
    return model.Aux(*(jnp.stack(pair) for pair in zip(*auxes)))


@register
class Filippov(Integrator):
    """The sliding-mode step for the hard switch: the dt -> 0 limit at dt = 1e-3 (docs/model.md)."""

    name = "filippov"
    description = "the sliding-mode step for the hard switch, the default for it: its answer is the dt -> 0 limit at dt = 1e-3"
    switches = ("hard",)
    default_for = ("hard",)
    converged_dt = {
        ("carry", "hard"): 2e-3,  # 16 of 16 samples, at 2e-3 and every finer step
        ("paper", "hard"): 1e-3,  # no sliding: forces within 1e-3 N of rk4 at 1e-4
    }

    def step(self, params, y, t, dt, scenario, options):
        return step(params, y, t, dt, scenario, options)

    def observe(self, params, y, t, dt, scenario, options) -> model.Aux:
        return observe(params, y, t, dt, scenario, options)
