"""The sliding-mode integrator for the hard switch (docs/model.md, "What `integrator=\"filippov\"` does").

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

Names: a step is up to `PIECES` pieces (`Piece`, from `substep`), carried through the step as
`Progress`. A piece's `Plan` is its length and its `Overrides`: per robot, the contact held on or
off and the switch held as a `Switch` (`OFF`, `ON`, or `FREE` for the Filippov weight), plus
whether the piece ends where the robot's force reaches F_lim (`at_switch`, a separate field: a
switch kept held after a sliding exit does not end the piece at a switch). The events a piece's own
solution reveals are `Event`s (`trial_crossing`, `sliding_exit`). `Touch` is one robot's contact
at a point; `Fields` its two fields there.

Layout: the state is a `Rows` pytree, one dict of (B,) rows per robot and the body's rows, and each
robot's fields are evaluated on its own rows (model.py, module docstring: the fast layout).
"""

from __future__ import annotations

import enum
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from coopjax import model
from coopjax.integration.base import Integrator, Path, decided, register
from coopjax.integration.tableau import RK4
from coopjax.scenarios import Clock

EPS = 1e-9  # N/s: below this the two switching rates are taken as equal (step 1 of the weight)
# Rows that differ between the w = 0 and w = 1 fields; the kinematic rows (x_r, x_v, x_f) do not.
SWITCHED = ("v_r", "v_v", "q_c", "v_f", "Z", "Y_e")
PIECES = 3  # substeps per step: up to two events located in one step
# Of the step: an event nearer than this is taken as reached (a first-order prediction's residue; for
# the surface, sliding on it). Located or not, so short a piece changes the step by far less than
# the tolerances.
SHORTEST_EVENT = 1e-2


class Switch(enum.IntEnum):
    """How a piece sets one robot's switch w_i. Carried as int codes in (B,) arrays."""

    FREE = -1  # not held: the Filippov weight lambda decides
    OFF = 0  # held off, w = 0 (below the surface, up to the force reaching F_lim)
    ON = 1  # held on, w = 1 (above it)


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


class Overrides(NamedTuple):
    """What a piece holds fixed for each robot, each a pair (L, R) of (B,) arrays."""

    touching: tuple  # bool: contact held on (the piece after the robot's impact)
    apart: tuple  # bool: contact held off (the piece that ends at the robot's impact)
    switch: tuple | None = None  # `Switch` codes: w_i held through the piece, or FREE
    free: tuple | None = None  # bool: sliding through the piece with lambda* unclipped (the exit trial)
    leaving: tuple | None = None  # `Switch`: leaving the surface at the piece's start, upwards (ON) or down (OFF)


class Touch(NamedTuple):
    """One robot's contact at a point."""

    in_contact: jax.Array  # (B,) bool, after the piece's overrides
    F: jax.Array  # (B,) the contact force max(kelvin, 0) in contact, else 0, N
    kelvin: jax.Array  # (B,) K_g delta + R_g delta_dot, N
    delta: jax.Array  # (B,) penetration, m
    delta_dot: jax.Array  # (B,) its rate, m/s


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


def touches(ps, rows: Rows, options, overrides: Overrides | None = None) -> tuple[Touch, Touch]:
    """Both robots' contact at a point, under a piece's contact overrides if any."""
    out = []
    for i in range(2):
        delta, delta_dot, kelvin = model.geometry(ps[i], rows.robot(i), model.SIGNS[i])
        if options.contact == "bilateral":
            out.append(Touch(jnp.ones_like(delta, bool), kelvin, kelvin, delta, delta_dot))
            continue
        in_contact = delta > 0.0
        if overrides is not None:
            in_contact = overrides.touching[i] | (~overrides.apart[i] & in_contact)
        out.append(Touch(in_contact, jnp.where(in_contact, jnp.maximum(kelvin, 0.0), 0.0), kelvin, delta, delta_dot))
    return tuple(out)


def forces(touch: tuple[Touch, Touch]) -> jax.Array:
    """The two contact forces (2, B)."""
    return jnp.stack([t.F for t in touch])


def fields(ps, rows: Rows, clock: Clock, overrides: Overrides | None, scenario, options):
    """Both robots' w = 0 and w = 1 fields at one point (a pair of `Fields`) and the body's rates.
    `ps` is `model.robots(params)`; ps[0] also carries the shared parameters.

    The contact forces come first: the body's acceleration needs both, and neither depends on w.
    """
    commands = scenario.command(ps[0], clock)
    touch = touches(ps, rows, options, overrides)
    body = model.body_field(ps[0], rows.body, touch[0].F, touch[1].F)
    out = []
    for i in range(2):
        p, st, s, c = ps[i], rows.robot(i), model.SIGNS[i], touch[i]
        off, aux_off = model.robot_field(p, st, s, c.F, 0.0, commands[i], options)
        clamped = jnp.maximum(c.F, p.F_lim)  # the clamp of the w = 1 field (module docstring)
        on, aux_on = model.robot_field(p, st, s, c.F, 1.0, commands[i], options, F_gamma=clamped, F_memory=clamped)
        # d/dt (K_g delta + R_g delta_dot) for each field: the body's rows hold no w.
        sd0 = p.K_g * c.delta_dot + p.R_g * s * (off["v_r"] - body["v_o"])
        sd1 = p.K_g * c.delta_dot + p.R_g * s * (on["v_r"] - body["v_o"])
        sigma = jnp.where(c.in_contact, c.kelvin, 0.0) - p.F_lim
        out.append(Fields(c.in_contact, c.F, p.F_lim, sigma, sd0, sd1, off, on, aux_off, aux_on))
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
        approach_from_below, jnp.clip(-sigma_n / jnp.where(approach_from_below, sd0 * h, 1.0), 0.0, 1.0), 1.0
    )
    approach_from_above = -sd1 * h > 0.0
    theta_above = jnp.where(
        approach_from_above, jnp.clip(sigma_n / jnp.where(approach_from_above, -sd1 * h, 1.0), 0.0, 1.0), 1.0
    )
    return theta_below, theta_above


def sliding_weight(f: Fields):
    """lambda* of step 1 before its clip to [0, 1]: sd0 / Delta where the rates differ, else H(sd0).
    On the surface it is the weight that keeps sigma = 0; it leaves [0, 1] where the sliding ends."""
    sd0, sd1 = f.sd0, f.sd1
    delta = sd0 - sd1
    sliding = delta > EPS
    return jnp.where(sliding, sd0 / jnp.where(sliding, delta, 1.0), (sd0 >= 0.0).astype(sd0.dtype))


def weight(f: Fields, sigma_n, h, switch=None, theta=None, free=None, leaving=None):
    """lambda of one robot (B,): steps 1 and 2 of the scheme (module docstring), at one stage.

    sigma_n is sigma at the (sub)step start; h the (sub)step length, per sample (B,); `theta` the
    substep start's `fractions` (taken from this point's rates if None); `switch` (B,) holds w at
    OFF (0) or ON (1) where it is not `Switch.FREE`; where `free` (B,) holds, lambda* is not clipped
    (the sliding motion continued past its exit, for `step` to locate the exit on the piece's
    solution); where `leaving` (B,) is ON (OFF), lambda* is 1 (0) through the piece (`leaving`).
    """
    lam_star_unclipped = sliding_weight(f)
    lam_star = jnp.clip(lam_star_unclipped, 0.0, 1.0)
    if free is not None:
        lam_star = jnp.where(free, lam_star_unclipped, lam_star)
    if leaving is not None:
        lam_star = jnp.where(leaving != Switch.FREE, leaving.astype(lam_star.dtype), lam_star)
    theta_below, theta_above = fractions(f, sigma_n, h) if theta is None else theta
    lam = jnp.where(sigma_n < 0.0, (1.0 - theta_below) * lam_star, theta_above + (1.0 - theta_above) * lam_star)
    if switch is not None:
        lam = jnp.where(switch != Switch.FREE, switch.astype(lam.dtype), lam)
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
    return model.Aux(
        F=f.F,
        w=lam,
        gamma=blend(f.aux_off.gamma, f.aux_on.gamma),
        x_ref=f.aux_off.x_ref,
        v_ref=blend(f.aux_off.v_ref, f.aux_on.v_ref),
    )


def _rates(fs, body, sigma_n, h, overrides: Overrides, thetas) -> Rows:
    """The state's rates at one stage of a piece: each robot's rows weighted by its lambda."""
    free = (None, None) if overrides.free is None else overrides.free
    leaving = (None, None) if overrides.leaving is None else overrides.leaving
    return Rows(
        tuple(
            combine(fs[i], weight(fs[i], sigma_n[i], h, overrides.switch[i], thetas[i], free[i], leaving[i]))
            for i in range(2)
        ),
        body,
    )


def _axpy(rows: Rows, c, k: Rows) -> Rows:
    """rows + c k; c is per sample (B,)."""
    return jax.tree_util.tree_map(lambda a, b: a + c * b, rows, k)


class Plan(NamedTuple):
    """What a piece decides at its start: its length, what it holds fixed, and where it ends."""

    h: jax.Array  # (B,) s
    overrides: Overrides  # contact and switch held through the piece (`free` is decided after the plan)
    at_switch: tuple  # per robot (B,) bool: the piece ends where the robot's force reaches F_lim

    @property
    def impact(self) -> tuple:
        """Per robot: the piece ends at its impact (the contact is held off exactly up to it)."""
        return self.overrides.apart


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
    the switch's hold until then: OFF when the force rises to F_lim, ON when it falls to it, FREE
    when the Kelvin-Voigt force reaches 0 (below F_lim, where the w = 0 rate applies). A force
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
    switch = jnp.where(tau <= tau0, jnp.where(above, Switch.ON, Switch.OFF), Switch.FREE)
    return first, jnp.where(jnp.isfinite(first), switch, Switch.FREE)


def plan(ps, rows: Rows, fs, body, remaining, touching, dt, options, last, kept) -> Plan:
    """The next piece: up to the first event of either robot within `remaining` (all of it for
    the `last` piece a step has). `touching` (per robot) holds the contact of robots that have just
    hit; `kept` (per robot) the switch of a robot whose sliding has just ended: OFF below the surface,
    ON above it, FREE for none."""
    times, switches, impacts = [], [], []
    for i in range(2):
        tau, switch = switching_time(fs[i], SHORTEST_EVENT * dt)
        if options.contact == "bilateral":  # always in contact: no impacts
            hit = jnp.full_like(tau, jnp.inf)
        else:
            hit = jnp.where(
                touching[i], jnp.inf, impact_time(ps[i], rows.robot(i), model.SIGNS[i], fs[i].off["v_r"], body["v_o"])
            )
        times.append(jnp.minimum(tau, hit))
        switches.append(jnp.where(hit < tau, Switch.FREE, switch))
        impacts.append(hit <= tau)
    h = jnp.where(last, remaining, jnp.minimum(jnp.minimum(*times), remaining))
    first = tuple((times[i] <= h) & (times[i] <= remaining) & ~last for i in range(2))  # ties: both at once
    apart = tuple(first[i] & impacts[i] for i in range(2))
    held = tuple(kept[i] != Switch.FREE for i in range(2))
    # A switch kept from a sliding exit is held through the piece, but the piece does not end there.
    switch = tuple(jnp.where(held[i], kept[i], jnp.where(first[i], switches[i], Switch.FREE)) for i in range(2))
    at_switch = tuple(~held[i] & first[i] & (switches[i] != Switch.FREE) for i in range(2))
    return Plan(h, Overrides(touching, apart, switch), at_switch)


def crossing(sigma_n, rate, sigma_end, h):
    """Where sigma, held on one side of the surface through a piece of length h, reaches 0 in it: the
    root of the quadratic with sigma's value and rate at the start and its value at the end (the
    piece's own RK4 solution, so fast modes too small to see in the start's rates are in it).
    For sigma_n <= 0 < sigma_end, written without cancellation; the caller flips signs for the
    crossing from above. Where there is no crossing the value is meaningless (the caller masks it);
    divisions are guarded so that it puts no NaN in a gradient."""
    hs = jnp.where(h > 0.0, h, 1.0)
    curvature = (sigma_end - sigma_n - rate * hs) / hs**2
    disc = rate**2 - 4.0 * curvature * sigma_n
    real = (sigma_n <= 0.0) & (sigma_end > 0.0) & (disc >= 0.0)
    positive = real & (disc > 0.0)  # sqrt's derivative is infinite at 0: it would put a NaN in a gradient
    root = jnp.where(positive, jnp.sqrt(jnp.where(positive, disc, 1.0)), 0.0)
    # The positive root in the form without cancellation for each sign of the rate: for a rate
    # <= 0 (sigma first moves away from the surface, as for a robot that has just left it) and
    # sigma_n -> 0, the root tends to the return time -rate / curvature, not to 0.
    rising = rate > 0.0
    numerator = jnp.where(rising, -2.0 * sigma_n, root - rate)
    denominator = jnp.where(rising, rate + root, 2.0 * curvature)
    ok = real & (denominator > 0.0)
    # A crossing always has a root in (0, h); `ok` fails only to round-off, at its end.
    return jnp.where(ok, jnp.clip(numerator / jnp.where(ok, denominator, 1.0), 0.0, h), h)


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


class Slide(NamedTuple):
    """One robot's sliding through a piece, for `sliding_exit`."""

    free: jax.Array  # (B,) bool: it slides through the piece with lambda* unclipped
    start: jax.Array  # (B,) lambda* (unclipped) at the piece's start
    end: jax.Array  # (B,) lambda* (unclipped) at its last stage


class Event(NamedTuple):
    """An event one robot's piece reveals on its own solution."""

    found: jax.Array  # (B,) bool
    time: jax.Array  # (B,) s into the piece (inf where not found)
    switch: jax.Array  # (B,) `Switch`: held after it (a crossing of F_lim is on the surface unless FREE)


def trial_crossing(g: Held, kelvin_end, F_lim, h, fresh) -> Event:
    """One robot's event found on a piece's own solution. The force crossed F_lim while the switch
    was held (OFF from below, ON from above), or the Kelvin-Voigt force crossed 0 while touching
    (FREE); the time is the first of them. Nothing is found where `fresh` is False (the step's last
    piece)."""
    sigma_end = kelvin_end - F_lim
    up, down = g.off & (sigma_end > 0.0), g.on & (sigma_end < 0.0)
    kelvin = g.sigma_n + F_lim
    through_zero = g.in_contact & (F_lim > 0.0) & (kelvin * kelvin_end < 0.0)
    tau = jnp.where(
        up,
        crossing(g.sigma_n, g.sd0, sigma_end, h),
        jnp.where(down, crossing(-g.sigma_n, -g.sd1, -sigma_end, h), jnp.inf),
    )
    sign = jnp.where(kelvin > 0.0, -1.0, 1.0)  # the Kelvin-Voigt force rising through 0 or falling
    tau0 = jnp.where(through_zero, crossing(sign * kelvin, sign * g.rate, sign * kelvin_end, h), jnp.inf)
    switch = jnp.where(tau0 < tau, Switch.FREE, jnp.where(g.off, Switch.OFF, Switch.ON))
    return Event(fresh & (up | down | through_zero), jnp.minimum(tau, tau0), switch)


def sliding_exit(slide: Slide, h) -> Event:
    """One robot's sliding exit found on a piece it slid through (`slide.free`).
    lambda* (unclipped) left [0, 1] between its values at the piece's start and at the last stage:
    below 0 the force leaves the surface downwards (switch OFF after it), above 1 upwards (ON).
    The time is the linear interpolation of lambda*; its error, O(h^2), moves the exit's kink by
    that much, which changes the step by O(h^4)."""
    start, end = slide.start, slide.end
    down, up = slide.free & (end < 0.0), slide.free & (end > 1.0)
    denominator = jnp.where(down, start - end, jnp.where(up, end - start, 1.0))
    share = jnp.where(down, start, 1.0 - start) / jnp.where(down | up, denominator, 1.0)
    return Event(
        down | up, jnp.where(down | up, jnp.clip(share, 0.0, 1.0) * h, jnp.inf), jnp.where(up, Switch.ON, Switch.OFF)
    )


def first_event(crossed: Event, exited: Event) -> Event:
    """One robot's earlier event of the two a piece can reveal (an exit wins where it is strictly first)."""
    return Event(
        crossed.found | exited.found,
        jnp.minimum(jnp.where(crossed.found, crossed.time, jnp.inf), exited.time),
        jnp.where(exited.found & (exited.time < crossed.time), exited.switch, crossed.switch),
    )


class Piece(NamedTuple):
    """What `substep` gives `step`: a piece run to the end of its plan."""

    rows: Rows  # the state at the plan's end
    plan: Plan
    signals: model.Aux  # at the piece's start, each (2, B)
    held: tuple  # per robot, `Held`
    stages: tuple  # (k1, (k2, k3, k4) stacked): the four stages' rates, for `dense`
    slides: tuple  # per robot, `Slide`


def substep(ps, rows: Rows, clock: Clock, remaining, touching, kept, dt, scenario, options, last=False) -> Piece:
    """RK4 over the next piece of a step: up to the first event predicted at its start, or the rest
    of the step (`remaining`, per sample). `touching` holds the contact of robots that have just hit,
    `kept` the switch of robots whose sliding has just ended (`plan`).

    The first stage is the piece's start: its fields give the plan (length and overrides) and
    the fractions theta for all four. A robot sliding at the start (on the surface, 0 < lambda* < 1)
    slides through the whole piece, lambda* unclipped, unless it is the step's last piece.
    """
    apart = (jnp.zeros_like(touching[0]),) * 2
    # sigma at the piece's start, which every stage's theta uses (step 2 of the weight): with the
    # contact held on for a robot that has just hit, and no contact held off, since the impact a
    # piece may end at is not known before its plan.
    sigma_n = tuple(
        jnp.where(c.in_contact, c.kelvin, 0.0) - p.F_lim
        for c, p in zip(touches(ps, rows, options, Overrides(touching, apart)), ps)
    )
    # The first stage, at the piece's start: its fields give the plan (length and overrides), the
    # fractions theta that serve all four stages, and the signals. Outside the stage loop, so the
    # other three stages do not compute (and discard) them. No switch is held yet: the plan decides.
    free_switch = (jnp.full(touching[0].shape, Switch.FREE),) * 2
    fs, body = fields(ps, rows, clock, Overrides(touching, apart, free_switch), scenario, options)
    piece = decided(plan(ps, rows, fs, body, remaining, touching, dt, options, last, kept))
    held_switch = piece.overrides.switch
    # sigma at the start and the fractions theta are the piece's plan too (`decided`): their signs and
    # clips pick the weight's formula, and a recomputation that rounded them the other way moved a
    # float32 derivative by 1 % (docs/speed.md).
    sigma_n, thetas = decided((sigma_n, tuple(fractions(f, s_n, piece.h) for f, s_n in zip(fs, sigma_n))))
    lam_star = tuple(sliding_weight(f) for f in fs)
    # 0 < lambda* < 1 only where the two rates differ (`sliding_weight` is 0 or 1 elsewhere).
    free = tuple(
        f.in_contact
        & (switch == Switch.FREE)
        & (r > 0.0)
        & (r < 1.0)
        & ~last
        & jnp.where(s_n < 0.0, theta_below < 1.0, theta_above < 1.0)
        for f, r, s_n, switch, (theta_below, theta_above) in zip(fs, lam_star, sigma_n, held_switch, thetas)
    )
    # A robot on the surface at the start (reaching it within the piece) whose lambda* is outside
    # [0, 1] leaves it at once: upwards (ON) for lambda* >= 1, downwards (OFF) for lambda* <= 0. It
    # is then held as a robot just above (below) the surface is, whatever the sign of sigma_n's
    # round-off: switched on (off) through the piece, its return to the surface looked for on the
    # piece's solution. Decided on the sign of sigma_n, a 1e-14 N change moved the step by O(dt).
    leaving = tuple(
        jnp.where(
            f.in_contact & (switch == Switch.FREE) & jnp.where(s_n < 0.0, theta_below < 1.0, theta_above < 1.0),
            jnp.where(r >= 1.0, Switch.ON, jnp.where(r <= 0.0, Switch.OFF, Switch.FREE)),
            Switch.FREE,
        )
        for f, r, s_n, switch, (theta_below, theta_above) in zip(fs, lam_star, sigma_n, held_switch, thetas)
    )
    free, leaving = decided((free, leaving))
    overrides = piece.overrides._replace(free=free, leaving=leaving)
    k = _rates(fs, body, sigma_n, piece.h, overrides, thetas)
    # The start's weights without `free`: lambda* clipped, so the recorded signals and `Held.rate`
    # are the clipped sliding motion's, where the stages' rates continue it unclipped.
    weights = tuple(
        weight(f, s_n, piece.h, switch, theta) for f, s_n, switch, theta in zip(fs, sigma_n, held_switch, thetas)
    )
    signals = model.Aux(*(jnp.stack(pair) for pair in zip(*(aux(f, lam) for f, lam in zip(fs, weights)))))

    def stage(carry, tableau):
        k_prev, total = carry
        a, b = tableau
        fs, body = fields(
            ps, _axpy(rows, a * piece.h, k_prev), clock.advance(a * piece.h), overrides, scenario, options
        )
        k = _rates(fs, body, sigma_n, piece.h, overrides, thetas)
        lam_star = jnp.stack([sliding_weight(f) for f in fs])
        return (k, jax.tree_util.tree_map(lambda x, y: x + b * y, total, k)), (k, lam_star)

    # The other three stages as a `lax.scan` over the tableau: one stage body for XLA to compile
    # instead of three copies. The first stage's weight b_1 = 1 is the `total` it starts from.
    tableau = (jnp.asarray(RK4.a[1:], remaining.dtype), jnp.asarray(RK4.b[1:], remaining.dtype))
    (_, total), (ks, lam_stars) = jax.lax.scan(stage, (k, k), tableau)
    # Per robot, the switch held off (on) through the whole piece below (above) the surface: where
    # `step` looks at the piece's end for a crossing its start did not predict.
    held = []
    for f, s_n, switch, (theta_below, theta_above), lam, away in zip(
        fs, sigma_n, held_switch, thetas, weights, leaving
    ):
        free_here = switch == Switch.FREE
        # Held off: below the surface, or on it and switched off (a sliding exit downwards, or
        # leaving it), whichever side of it round-off puts sigma_n; held on likewise.
        off = f.in_contact & (
            (switch == Switch.OFF) | (free_here & (s_n < 0.0) & (theta_below >= 1.0)) | (away == Switch.OFF)
        )
        on = f.in_contact & (
            (switch == Switch.ON) | (free_here & (s_n > 0.0) & (theta_above >= 1.0)) | (away == Switch.ON)
        )
        # Its crossing is looked for from its own side of the surface.
        s_n = jnp.where(on, jnp.maximum(s_n, 0.0), jnp.where(off, jnp.minimum(s_n, 0.0), s_n))
        held.append(Held(off, on, s_n, f.sd0, f.sd1, f.in_contact, f.sd0 + lam * (f.sd1 - f.sd0)))
    slides = tuple(Slide(free[i], lam_star[i], lam_stars[-1, i]) for i in range(2))
    end = _axpy(rows, piece.h / RK4.denominator, total)
    return Piece(end, piece, signals, tuple(held), (k, ks), slides)


def dense(rows, h, stages, theta):
    """RK4's continuous extension (third order) at theta of the piece: rows + h sum_j b_j(theta) k_j."""
    groups = [(RK4.polynomial(row, theta), members) for row, members in RK4.dense_groups()]

    def extend(y, k1, rest):
        k = (k1, *rest)
        terms = [b * _sum(k, members) for b, members in groups]
        return y + h * sum(terms[1:], terms[0])

    k1, rest = stages
    return jax.tree_util.tree_map(extend, rows, k1, rest)


def _sum(k, members):
    """k[members[0]] + k[members[1]] + ..., in order."""
    total = k[members[0]]
    for j in members[1:]:
        total = total + k[j]
    return total


def as_buffers(values, fallback):
    """`values`, materialised once as buffers that their consumers read.

    Without this, XLA fuses the plan's decision (and the roots it stems from) into each of its many
    consumers and recomputes it there. A `lax.cond` whose outputs are buffers stops that; its
    predicate holds for every state (a piece's planned length is never negative), and `fallback`
    (same structure) is never taken. `lax.optimization_barrier` would state the intent better, but
    measured slower in paired runs (docs/speed.md, "What was tried").
    """
    h = values[0]
    return jax.lax.cond(~(h < 0.0).any(), lambda pair: pair[0], lambda pair: pair[1], (values, fallback))


class Progress(NamedTuple):
    """The carry through a step's pieces."""

    rows: Rows  # the state at the end of the pieces so far
    remaining: jax.Array  # (B,) of the step, s
    offset: jax.Array  # (B,) into the step, s
    touching: tuple  # per robot (B,) bool: it hit at the last piece's end, so its contact is held on
    kept: tuple  # per robot (B,) `Switch`: held through the next piece after a sliding exit
    F_end: jax.Array  # (2, B) the contact forces at the last piece's end, N
    signals: model.Aux  # at the step's start, each (2, B)


def step(params, y, t, dt, scenario, options):
    """y(t) -> (y(t + dt), the signals at t, the grip force's path through the step).

    Up to `PIECES` substeps, each ending at the first event (see "Events" in the module docstring).
    A substep with nothing left to do for every sample of the batch (most steps have one piece) is
    skipped: an exact no-op for a finite state, and the largest saving of the step.
    The path (each piece's plan and cut, and whether it runs) is named `DECISIONS`, so that reverse
    mode keeps it from the forward pass instead of recomputing it (`base.DECISIONS`).
    """
    rows, signals, path = step_rows(params, Rows.of(y), t, dt, scenario, options)
    return rows.array(), signals, path


def step_rows(params, rows: Rows, t, dt, scenario, options):
    """`step` on the state as `Rows`."""
    ps = model.robots(params)
    clock = Clock.at(t)
    # Made to depend on the state (by adding a zero that does), so that under differentiation the
    # pieces' loop sees tangents in its whole carry from the start (as `loop.integrate` does for the
    # time loop): otherwise reverse mode processed the pieces' body again until they settled, and
    # tracing `grad` took 11 s.
    remaining = dt + 0.0 * rows.robots[0]["x_r"]
    false = jnp.zeros(remaining.shape, bool)

    def run(carry: Progress, j):
        last = j == PIECES - 1
        piece = substep(
            ps,
            carry.rows,
            clock.advance(carry.offset),
            carry.remaining,
            carry.touching,
            carry.kept,
            dt,
            scenario,
            options,
            last=last,
        )
        planned = piece.plan
        # The contact at the piece's end and at a cut inside it, under the piece's own contact
        # overrides (a robot that hits at the end is still apart there).
        touch = touches(ps, piece.rows, options, planned.overrides)
        # The piece as a trial: cut at a crossing it held the switch through, or where a robot's
        # sliding ended (module docstring).
        crossings = tuple(
            trial_crossing(g, c.kelvin, p.F_lim, planned.h, ~last) for g, c, p in zip(piece.held, touch, ps)
        )
        exits = tuple(sliding_exit(slide, planned.h) for slide in piece.slides)
        events = tuple(map(first_event, crossings, exits))
        cut = events[0].found | events[1].found
        tau = jnp.minimum(
            jnp.where(events[0].found, events[0].time, jnp.inf), jnp.where(events[1].found, events[1].time, jnp.inf)
        )
        h = jnp.where(cut, tau, planned.h)
        # A piece that reaches the step's end (the rest is 0 to round-off) ends there in its tangent
        # too: the same value, but the rest's tangent would otherwise be lost with the piece skipped.
        h = jnp.where(h >= carry.remaining, carry.remaining, h)
        theta = h / jnp.where(planned.h > 0.0, planned.h, 1.0)
        h, theta, cut, tau, events = decided(
            as_buffers(
                (h, theta, cut, tau, events),
                (planned.h, jnp.ones_like(theta), jnp.zeros_like(cut), planned.h, events),
            )
        )
        rows_cut = dense(carry.rows, planned.h, piece.stages, theta)
        F_end = forces(touches(ps, rows_cut, options, planned.overrides))
        signals = jax.tree_util.tree_map(
            lambda s, n: jnp.where(carry.offset == 0.0, n, s), carry.signals, piece.signals
        )
        impact = tuple(i & ~cut for i in planned.impact)
        # A piece ends on the surface where it is cut at a crossing of F_lim or a sliding exit, or
        # where its plan ended it at a switch.
        surface = jnp.stack(
            [
                jnp.where(cut, e.found & (e.time <= tau) & (e.switch != Switch.FREE), at_switch)
                for e, at_switch in zip(events, planned.at_switch)
            ]
        )
        # The next piece holds the switch of a robot whose sliding ended here, as it left the surface.
        kept = tuple(jnp.where(cut & x.found & (x.time <= tau), x.switch, Switch.FREE) for x in exits)
        carry = Progress(rows_cut, carry.remaining - h, carry.offset + h, impact, kept, F_end, signals)
        return carry, (h, piece.signals.F, F_end, surface, jnp.stack(impact))

    def skip(carry: Progress, j):
        nothing = jnp.zeros_like(carry.F_end, bool)
        return carry, (0.0 * carry.remaining, carry.F_end, carry.F_end, nothing, nothing)

    def piece(carry: Progress, j):
        # One predicate for the whole batch; under `vmap` the cond becomes a select and both run.
        return jax.lax.cond(decided((carry.remaining > 0.0).any()), run, skip, carry, j)

    signals0 = model.Aux(*(jnp.stack([0.0 * remaining] * 2) for _ in model.Aux._fields))
    free_switch = jnp.full(remaining.shape, Switch.FREE)
    F0 = forces(touches(ps, rows, options))
    start = Progress(rows, remaining, 0.0 * remaining, (false, false), (free_switch, free_switch), F0, signals0)
    end, (h, starts, ends, surface, impact) = jax.lax.scan(piece, start, jnp.arange(PIECES))
    return end.rows, end.signals, Path(h / dt, starts, ends, surface, impact)


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
    description = (
        "the sliding-mode step for the hard switch, the default for it: its answer is the dt -> 0 limit at dt = 1e-3"
    )
    switches = ("hard",)
    default_for = ("hard",)
    converged_dt = {
        ("carry", "hard"): 2e-3,  # 16 of 16 samples, at 2e-3 and every finer step
        ("paper", "hard"): 1e-3,  # no sliding: forces within 1e-3 N of rk4 at 1e-4
    }

    def step(self, params, y, t, dt, scenario, options):
        return step(params, y, t, dt, scenario, options)

    def batch_order(self, params):
        """By body mass (stable): bodies of like mass meet their events at like times, so a slab of
        them runs a piece's later parts (`lax.cond` on the slab's need, `step`) less often. Each
        sample's answer does not depend on its neighbours, so the order changes no bit of it."""
        mass = np.asarray(params.M_b)
        return np.argsort(mass.reshape(-1, mass.shape[-1])[0], kind="stable")

    def observe(self, params, y, t, dt, scenario, options) -> model.Aux:
        return observe(params, y, t, dt, scenario, options)
