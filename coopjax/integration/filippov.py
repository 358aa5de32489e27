"""The sliding-mode integrator for the hard switch (docs/model.md, "The sliding-mode step").

Fixed step, branch-free inside each RK4 stage, batched. The hard switch makes the field
discontinuous on sigma_i = F_i - F_lim = 0. In the carry scenario both surfaces attract, so the exact
solution slides on them (a Filippov sliding mode); plain RK4 chatters across them and converges only
at O(dt). This step reaches the dt -> 0 limit at dt = 1e-3, in its values and in its derivatives.

What makes it cheap:
- Each robot's switch w_i enters only its own nine rows, and the body's rows hold no w. So the rate of
  robot i's switching function, sigma_dot_i = K_g delta_dot_i + R_g s_i (a_r,i - a_o), depends on
  w_i alone: one scalar weight per robot.
- sigma is linear in the state while in contact. RK4 keeps linear functionals exactly, so stages
  that all have sigma_dot = 0 keep sigma on the surface to round-off.
- The switch-on field (w = 1) is evaluated with max(F, F_lim) in gamma and dZ/dt (the clamp): gamma
  is unclipped, and just below the surface the controller's denominator can vanish.

The weight, per RK4 stage and per robot i: evaluate the rows f0 (w = 0) and f1 (w = 1, clamped),
with switching rates sd0 and sd1, Delta = sd0 - sd1, then
  1. lambda* = clip(sd0 / Delta, 0, 1) if Delta > eps, else H(sd0): the on-surface Filippov weight;
  2. the share theta of the substep of length h spent before reaching the surface, from sigma_n and
     the rates at the substep's start:
       sigma_n < 0:  theta = clip(-sigma_n / (sd0 h), 0, 1) if sd0 > 0 else 1,  lambda = (1 - theta) lambda*
       sigma_n >= 0: theta = clip(sigma_n / (-sd1 h), 0, 1) if sd1 < 0 else 1,  lambda = theta + (1 - theta) lambda*
  3. robot i's rows are f0 + lambda (f1 - f0); lambda = 0 for a robot out of contact.

Events: the step is cut into up to three substeps, each ending at the first event of either robot
predicted at its start (or at the step's end). The events are where the field, or its rate, jumps:
- an impact, a tip out of contact (delta <= 0) meeting the body, predicted from
  delta + delta_dot tau + delta_ddot tau^2 / 2 = 0 (delta_ddot from the contact-free field). Its
  contact is held off up to the impact and on after it (no delta > 0 test);
- the grip force reaching F_lim from below or from above (the switch), predicted to first order from
  sigma and its rate; the switch is held as it is up to the event;
- the Kelvin-Voigt force passing 0 while the tip touches, below F_lim (the contact force stops at 0);
- the end of a sliding mode, where lambda* leaves [0, 1] and the force leaves the surface (downwards
  at 0, upwards at 1). The field is continuous there but kinks; unlocated, the kink's place in the
  step moves with the parameters and the derivative errs by O(dt) at every exit. A robot sliding at a
  piece's start slides through the whole piece with lambda* unclipped (the sliding motion's smooth
  continuation), and the next piece holds the switch off (or on) as the force leaves.
A first-order prediction is late for a force that accelerates towards F_lim (or 0), so each piece is
also a trial: where a robot's switch was held through it (off below the surface, on above) and its
own RK4 solution ends across the surface, or the Kelvin-Voigt force changed sign while touching, or
a sliding robot's lambda* left [0, 1] by the last stage (`sliding_exit`), the piece ends at the
crossing instead (`crossing`, from the start's value and rate and the trial's end
value, so the stiff modes are in it), on RK4's continuous extension (`dense`). The rest of the step
is the next piece. The last piece of a step is not cut.
A substep of zero length is an exact no-op, so the step map is continuous. Unlocated, an event's
effect on the step would depend on where in the step it fell: the value would still be right to
O(dt), but its derivative with respect to the parameters would not converge.

Stage times differ per sample within the substeps; commands take them through `Clock.advance`.

Layout: the state is a `Rows` pytree, one dict of (B,) rows per robot and the body's rows, and each
robot's fields are evaluated on its own rows (model.py, module docstring: the fast layout).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from coopjax import model
from coopjax.integration.base import Integrator, Path, register
from coopjax.scenarios import Clock

EPS = 1e-9  # N/s: below this the two switching rates are taken as equal (step 1 of the weight)
# Rows that differ between the w = 0 and w = 1 fields; the kinematic rows (x_r, x_v, x_f) do not.
SWITCHED = ("v_r", "v_v", "q_c", "v_f", "Z", "Y_e")
PIECES = 3  # substeps per step: up to two events located in one step
# Of the step: an event nearer than this is taken as reached (a first-order prediction's residue; for
# the surface, sliding on it). Located or not, so short a piece changes the step by far less than
# the tolerances.
SHORTEST_EVENT = 1e-2


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
    """Per-robot overrides for a substep, each a pair of (B,) arrays (L, R): the contact forced on or
    off (booleans), and the switch held off or on for the whole substep (`hold`: 0 off, 1 on, -1 not
    held), for a robot whose substep ends where its force reaches F_lim."""

    on: tuple
    off: tuple
    hold: tuple | None = None
    free: tuple | None = None  # (B,) bool per robot: sliding, lambda* not clipped (the exit trial)


class Fields(NamedTuple):
    """Everything one evaluation point gives for one robot, before its Filippov weight is chosen."""

    in_contact: jax.Array  # (B,) bool
    F: jax.Array  # (B,) contact force, N
    F_lim: jax.Array  # (B,) the robot's force limit, N
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
        out.append(Fields(in_contact, F, p.F_lim, sigma, sd0, sd1, off, on, aux_off, aux_on))
    return tuple(out), body


def fractions(f: Fields, sigma_n, h):
    """The shares theta of a (sub)step of length h (B,) spent before the surface is reached, from
    below and from above (step 2 of the scheme), from sigma_n and the switching rates at its start.

    They are taken at the substep's start, not at each stage: an event the step is split at then
    ends its first substep with theta = 1 exactly, whether it is split there or not, so the map does
    not jump when the order of two events (of the two robots) changes.
    Divisions are guarded so that a branch that is not taken cannot put a NaN in a gradient.
    """
    sd0, sd1 = f.sd0, f.sd1
    approach_from_below = sd0 * h > 0.0
    theta_below = jnp.where(
        approach_from_below, jnp.clip(-sigma_n / jnp.where(approach_from_below, sd0 * h, 1.0), 0.0, 1.0), 1.0)
    approach_from_above = -sd1 * h > 0.0
    theta_above = jnp.where(
        approach_from_above, jnp.clip(sigma_n / jnp.where(approach_from_above, -sd1 * h, 1.0), 0.0, 1.0), 1.0)
    return theta_below, theta_above


def sliding_weight(f: Fields):
    """lambda* of step 1 before its clip to [0, 1]: sd0 / Delta where the rates differ, else H(sd0).
    On the surface it is the weight that keeps sigma = 0; it leaves [0, 1] where the sliding ends."""
    sd0, sd1 = f.sd0, f.sd1
    delta = sd0 - sd1
    sliding = delta > EPS
    return jnp.where(sliding, sd0 / jnp.where(sliding, delta, 1.0), (sd0 >= 0.0).astype(sd0.dtype))


def weight(f: Fields, sigma_n, h, hold=None, theta=None, free=None):
    """lambda of one robot (B,): steps 1 and 2 of the scheme (module docstring), at one stage.

    sigma_n is sigma at the (sub)step start; h the (sub)step length, per sample (B,); `theta` the
    substep start's `fractions` (taken from this point's rates if None); `hold` (B,) holds the
    switch off (0) or on (1) where it is not -1; where `free` (B,) holds, lambda* is not clipped (the
    sliding motion continued past its exit, for `step` to locate the exit on the piece's solution).
    """
    raw = sliding_weight(f)
    lam_star = jnp.clip(raw, 0.0, 1.0) if free is None else jnp.where(free, raw, jnp.clip(raw, 0.0, 1.0))
    theta_below, theta_above = fractions(f, sigma_n, h) if theta is None else theta
    lam = jnp.where(sigma_n < 0.0, (1.0 - theta_below) * lam_star, theta_above + (1.0 - theta_above) * lam_star)
    if hold is not None:
        lam = jnp.where(hold >= 0, hold.astype(lam.dtype), lam)
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


def _rates(fs, body, sigma_n, h, contact: Contact | None, thetas) -> Rows:
    holds = (None, None) if contact is None or contact.hold is None else contact.hold
    frees = (None, None) if contact is None or contact.free is None else contact.free
    return Rows(tuple(combine(f, weight(f, s_n, h, hold, theta, free))
                      for f, s_n, hold, theta, free in zip(fs, sigma_n, holds, thetas, frees)), body)


def _axpy(rows: Rows, c, k: Rows) -> Rows:
    """rows + c k; c is per sample (B,)."""
    return jax.tree_util.tree_map(lambda a, b: a + c * b, rows, k)


# RK4's tableau: stage j is evaluated at y + A_j h k_{j-1}, t + A_j h, and weighted B_j / 6.
RK4_A = (0.0, 0.5, 0.5, 1.0)
RK4_B = (1.0, 2.0, 2.0, 1.0)


class Plan(NamedTuple):
    """What a substep decides at its start: its length and, per robot, its overrides."""

    h: jax.Array  # (B,) s
    on: tuple  # contact held on (the substep after an impact)
    off: tuple  # contact held off (the substep that ends at an impact)
    hold: tuple  # switch held: 0 off, 1 on, -1 not held (the substep that ends where F reaches F_lim)
    impact: tuple  # this substep ends at the robot's impact


def impact_time(p, st, s, a_r_off, a_o):
    """Time to one robot's contact onset (inf if none is predicted).

    The contact time solves delta + delta_dot tau + delta_ddot tau^2 / 2 = 0, written without
    cancellation as tau = -2 delta / (delta_dot + sqrt(delta_dot^2 - 2 delta_ddot delta)). For a robot
    out of contact the switch-off field is the contact-free one, so delta_ddot comes from its tip
    acceleration a_r_off and the body's a_o.
    """
    delta, delta_dot, _ = model.geometry(p, st, s)
    delta_ddot = s * (a_r_off - a_o)
    disc = delta_dot**2 - 2.0 * delta_ddot * delta
    real = (delta <= 0.0) & (disc > 0.0)
    denominator = delta_dot + jnp.sqrt(jnp.where(real, disc, 1.0))
    hits = real & (denominator > 0.0)
    return jnp.where(hits, -2.0 * delta / jnp.where(hits, denominator, 1.0), jnp.inf)


def switching_time(f: Fields, shortest):
    """Time to one robot's next switching event while in contact (inf if none), first order, and
    the switch's hold until then: off (0) when the force rises to F_lim, on (1) when it falls to it,
    -1 when the Kelvin-Voigt force reaches 0 (below F_lim, where the w = 0 rate applies). A force
    already within `shortest` of F_lim is taken as on the surface (sliding there)."""
    below = f.in_contact & (f.sigma < 0.0) & (f.sd0 > 0.0)
    above = f.in_contact & (f.sigma > 0.0) & (f.sd1 < 0.0)
    rate = jnp.where(below, f.sd0, jnp.where(above, -f.sd1, 1.0))
    tau = jnp.where((below | above), jnp.abs(f.sigma) / rate, jnp.inf)
    tau = jnp.where(tau > shortest, tau, jnp.inf)
    kelvin = f.sigma + f.F_lim
    # Below F_lim only, where the w = 0 rate is the one acting: above it, the force reaches F_lim first.
    crossing = f.in_contact & (f.F_lim > 0.0) & (f.sigma < 0.0) & (kelvin * f.sd0 < 0.0)
    tau0 = jnp.where(crossing, jnp.abs(kelvin) / jnp.where(crossing, jnp.abs(f.sd0), 1.0), jnp.inf)
    tau0 = jnp.where(tau0 > shortest, tau0, jnp.inf)
    first = jnp.minimum(tau, tau0)
    hold = jnp.where(tau <= tau0, jnp.where(above, 1, 0), -1)
    return first, jnp.where(jnp.isfinite(first), hold, -1)


def plan(ps, rows: Rows, fs, body, remaining, on, dt, options, last, kept) -> Plan:
    """The next substep: up to the first event of either robot within `remaining` (all of it for
    the `last` piece a step has). `kept` (per robot) holds the switch of a robot whose sliding has
    just ended: off (0) below the surface, on (1) above it, -1 for none."""
    times, holds, impacts = [], [], []
    for i in range(2):
        tau, hold = switching_time(fs[i], SHORTEST_EVENT * dt)
        if options.contact == "bilateral":  # always in contact: no impacts
            hit = jnp.full_like(tau, jnp.inf)
        else:
            hit = jnp.where(on[i], jnp.inf, impact_time(ps[i], rows.robot(i), model.SIGNS[i], fs[i].off["v_r"], body["v_o"]))
        times.append(jnp.minimum(tau, hit))
        holds.append(jnp.where(hit < tau, -1, hold))
        impacts.append(hit <= tau)
    h = jnp.where(last, remaining, jnp.minimum(jnp.minimum(*times), remaining))
    first = tuple((times[i] <= h) & (times[i] <= remaining) & ~last for i in range(2))  # ties: both at once
    impact = tuple(first[i] & impacts[i] for i in range(2))
    hold = tuple(jnp.where(kept[i] >= 0, kept[i], jnp.where(first[i], holds[i], -1)) for i in range(2))
    return Plan(h, on, impact, hold, impact)


def crossing(sigma_n, rate, sigma_end, h):
    """Where sigma, held on one side of the surface through a piece of length h, reaches 0 in it: the
    root of the quadratic with sigma's value and rate at the start and its value at the end (the
    piece's own RK4 solution, so fast modes too small to see in the start's rates are in it).
    For sigma_n < 0 < sigma_end, written without cancellation; the caller flips signs for the
    crossing from above. Where there is no crossing the value is meaningless (the caller masks it);
    divisions are guarded so that it puts no NaN in a gradient."""
    hs = jnp.where(h > 0.0, h, 1.0)
    curvature = (sigma_end - sigma_n - rate * hs) / hs**2
    disc = rate**2 - 4.0 * curvature * sigma_n
    real = (sigma_n < 0.0) & (sigma_end > 0.0) & (disc >= 0.0)
    denominator = rate + jnp.sqrt(jnp.where(real, disc, 1.0))
    ok = real & (denominator > 0.0)
    # A crossing always has a root in (0, h); `ok` fails only to round-off, at its end.
    return jnp.where(ok, jnp.clip(-2.0 * sigma_n / jnp.where(ok, denominator, 1.0), 0.0, h), h)


class Held(NamedTuple):
    """One robot at a piece's start, for `trial_crossing`: whether the switch is held off (below the
    surface) or on (above it) through the whole piece, and the start's sigma and rates."""

    off: jax.Array  # (B,) bool
    on: jax.Array  # (B,) bool
    sigma_n: jax.Array  # (B,) N
    sd0: jax.Array  # (B,) N/s, the w = 0 field's
    sd1: jax.Array  # (B,) N/s, the w = 1 field's
    in_contact: jax.Array  # (B,) bool
    rate: jax.Array  # (B,) N/s, the start's weighted field's


def trial_crossing(g: Held, kelvin_end, F_lim, h, fresh):
    """One robot's event found on a piece's own solution: (found, time, hold). The force crossed
    F_lim while the switch was held (hold 0 from below, 1 from above), or the Kelvin-Voigt force
    crossed 0 while touching (hold -1); the time is the first of them. Nothing is found where
    `fresh` is False (the step's last piece)."""
    sigma_end = kelvin_end - F_lim
    up, down = g.off & (sigma_end > 0.0), g.on & (sigma_end < 0.0)
    kelvin = g.sigma_n + F_lim
    kink = g.in_contact & (F_lim > 0.0) & (kelvin * kelvin_end < 0.0)
    tau = jnp.where(up, crossing(g.sigma_n, g.sd0, sigma_end, h),
                    jnp.where(down, crossing(-g.sigma_n, -g.sd1, -sigma_end, h), jnp.inf))
    sign = jnp.where(kelvin > 0.0, -1.0, 1.0)  # the Kelvin-Voigt force rising through 0 or falling
    tau0 = jnp.where(kink, crossing(sign * kelvin, sign * g.rate, sign * kelvin_end, h), jnp.inf)
    hold = jnp.where(tau0 < tau, -1, jnp.where(g.off, 0, 1))
    return fresh & (up | down | kink), jnp.minimum(tau, tau0), hold


def sliding_exit(free, start, end, h):
    """One robot's sliding exit found on a piece it slid through (`free`): (found, time, hold).
    lambda* (unclipped) left [0, 1] between its values at the piece's start and at the last stage:
    below 0 the force leaves the surface downwards (switch off after it), above 1 upwards (on).
    The time is the linear interpolation of lambda*; its error, O(h^2), moves the exit's kink by
    that much, which changes the step by O(h^4)."""
    down, up = free & (end < 0.0), free & (end > 1.0)
    denominator = jnp.where(down, start - end, jnp.where(up, end - start, 1.0))
    share = jnp.where(down, start, 1.0 - start) / jnp.where(down | up, denominator, 1.0)
    return down | up, jnp.where(down | up, jnp.clip(share, 0.0, 1.0) * h, jnp.inf), jnp.where(up, 1, 0)


def substep(ps, rows: Rows, clock: Clock, remaining, on, kept, dt, scenario, options, last=False):
    """RK4 over the next piece of a step: up to the first event predicted at its start, or the rest
    of the step (`remaining`, per sample). `on` holds the contact of robots that have just hit,
    `kept` the switch of robots whose sliding has just ended (`plan`).

    The first stage is the substep's start: its fields give the plan (length and overrides) and
    the fractions theta for all four. A robot sliding at the start (on the surface, 0 < lambda* < 1)
    slides through the whole piece, lambda* unclipped, unless it is the step's last piece.
    Returns the new state, the plan, the signals at the start, each robot's `Held`, the four
    stages' rates (for `dense`), and per robot whether it slides through the piece with its
    unclipped lambda* at the first and the last stage (for `sliding_exit`).
    """
    # Every stage's theta uses sigma at the substep start (step 2 of the weight): the contact alone.
    no = jnp.zeros_like(on[0])
    sigma_n = tuple(jnp.where(c[0], c[2], 0.0) - p.F_lim for c, p in zip(_contacts(ps, rows, options, Contact(on, (no, no))), ps))
    # The first stage, at the substep's start: its fields give the plan (length and overrides), the
    # fractions theta that serve all four stages, and the signals. Outside the stage loop, so the
    # other three stages do not compute (and discard) them.
    unheld = jnp.full(no.shape, -1)
    fs, body = fields(ps, rows, clock, Contact(on, (no, no), (unheld, unheld)), scenario, options)
    part = plan(ps, rows, fs, body, remaining, on, dt, options, last, kept)
    thetas = tuple(fractions(f, s_n, part.h) for f, s_n in zip(fs, sigma_n))
    raw = tuple(sliding_weight(f) for f in fs)
    # 0 < lambda* < 1 only where the two rates differ (`sliding_weight` is 0 or 1 elsewhere).
    free = tuple(f.in_contact & (hold < 0) & (r > 0.0) & (r < 1.0) & ~last
                 & jnp.where(s_n < 0.0, theta_below < 1.0, theta_above < 1.0)
                 for f, r, s_n, hold, (theta_below, theta_above) in zip(fs, raw, sigma_n, part.hold, thetas))
    contact = Contact(part.on, part.off, part.hold, free)
    k = _rates(fs, body, sigma_n, part.h, contact, thetas)
    weights = tuple(weight(f, s_n, part.h, hold, theta) for f, s_n, hold, theta in zip(fs, sigma_n, part.hold, thetas))
    signals = model.Aux(*(jnp.stack(pair) for pair in zip(*(aux(f, lam) for f, lam in zip(fs, weights)))))

    def stage(carry, tableau):
        k_prev, total = carry
        a, b = tableau
        fs, body = fields(ps, _axpy(rows, a * part.h, k_prev), clock.advance(a * part.h), contact, scenario, options)
        k = _rates(fs, body, sigma_n, part.h, contact, thetas)
        return (k, jax.tree_util.tree_map(lambda x, y: x + b * y, total, k)), (k, jnp.stack([sliding_weight(f) for f in fs]))

    # The other three stages as a `lax.scan` over the tableau: one stage body for XLA to compile
    # instead of three copies.
    tableau = (jnp.asarray(RK4_A[1:], remaining.dtype), jnp.asarray(RK4_B[1:], remaining.dtype))
    (_, total), (ks, raws) = jax.lax.scan(stage, (k, k), tableau)
    # Per robot, the switch held off (on) through the whole piece below (above) the surface: where
    # `step` looks at the piece's end for a crossing its start did not predict.
    held = []
    for f, s_n, hold, (theta_below, theta_above), lam in zip(fs, sigma_n, part.hold, thetas, weights):
        off = f.in_contact & (s_n < 0.0) & ((hold == 0) | ((hold < 0) & (theta_below >= 1.0)))
        on_ = f.in_contact & (s_n > 0.0) & ((hold == 1) | ((hold < 0) & (theta_above >= 1.0)))
        held.append(Held(off, on_, s_n, f.sd0, f.sd1, f.in_contact, f.sd0 + lam * (f.sd1 - f.sd0)))
    slides = tuple((fr, r, raws[-1, i]) for i, (fr, r) in enumerate(zip(free, raw)))
    return _axpy(rows, part.h / 6, total), part, signals, tuple(held), (k, ks), slides


def dense(rows, h, ks, theta):
    """RK4's continuous extension (third order) at theta of the piece: rows + h sum b_i(theta) k_i."""
    k1, rest = ks
    b1 = theta - 1.5 * theta**2 + 2.0 / 3.0 * theta**3
    b23 = theta**2 - 2.0 / 3.0 * theta**3
    b4 = -0.5 * theta**2 + 2.0 / 3.0 * theta**3
    return jax.tree_util.tree_map(lambda y, a, k: y + h * (b1 * a + b23 * (k[0] + k[1]) + b4 * k[2]), rows, k1, rest)


def step(params, y, t, dt, scenario, options):
    """y(t) -> (y(t + dt), the signals at t, the grip force's path through the step).

    Up to `PIECES` substeps, each ending at the first event (see "Events" in the module docstring).
    A substep with nothing left to do for every sample of the batch (most steps have one piece) is
    skipped: an exact no-op for a finite state, and the largest saving of the step.
    """
    rows = Rows.of(y)
    ps = model.robots(params)
    clock = Clock.at(t)
    no = jnp.zeros(y.shape[1:], bool)
    remaining = jnp.full(y.shape[1:], dt, y.dtype)
    F0 = jnp.stack([c[1] for c in _contacts(ps, rows, options)])

    def run(carry, j):
        rows, remaining, offset, on, kept, F_end, signals = carry
        last = j == PIECES - 1
        new, part, start_signals, held, ks, slides = substep(ps, rows, clock.advance(offset), remaining, on, kept, dt,
                                                             scenario, options, last=last)
        contact = Contact(part.on, part.off, part.hold)
        touch = _contacts(ps, new, options, contact)
        # The piece as a trial: cut at a crossing it held the switch through, or where a robot's
        # sliding ended (module docstring).
        crossings = tuple(trial_crossing(g, c[2], p.F_lim, part.h, ~last) for g, c, p in zip(held, touch, ps))
        exits = tuple(sliding_exit(*slide, part.h) for slide in slides)
        found = tuple((fc | fe, jnp.minimum(jnp.where(fc, tc, jnp.inf), te), jnp.where(fe & (te < tc), he, hc))
                      for (fc, tc, hc), (fe, te, he) in zip(crossings, exits))
        flag = found[0][0] | found[1][0]
        tau = jnp.minimum(jnp.where(found[0][0], found[0][1], jnp.inf), jnp.where(found[1][0], found[1][1], jnp.inf))
        h = jnp.where(flag, tau, part.h)
        theta = h / jnp.where(part.h > 0.0, part.h, 1.0)
        # A cond's outputs are buffers: their consumers read the decision instead of each fusing, and
        # recomputing, the plan and the roots it stems from. The predicate holds for every state.
        decided = (h, theta, flag, tau, found)
        h, theta, flag, tau, found = jax.lax.cond(
            (part.h >= 0.0).all(), lambda a: a[0], lambda a: a[1],
            (decided, (part.h, jnp.ones_like(theta), jnp.zeros_like(flag), part.h, found)))
        cut = dense(rows, part.h, ks, theta)
        end = jnp.stack([c[1] for c in _contacts(ps, cut, options, contact)])
        signals = jax.tree_util.tree_map(lambda s, n: jnp.where(offset == 0.0, n, s), signals, start_signals)
        impact = tuple(i & ~flag for i in part.impact)
        at_tau = [f & (t_ <= tau) for f, t_, _ in found]
        # A piece ends on the surface where it is cut at a crossing or a sliding exit, or where its
        # plan ended it at a switch (a hold kept from a sliding exit is not one).
        surface = jnp.stack([jnp.where(flag, a & (hd >= 0), (hold >= 0) & (k_in < 0))
                             for a, (_, _, hd), hold, k_in in zip(at_tau, found, part.hold, kept)])
        # The next piece holds the switch of a robot whose sliding ended here, as it left the surface.
        kept = tuple(jnp.where(flag & fe & (te <= tau), he, -1) for fe, te, he in exits)
        carry = (cut, remaining - h, offset + h, impact, kept, end, signals)
        return carry, (h, start_signals.F, end, surface, jnp.stack(impact))

    def piece(carry, j):
        # One predicate for the whole batch; under `vmap` the cond becomes a select and both run.
        return jax.lax.cond((carry[1] > 0.0).any(), run,
                            lambda carry, _: (carry, (0.0 * carry[1], carry[5], carry[5], jnp.zeros_like(carry[5], bool),
                                                      jnp.zeros_like(carry[5], bool))),
                            carry, j)

    signals0 = model.Aux(*(jnp.stack([0.0 * remaining] * 2) for _ in model.Aux._fields))
    unheld = jnp.full(y.shape[1:], -1)
    carry = (rows, remaining, 0.0 * remaining, (no, no), (unheld, unheld), F0, signals0)
    (new, _, _, _, _, _, signals), (h, starts, ends, surface, impact) = jax.lax.scan(piece, carry, jnp.arange(PIECES))
    return new.array(), signals, Path(h / dt, starts, ends, surface, impact)


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
