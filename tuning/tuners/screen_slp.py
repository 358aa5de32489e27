"""A batched screen, then trust-region linear programs on the worst case's epigraph with exact
Jacobians: the simulator's two strengths, one after the other.

1. **Screen.** The given starts and `screen` more points in the box around the first start
   (x/÷ e^spread), run at every training draw in batches of the trials' shape (one compiled program
   for both). With `search="cma"` (the default) the first batch is the starts and scrambled-Sobol
   points, and every later batch is a generation of `strategies` CMA-ES runs side by side (the `cma`
   package: the batch shared between them, initial step `sigma0`, bounded by the box; the first from
   the first start, the others from random points of the box) minimising the merit phi below: the
   same number of runs as a Sobol screen, spent where the merit is low. With `search="sobol"` every point is a
   Sobol point. The `local` best of all points screened are kept, no two closer than `diverse` (log
   units, max norm), so the local solves do not all refine one basin; the next ones wait in a queue.
2. **Local solve.** The worst case over the draws has a kink wherever two draws are worst at once,
   and a gradient step on a smooth maximum zigzags across it. Its epigraph form has none (shown for
   the default problem; every `max` term gets its epigraph variable, a `cvar` term the
   Rockafellar-Uryasev form, a `mean` term stays linear, every requirement is a constraint per draw):

       minimise   t_peak + t_lag                            over (theta, t)
       subject to peak_m <= t_peak,  w lag_m <= t_lag,      at every training draw m
                  c_m <= 0,  min_swi_m >= swi_margin        (the requirements; the grip with authority to spare)

   Each iteration linearises every per-draw output with its exact Jacobian (forward mode, all
   tangents in one pass) and solves the linear program for the step within a trust region
   (|d|_inf <= r, and the box). The constraints are elastic, priced at `penalty` N per unit of
   violation (N for forces, mm for lengths) and `swi_penalty` N per unit of margin, so the program is
   feasible from any start. Why the margin: while the grip holds, the shortfall c is 0 and flat, so a
   linear model of c alone sees no constraint and steps to where the grip is lost. The least Filippov
   weight `min_swi` is the distance to that loss, with a derivative.
3. **Trials.** A Jacobian costs many primal runs, so each iteration tries the programs' steps at
   r, r/2, ... (`radii` of them) in one batch of values, and keeps the one with the lowest merit

       phi = sum_j weight_j over_j(metric_j) + penalty sum max(0, c) + swi_penalty sum max(0, swi_margin - min_swi)

   among those whose fall is at least `accept` of the predicted one. The radius doubles after a full
   step that matched its prediction, and drops below the shortest one tried when none is kept (Sl1LP:
   Fletcher and Sainz de la Maza, 1989, with several radii per model).

The draws are fixed for the whole run (`Problem.fixed_training_draws`: a grid with its ends, the heaviest mass
is where the grip is hardest), so every comparison is of the same function. The local solves run
side by side in one batch (lanes), each with its own radius; a lane whose program promises nothing
has converged and takes the screen's next point.
"""

from __future__ import annotations

import copy
import dataclasses
from typing import ClassVar

import numpy as np
from scipy.optimize import linprog
from scipy.stats import qmc

from coopjax.errors import InputError
from tuning.training import aggregate
from tuning.tuners.base import (
    Best,
    Evaluation,
    Query,
    Tuner,
    concatenate,
    least_margin,
    register,
    setting,
    violation,
    worst_constraint,
)
from tuning.tuners.cmaes import sample, strategy, told

SHORTEST = 1e-4  # log units: a trust region this small has converged
BAD = 1e6  # the merit CMA-ES is told for a point whose runs are not measured (x (1 + unmeasured))
FEASIBILITY = 1e3  # N of the polish's merit per unit of relative violation, where no solve holds


@dataclasses.dataclass
class State:
    phase: str  # "screen", then "jacobian" and "trials" in turn, then "done"
    step: int  # Jacobian evaluations told so far (local iterations)
    draws: np.ndarray  # (M, p) the training draws, fixed for the run
    starts: np.ndarray  # (K0, n) the given starts (screened with the Sobol points)
    theta: np.ndarray | None = None  # (K, n) each lane's iterate
    radius: np.ndarray | None = None  # (K,) its trust region, log units; 0: converged or dead
    current: dict | None = None  # outputs and Jacobians at theta, and phi (K,)
    trials: np.ndarray | None = None  # (K, R, n) the steps to try next, one per radius
    predicted: np.ndarray | None = None  # (K, R) the linear programs' predicted falls of phi there
    pending: np.ndarray | None = None  # (K,) the lane's iterate is new: its Jacobian comes next
    queue: list = dataclasses.field(default_factory=list)  # the screen's next best points, for refills
    best: list = dataclasses.field(default_factory=list)  # per local solve: its best point by merit (`Best`)
    lane: list = dataclasses.field(default_factory=list)  # which solve (index into best) each lane runs
    history: dict = dataclasses.field(default_factory=dict)
    screened: dict | None = None  # the screen's summary
    screen_all: np.ndarray | None = None  # (S, n) the screen's points
    screen_log: list = dataclasses.field(default_factory=list)  # its batches so far: (thetas, Evaluation)
    seed: int = 0
    problem: object = None
    es: tuple = ()  # search="cma": the screen's evolution strategies (rebuilt by replay on resume)
    polish_es: object = None  # the polish's evolution strategy
    polished: Best = Best()  # the polish's best point, by its merit (`polish_merit`)
    # No local solve met every requirement at every training draw: the polish minimises the judge's
    # violation first (`polish_merit`), and the objective only where it is 0.
    infeasible: bool = False
    generation: int = 0  # polish generations told
    until: int | None = None  # the polish ends after this many (None: the tuner's `polish`)
    resolved: bool = False  # the local solves ran again from the feasibility polish's answer (`resolve`)


def segments(problem, M: int) -> list[tuple[slice, str]]:
    """The objective terms' columns in an evaluation's `parts` for M draws, with each term's `over`."""
    out, at = [], 0
    for o, cols in zip(problem.minimise, problem.objective_columns(M)):
        out.append((slice(at, at + len(cols)), o.over))
        at += len(cols)
    return out


def merit(out: dict, problem, M: int, penalty, swi_penalty, swi_margin):
    """phi per candidate: the objective with hard aggregates, plus the priced violations."""
    phi = sum(np.asarray(aggregate(out["parts"][:, seg], over)) for seg, over in segments(problem, M))
    gap = np.maximum(0.0, swi_margin - out["swi"])
    return phi + penalty * np.maximum(out["c"], 0.0).sum(1) + swi_penalty * gap.sum(1)


def polish_merit(tuner, ev, problem, M: int, infeasible: bool = False) -> np.ndarray:
    """The polish's merit per candidate: the problem's objective with hard aggregates, `penalty` per
    unit of constraint violation, and half the local solves' grip margin (without one, the polish
    settles on the edge of losing the grip at the training draws, and loses it between them: measured
    on a 4-parameter uncertain box). A candidate whose runs are not measured gets a finite value
    above every measured one (`Evaluation.bad`).

    `infeasible` (no local solve met every requirement): `FEASIBILITY` x the judge's violation (the
    largest relative miss, `violation`) plus the objective. The sum of priced misses over the draws
    is not what the judge reports when requirements fight: it trades one draw's large miss for
    many small ones, and one requirement's miss for another's in N rather than relative to bound."""
    out = _outputs(ev)
    if infeasible:
        phi = FEASIBILITY * violation(ev) + merit(out, problem, M, 0.0, 0.0, 0.0)
    else:
        phi = merit(out, problem, M, tuner.penalty, tuner.swi_penalty, 0.5 * tuner.swi_margin)
    return np.where(ev.valid & np.isfinite(phi), phi, ev.bad(BAD))


def program(theta, out: dict, radius, lo, hi, problem, M, penalty, swi_penalty, swi_margin):
    """The trust-region linear program at one point (`out`: its outputs, Jacobians and merit phi):
    (d, predicted fall of phi).

    Variables: the step d; per `max` term its epigraph t; per `cvar:ALPHA` term the threshold eta
    and the excesses u of its k = ceil(ALPHA N) worst cases (Rockafellar-Uryasev); per constraint
    column its elastic e >= 0; per grip case its margin gap g >= 0. A `mean` term is linear in d.
        minimise  sum t + sum (eta + sum u / k) + mean terms + penalty sum e + swi_penalty sum g
        subject to  part + J d <= t (max), part + J d <= eta + u (cvar), c + J_c d <= e,
                    swi_margin - swi - J_swi d <= g, |d|_inf <= radius within the box.
    """
    n = len(theta)
    rows, rhs, cost, extra_bounds, const = [], [], [], [], 0.0
    blocks = []  # per auxiliary variable group: its size

    def add(count, price, bounds):
        start = n + sum(blocks)
        blocks.append(count)
        cost.extend(np.broadcast_to(price, (count,)).tolist())
        extra_bounds.extend([bounds] * count)
        return start

    linear = np.zeros(n)
    pending = []  # (J rows, part values, variable columns with -1) for inequality rows
    for seg, over in segments(problem, M):
        J, x = out["J_parts"][seg], out["parts"][seg]
        if over == "mean":
            linear += J.mean(0)
            const += float(x.mean())
        elif over == "max":
            t = add(1, 1.0, (None, None))
            pending.append((J, -x, [[t]] * len(x)))
        else:
            k = max(1, int(np.ceil(float(over.split(":")[1]) * len(x))))
            eta = add(1, 1.0, (None, None))
            u = add(len(x), 1.0 / k, (0.0, None))
            pending.append((J, -x, [[eta, u + i] for i in range(len(x))]))
    Q = out["c"].shape[0]
    if Q:
        e = add(Q, penalty, (0.0, None))
        pending.append((out["J_c"], -out["c"], [[e + i] for i in range(Q)]))
    G = out["swi"].shape[0]
    if G:
        g = add(G, swi_penalty, (0.0, None))
        pending.append((-out["J_swi"], out["swi"] - swi_margin, [[g + i] for i in range(G)]))
    size = n + sum(blocks)
    for J, b, minus in pending:
        block = np.zeros((len(b), size))
        block[:, :n] = J
        for i, cols in enumerate(minus):
            block[i, cols] = -1.0
        rows.append(block)
        rhs.append(b)
    c_vec = np.concatenate([linear, np.asarray(cost)])
    box = [(max(-radius, low - x), min(radius, high - x)) for x, low, high in zip(theta, lo, hi)]
    solution = linprog(
        c_vec,
        A_ub=np.concatenate(rows) if rows else None,
        b_ub=np.concatenate(rhs) if rhs else None,
        bounds=box + extra_bounds,
        method="highs",
    )
    if solution.status != 0:
        return np.zeros(n), 0.0
    return solution.x[:n], float(out["phi"] - (solution.fun + const))


def trial_steps(tuner, theta, here: dict, radius, lo, hi, problem, M):
    """One point's trials: the programs' steps at radius, radius / 2, ... (`tuner.radii` of them),
    with their predicted falls of phi; past the first radius whose program promises nothing, the
    trials stay at theta with a predicted fall of 0. `tuner` carries the merit's settings."""
    trials, predicted = np.repeat(theta[None], tuner.radii, 0), np.zeros(tuner.radii)
    for j in range(tuner.radii):
        d, fall = program(
            theta, here, radius / 2**j, lo, hi, problem, M, tuner.penalty, tuner.swi_penalty, tuner.swi_margin
        )
        if fall <= 1e-9 * max(1.0, abs(here["phi"])):  # nothing left to gain in the model
            break
        trials[j], predicted[j] = np.clip(theta + d, lo, hi), fall
    return trials, predicted


def trust_update(tuner, theta, radius, trials, predicted, phi_now, phi, ok):
    """The ratio test on one point's evaluated trials: (index of the trial taken or None, new radius).

    The best trial whose fall is at least `tuner.accept` of its prediction is taken; the radius
    doubles (up to `tuner.max_radius`) after a full step that matched its prediction, and drops
    below the smallest radius tried when none is taken (0 once below SHORTEST: converged)."""
    ratio = (phi_now - phi) / np.where(predicted > 0, predicted, 1.0)
    good = ok & (predicted > 0) & (ratio >= tuner.accept)
    radii = radius / 2.0 ** np.arange(len(trials))
    if not good.any():
        return None, (radii[-1] / 2 if radii[-1] / 2 >= SHORTEST else 0.0)
    j = int(np.argmin(np.where(good, phi, np.inf)))
    grow = j == 0 and ratio[j] > 0.75 and np.abs(trials[j] - theta).max() >= 0.99 * radii[0]
    return j, (min(2 * radii[j], tuner.max_radius) if grow else radii[j])


def diverse_best(thetas, phi, count, distance):
    """Indices of up to `count` finite-phi points, best first, no two within `distance` (max norm)."""
    chosen = []
    for i in np.argsort(phi, kind="stable"):
        if not np.isfinite(phi[i]):
            break
        if all(np.abs(thetas[i] - thetas[j]).max() >= distance for j in chosen):
            chosen.append(int(i))
        if len(chosen) == count:
            break
    return chosen


def _copied(state: State) -> State:
    """A deep copy of a state, sharing its problem (a state told is never changed: `Tuner`)."""
    return copy.deepcopy(state, {id(state.problem): state.problem})


def _outputs(ev) -> dict:
    out = {"parts": ev.parts, "c": ev.c, "swi": ev.min_swi}
    if ev.jacobian is not None:
        J = ev.jacobian
        out |= {"J_parts": J["parts"], "J_c": J["c"], "J_swi": J["min_swi"]}
    return out


def _central_differences(query, ev, K, h):
    """The query and evaluation that exact Jacobians would have given, from runs at each of K lanes
    and at +h and -h along each parameter (`ScreenSLP.ask` with jacobian="fd")."""
    n = query.thetas.shape[1]
    rows = lambda x: x.reshape((K, 2 * n + 1) + x.shape[1:])
    centre = lambda x: rows(x)[:, 0]
    slope = lambda x: np.moveaxis((rows(x)[:, 1 : n + 1] - rows(x)[:, n + 1 :]) / (2 * h), 1, -1)
    valid = rows(ev.valid).all(1)
    jac = {k: slope(getattr(ev, k)) for k in ("parts", "c", "min_swi", "f")}
    lanes = Evaluation(
        f=centre(ev.f),
        c=centre(ev.c),
        parts=centre(ev.parts),
        valid=valid,
        holds=centre(ev.holds) & valid,
        min_swi=centre(ev.min_swi),
        jacobian=jac,
    )
    return Query(centre(query.thetas), query.draws, "jacobian"), lanes


SEARCHES = ("cma", "sobol")


@register
@dataclasses.dataclass(frozen=True)
class ScreenSLP(Tuner):
    """A batched screen (CMA-ES or Sobol), then Sl1LP on the epigraph of the worst case from its best points."""

    name = "screen-SLP"
    description = (
        "a batched screen (CMA-ES generations), then trust-region linear programs on the worst case's "
        "epigraph with exact Jacobians (forward mode)"
    )
    uses_gradient = True
    plain_run = True
    # False: no local solve; the screen goes on, batch after batch, until the budget ends (`ScreenOnly`).
    local_solve: ClassVar[bool] = True

    screen: int = setting(
        2048,
        "points screened in the box x/÷ e^SPREAD around the first start, besides the starts (Sobol: a power of 2)",
        "--screen",
    )
    spread: float = 2.5  # the screen's box: x/÷ e^spread around the first start, within the search box
    search: str = setting(
        "cma",
        "the screen's points after its first batch: CMA-ES generations (cma) or Sobol points (sobol)",
        "--search",
        ("cma", "sobol"),
    )
    sigma0: float = 1.0  # search="cma": CMA-ES's initial step, log units
    # search="cma": independent evolution strategies sharing each batch of the screen, the first from
    # the first start, the others from random points of the screen's box (fewer where the batch has
    # not 2 points for each). One run of the screen often settles in a poor basin; two halves of the
    # batch are two chances (docs/tuning.md).
    strategies: int = 2
    local: int = setting(8, "local solves run side by side (lanes of one batch)", "--local")
    refills: int = 2  # the screen queues refills x local more points, for lanes whose solve has converged
    diverse: float = 0.5  # least distance between two local starts, log units (max norm)
    steps: int = setting(12, "Jacobian steps of the local solves", "--steps")
    polish: int = setting(
        16,
        "CMA-ES generations that polish the best local solve on the problem's own merit (half the grip "
        "margin), in batches of the screen's shape",
        "--polish",
    )
    # The polish's draws: `polish_finer` times the training draws, its population cut to keep the
    # screen's runs per batch. 2 helps where its best overfits the training draws (the default problem
    # at seeds 1 and 3) but did worse on five problems of the suite (docs/tuning.md), so 1.
    polish_finer: int = 1
    polish_sigma: float = 0.3  # the polish's initial step, log units
    # Where no local solve meets every requirement, the polish minimises the judge's violation (the
    # largest relative miss at any draw): from an initial step of `feasibility_sigma` log units, on
    # `feasibility_finer` times the training draws at the screen's population (so that many times its
    # runs). The least violation lies far from where the solves' priced merit ends, and on 8 draws the
    # polish found it between them (0.999 on the training draws, 1.97 on validation); docs/tuning.md.
    feasibility_sigma: float = 1.0
    feasibility_finer: int = 2
    resolve_sigma: float = 0.1  # the spread of the solves' starts around the feasibility polish's answer (`resolve`)
    polish_again: int = 8  # polish generations of a round that goes on with the judge's worst draws (`go_on`)
    radius: float = 0.25  # initial trust region, log units
    radii: int = 4  # steps tried per iteration, at radius, radius / 2, ... (values only: cheap beside a Jacobian)
    max_radius: float = 1.0
    penalty: float = 100.0  # N of merit per N of grip shortfall at one mass
    swi_margin: float = 0.1  # the least Filippov weight asked for at every training draw of the grip requirement
    swi_penalty: float = 20.0  # N of merit per unit of margin missing at one mass
    accept: float = 0.1  # least share of the predicted fall a step must achieve
    # "exact": forward-mode Jacobians; "fd": central differences of width fd_step (log units), 2n + 1
    # runs per lane, as a design optimiser without derivatives would take them (the ablation).
    jacobian: str = "exact"
    fd_step: float = 1e-3

    def largest_batch(self, n_params: int, starts: int) -> tuple[int, str]:
        lanes = self.local * (2 * n_params + 1 if self.jacobian == "fd" else self.radii)
        return max(
            (lanes, f"--local {self.local}"), (starts, f"--starts {starts}")
        )  # the screen runs in batches of the lanes' shape

    def kept_bytes(self, n_params: int, starts: int, draws: int) -> tuple[int, str]:
        # The screen's points and their evaluations (objective, constraints and margins per draw).
        return (self.screen + starts) * (n_params + 4 + 4 * draws) * 8 * 2, f"--screen {self.screen}"

    def _phi(self, out, state):
        return merit(out, state.problem, len(state.draws), self.penalty, self.swi_penalty, self.swi_margin)

    def __post_init__(self):
        if self.jacobian not in ("exact", "fd"):
            raise InputError(f"jacobian is {self.jacobian!r}: exact or fd", "jacobian")
        if self.search not in SEARCHES:
            raise InputError(f"search is {self.search!r}: {' or '.join(SEARCHES)}", "search")
        for field, least in (
            ("screen", 0),
            ("steps", 1),
            ("local", 1),
            ("strategies", 1),
            ("polish", 0),
            ("polish_finer", 1),
            ("feasibility_finer", 1),
        ):
            value = getattr(self, field)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
                raise InputError(f"{field} is {value!r}: a whole number, at least {least}", field)

    def history(self, state) -> dict:
        return state.history

    def init(self, problem, starts, seed):
        lo, hi = problem.log_bounds()
        starts = np.clip(np.asarray(starts, np.float64), lo, hi)
        draws = problem.fixed_training_draws()
        history = {k: [] for k in ("step", "f", "holds", "shortfall", "phi", "radius", "margin", "accepted")}
        history["margin_asked"] = [self.swi_margin]
        state = State("screen", 0, draws, starts, history=history, seed=seed, problem=problem)
        state.screen_all = self.screen_points(state)
        if self.search == "cma":
            a, b = self._box(state)
            x0 = np.random.default_rng(seed).uniform(a, b, (self._runs(), len(a)))
            x0[0] = state.starts[0]
            sizes = [len(part) for part in np.array_split(np.arange(self.local * self.radii), self._runs())]
            state.es = tuple(strategy(x, self.sigma0, a, b, seed + 1 + j, k) for j, (x, k) in enumerate(zip(x0, sizes)))
        return state

    def later_queries(self, state):
        # The local solves' Jacobians: the largest program of the run, compiled while the screen runs.
        if self.jacobian != "exact":
            return []
        jacobian = Query(np.repeat(state.starts[:1], self.local, axis=0), state.draws, "jacobian")
        if not self.polish or self.polish_finer == 1:  # the polish runs the screen's program
            return [jacobian]
        draws = state.problem.fixed_training_draws(self.polish_finer)
        return [jacobian, Query(np.repeat(state.starts[:1], self._population(state.problem, draws), 0), draws)]

    def _seeded(self, state) -> int:
        """search="cma": the screen's points before CMA-ES takes over, the given starts and Sobol points
        filling their last batch."""
        batch = self.local * self.radii
        return min(-(-len(state.starts) // batch) * batch, len(state.screen_all))

    def _runs(self) -> int:
        """search="cma": the screen's CMA-ES runs, at least 2 points each per generation."""
        return max(1, min(self.strategies, self.local * self.radii // 2))

    def _generation(self, state) -> np.ndarray:
        return np.concatenate([sample(es) for es in state.es])

    def _tell_strategy(self, state, thetas, phi, ev):
        values = np.where(np.isfinite(phi), phi, ev.bad(BAD))
        ends = np.cumsum([0] + [es.popsize for es in state.es])
        state.es = tuple(told(es, thetas[i:j], values[i:j].tolist()) for es, i, j in zip(state.es, ends, ends[1:]))

    def _sobol_count(self, starts: int) -> int:
        """Sobol points in the screen: at least `screen`, as many as fill the last batch."""
        batch = self.local * self.radii
        return -(-(starts + self.screen) // batch) * batch - starts

    def _box(self, state):
        """The screen's box (log units): x/÷ e^spread around the first start, within the search box."""
        return state.problem.log_box_around(state.starts[0], self.spread)

    def screen_points(self, state) -> np.ndarray:
        """The given starts, then the Sobol points in the screen's box."""
        a, b = self._box(state)
        count = self._sobol_count(len(state.starts))
        sobol = qmc.Sobol(d=len(a), scramble=True, seed=state.seed)
        u = sobol.random_base2(max(0, int(np.ceil(np.log2(max(count, 1))))))[:count]
        return np.concatenate([state.starts, a + (b - a) * u])

    def ask(self, state):
        if state.phase == "screen":
            # In batches of the trials' shape: one compiled program serves both.
            done, batch = sum(len(q) for q, _ in state.screen_log), self.local * self.radii
            if self.search == "cma" and done >= self._seeded(state):
                return Query(self._generation(state), state.draws)
            return Query(state.screen_all[done : done + batch], state.draws)
        if state.phase == "screen only":  # no local solve (the ablation): the screen goes on until the budget ends
            return Query(self._more_points(state), state.draws)
        if state.phase == "jacobian" and state.step < self.steps:
            if self.jacobian == "fd":  # each lane, then it moved by +h and -h along each parameter: values only
                K, n = state.theta.shape
                shifts = np.concatenate([np.zeros((1, n)), self.fd_step * np.eye(n), -self.fd_step * np.eye(n)])
                return Query((state.theta[:, None] + shifts[None]).reshape(-1, n), state.draws)
            # Copies: the log keeps the query, and the lanes' arrays change in place.
            return Query(state.theta.copy(), state.draws, "jacobian")
        if state.phase == "trials":
            return Query(state.trials.reshape(-1, state.trials.shape[-1]).copy(), state.draws)
        if state.phase == "polish":
            return Query(sample(state.polish_es), state.draws)
        return None

    def _more_points(self, state):
        """The next generation of the screen's CMA-ES, or the next batch of the same Sobol sequence."""
        if self.search == "cma":
            return self._generation(state)
        a, b = self._box(state)
        batch = self.local * self.radii
        sobol = qmc.Sobol(d=len(a), scramble=True, seed=state.seed)
        sobol.fast_forward(len(state.screen_all) - len(state.starts) + state.step * batch)
        return a + (b - a) * sobol.random(batch)

    def _tell_more(self, state, query, ev):
        _, ok, phi = self._ok_phi(state, ev)
        if self.search == "cma":
            self._tell_strategy(state, query.thetas, phi, ev)
        for i in range(len(phi)):
            self._keep_best(state, 0, ev.holds[i], phi[i], query.thetas[i])
        state.step += 1
        return state

    def tell(self, state, query, ev):
        # The state told is never changed (`Tuner`): the next one starts as a copy (the problem shared).
        state = _copied(state)
        if state.phase == "screen only":
            return self._tell_more(state, query, ev)
        tell = {"screen": self._tell_screen, "jacobian": self._tell_jacobian, "trials": self._tell_trials}
        state = (tell | {"polish": self._tell_polish})[state.phase](state, query, ev)
        if state.phase == "jacobian" and state.step >= self.steps:  # the local solves' steps are spent
            self._start_polish(state)
        return state

    def _ok_phi(self, state, ev):
        out = _outputs(ev)
        ok = ev.valid & np.all([np.isfinite(v).reshape(len(ev.f), -1).all(1) for v in out.values()], axis=0)
        return out, ok, np.where(ok, self._phi(out, state), np.inf)

    def _tell_screen(self, state, query, ev):
        if self.search == "cma" and sum(len(q) for q, _ in state.screen_log) >= self._seeded(state):  # a generation
            self._tell_strategy(state, query.thetas, self._ok_phi(state, ev)[2], ev)
        state.screen_log.append((query.thetas, ev))
        if sum(len(q) for q, _ in state.screen_log) < len(state.screen_all):
            return state
        thetas = np.concatenate([q for q, _ in state.screen_log])
        ev = concatenate([e for _, e in state.screen_log])
        query = Query(thetas, state.draws)
        state.screen_log = []
        _, ok, phi = self._ok_phi(state, ev)
        ranked = diverse_best(query.thetas, phi, self.local * (1 + self.refills), self.diverse)
        if not ranked:  # nothing ran: carry on from the given starts (their failure is reported)
            ranked = list(range(min(self.local, len(state.starts))))
        chosen, rest = ranked[: self.local], ranked[self.local :]
        self._start_solves(
            state,
            query.thetas[chosen].copy(),
            [Best(bool(ev.holds[i]), float(phi[i]), query.thetas[i].copy()) for i in chosen],
            [query.thetas[i].copy() for i in rest],
        )
        state.screened = {
            "points": len(query.thetas),
            "finite": int(ok.sum()),
            "holding": int((ok & ev.holds).sum()),
            "best_phi": float(np.min(phi)) if ok.any() else None,
        }
        state.phase = "jacobian" if self.local_solve else "screen only"
        return state

    def _start_solves(self, state, thetas, best, queue):
        """The local solves' lanes from `thetas` (each lane's `Best` so far in `best`), with `queue`
        for refills; each lane's Jacobian comes next."""
        state.theta, state.radius = thetas, np.full(len(thetas), self.radius)
        state.pending, state.queue = np.ones(len(thetas), bool), queue
        state.best, state.lane = best, list(range(len(thetas)))

    def _keep_best(self, state, k, holds, phi, theta):
        state.best[state.lane[k]] = state.best[state.lane[k]].told(holds, phi, theta)

    def _tell_jacobian(self, state, query, ev):
        if self.jacobian == "fd":
            query, ev = _central_differences(query, ev, len(state.theta), self.fd_step)
        out, ok, phi = self._ok_phi(state, ev)
        out["phi"] = phi
        state.current = out
        state.radius = np.where(ok, state.radius, 0.0)  # a lane whose iterate does not run is dead
        state.pending = np.zeros(len(ok), bool)
        for k in range(len(ok)):
            self._keep_best(state, k, ev.holds[k], phi[k], query.thetas[k])
        for key, value in (
            ("step", state.step),
            ("f", [float(x) for x in np.where(ok, ev.f, np.inf)]),
            ("holds", [bool(x) for x in ev.holds]),
            ("shortfall", [float(x) for x in worst_constraint(ev)]),
            ("phi", phi.tolist()),
            ("radius", state.radius.tolist()),
            ("margin", [float(x) for x in np.where(ok, least_margin(ev), np.nan)]),
        ):
            state.history[key].append(value)
        state.step += 1
        return self._plan(state)

    def _plan(self, state):
        """The next trials of every live lane (one per radius), and refills for converged lanes."""
        lo, hi = state.problem.log_bounds()
        K, n = state.theta.shape
        state.trials = np.repeat(state.theta[:, None], self.radii, 1)
        state.predicted = np.zeros((K, self.radii))
        cur = state.current
        for k in np.flatnonzero((state.radius > 0) & ~state.pending):
            here = {key: value[k] for key, value in cur.items()}
            state.trials[k], state.predicted[k] = trial_steps(
                self, state.theta[k], here, state.radius[k], lo, hi, state.problem, len(state.draws)
            )
            if state.predicted[k, 0] <= 0:  # converged
                state.radius[k] = 0.0
        for k in np.flatnonzero(state.radius <= 0):  # a converged (or dead) lane takes the screen's next point
            if not state.queue:
                break
            state.theta[k] = state.queue.pop(0)
            state.trials[k] = state.theta[k]
            state.radius[k], state.pending[k] = self.radius, True
            state.lane[k] = len(state.best)
            state.best.append(Best(False, np.inf, state.theta[k].copy()))
        if (state.predicted > 0).any():
            state.phase = "trials"
        elif state.pending.any():
            state.phase = "jacobian"
        else:
            self._start_polish(state)
        return state

    def _start_polish(self, state):
        """After the local solves: CMA-ES from their best point on the problem's own merit (the
        solves' merit asks for a grip margin the problem does not, and their linear models stall on
        peaks that jump between points), on `polish_finer` times the training draws (the same ones if 1)."""
        if self.polish == 0 or state.phase == "polish":
            state.phase = "done"
            return
        best = [b for b in state.best if np.isfinite(b.value)]
        if not best:
            state.phase = "done"
            return
        first = min(best, key=lambda b: (not b.holds, b.value)).theta
        state.infeasible = not any(b.holds for b in best)
        if state.infeasible:
            finer, sigma = self.feasibility_finer, self.feasibility_sigma
        else:
            finer, sigma = self.polish_finer, self.polish_sigma
        state.draws = state.problem.fixed_training_draws(finer)
        self._polish_from(state, first, state.seed + 2, sigma)

    def _population(self, problem, draws, infeasible: bool = False) -> int:
        """The polish's population: as many runs per batch as the screen's, over the polish's draws;
        where no solve holds, the screen's population."""
        if infeasible:
            return max(4, self.local * self.radii)
        return max(4, self.local * self.radii * len(problem.fixed_training_draws()) // len(draws))

    def _polish_from(self, state, theta, seed, sigma):
        """The polish's CMA-ES from `theta` over the search box, with initial step `sigma`."""
        lo, hi = state.problem.log_bounds()
        population = self._population(state.problem, state.draws, state.infeasible)
        state.polish_es = strategy(theta, sigma, lo, hi, seed, population)
        state.phase = "polish"

    def _tell_polish(self, state, query, ev):
        phi = polish_merit(self, ev, state.problem, len(state.draws), state.infeasible)
        state.polish_es = told(state.polish_es, query.thetas, phi.tolist())
        for i in range(len(phi)):
            if ev.valid[i]:
                state.polished = state.polished.told(ev.holds[i], phi[i], query.thetas[i])
        state.generation += 1
        if state.generation >= (self.polish if state.until is None else state.until):
            state.phase = "done"
        return state

    def go_on(self, state, theta, draws):
        """`polish_again` more generations of polish from `theta`, on the training draws with `draws` in: the
        fixed training draws can miss a narrow band of the box where the answer breaks (a peak of 90 N
        between masses where it stays under 55 N), which the judge's search between its draws finds.
        The candidates are then the new polish's best alone."""
        if self.polish_again == 0:
            return None
        state = _copied(state)
        # Each added draw takes the place of the training draw nearest it (max norm in the box's unit
        # coordinates): the runs keep their shapes, so nothing is compiled again (a new shape cost
        # 40 s of compiling on two scenarios), and that region of the box stays covered.
        draws = np.asarray(draws, np.float64).reshape(len(draws), -1)[: len(state.draws)]
        trained, added = state.problem.to_unit(state.draws), state.problem.to_unit(draws)
        state.draws, free = state.draws.copy(), list(range(len(state.draws)))
        for d, z in zip(draws, added):
            j = min(free, key=lambda i: np.abs(trained[i] - z).max())
            state.draws[j] = d
            free.remove(j)
        state.best, state.lane, state.polished = [], [], Best()
        self._polish_from(state, theta, state.seed + 3, self.polish_sigma)
        state.generation, state.until = 0, self.polish_again
        return state

    def polish_further(self, state, theta):
        """`polish` more generations of the same polish (its strategy goes on), whichever candidate was
        chosen: on some problems a longer polish generalises (the worst lag under a tight peak: 2.6
        against 6.3 mm after 64 generations, not 16, and at seed 1 from 5.7 mm, a local solve's
        answer that beat the 16 generations' best); on others it fits the training draws, and the
        validation keeps the answer before (`session.run`). The round's candidate is the polish's best.

        Where no local solve held and the feasibility polish's best holds at its training draws, the
        local solves run again instead, from that answer (`resolve`): the polish found the feasible
        set the screen missed, and minimising the objective inside it is the solves' work, not a
        shrunken strategy's (stiffness and mass at seed 1: 39.6 mm of lag after the polish)."""
        p = state.polished.theta
        if self.polish == 0 or state.polish_es is None or p is None:
            return None
        if state.infeasible and state.polished.holds and self.local_solve:
            return self.resolve(state, theta)
        state = _copied(state)
        state.best, state.lane = [], []
        state.phase, state.until = "polish", state.generation + self.polish
        return state

    def resolve(self, state, theta):
        """The local solves again, from `theta` and `local - 1` points around it (normal, `resolve_sigma`
        log units), on the training draws, then the plain polish from their best. The lanes keep the
        first solves' shape, so nothing is compiled again."""
        state = _copied(state)
        lo, hi = state.problem.log_bounds()
        rng = np.random.default_rng(state.seed + 5)
        thetas = np.clip(theta + rng.normal(0.0, self.resolve_sigma, (self.local, len(theta))), lo, hi)
        thetas[0] = theta
        state.draws = state.problem.fixed_training_draws()
        self._start_solves(state, thetas, [Best(False, np.inf, t.copy()) for t in thetas], [])
        state.phase, state.step, state.current = "jacobian", 0, None
        state.infeasible, state.polished, state.polish_es = False, Best(), None
        state.generation, state.until, state.resolved = 0, None, True
        return state

    def polish_afresh(self, state, theta):
        """A new polish of `polish` generations from `theta` (the chosen answer), from the polish's
        initial step: where the answer sits on the training step's stability limit, the run goes on
        at a finer step (`session.run`), and the strategy it had by then has shrunk its step too far
        to leave what the coarser step could measure (the paper's squeeze, peak bounded: 35.5 to 35.0 N
        going on, against 21.9 N trained at a quarter of the step). The candidates are then the new
        polish's best alone."""
        if self.polish == 0:
            return None
        state = _copied(state)
        state.best, state.lane, state.polished = [], [], Best()
        sigma = self.feasibility_sigma if state.infeasible else self.polish_sigma
        self._polish_from(state, theta, state.seed + 4, sigma)
        state.generation, state.until = 0, self.polish
        return state

    def _tell_trials(self, state, query, ev):
        _, ok, phi = self._ok_phi(state, ev)
        K, R, n = state.trials.shape
        ok, phi, holds = ok.reshape(K, R), phi.reshape(K, R), ev.holds.reshape(K, R)
        accepted = np.zeros(K, bool)
        for k in range(K):
            if state.predicted[k, 0] <= 0:
                continue
            for j in range(R):
                if state.predicted[k, j] > 0:
                    self._keep_best(state, k, holds[k, j], phi[k, j], state.trials[k, j])
            j, state.radius[k] = trust_update(
                self,
                state.theta[k],
                state.radius[k],
                state.trials[k],
                state.predicted[k],
                state.current["phi"][k],
                phi[k],
                ok[k],
            )
            if j is not None:
                state.theta[k] = state.trials[k, j]
                accepted[k] = True
        state.history["accepted"].append(accepted.tolist())
        state.pending = accepted
        if accepted.any():
            state.phase = "jacobian"
            return state
        return self._plan(state)

    def plan_text(self, n_params, starts):
        finer = f" on {self.polish_finer} x the draws" if self.polish_finer > 1 else ""
        polish = f", then {self.polish} CMA-ES generations of polish{finer}" if self.polish else ""
        return (
            f"a screen of {self._screen_text(starts)}, then {self.local} local solves side by side, "
            f"{self.steps} Jacobian steps (forward mode, {n_params} tangents){polish}"
        )

    def _screen_text(self, starts):
        batch, count = self.local * self.radii, self._sobol_count(starts)
        seeded = min(-(-starts // batch) * batch, starts + count)
        if self.search == "sobol" or seeded == starts + count:
            return f"{starts} starts + {count} Sobol points"
        runs = f"{self._runs()} CMA-ES runs side by side" if self._runs() > 1 else "CMA-ES"
        return (
            f"{starts} starts + {seeded - starts} Sobol points, then {(starts + count - seeded) // batch} "
            f"generations of {batch} ({runs})"
        )

    def progress_text(self, state, query, ev):
        text = self._progress_text(state, query)
        if state.phase == "polish" and state.generation == 0 and state.until is None:  # the polish starts now
            polish = (
                f"polish: CMA-ES from the best solve, {self.polish} generations of "
                f"{state.polish_es.popsize} on {len(state.draws)} training draws"
            )
            if state.infeasible:
                polish += (
                    f"; no solve meets every requirement, so it minimises the judge's violation, "
                    f"from an initial step of {self.feasibility_sigma:g} in log units"
                )
            text = polish if text is None else f"{text}\n{polish}"
        return text

    def run_text(self, state):
        if not state.infeasible:
            return None
        return (
            f"no solve held, so the polish minimised the judge's violation on {len(state.draws)} training "
            f"draws, from an initial step of {self.feasibility_sigma:g} in log units"
        )

    def _progress_text(self, state, query):
        if state.phase == "jacobian" and query.derivative is None and state.screened and state.step == 0:
            s = state.screened
            best = f"best merit {s['best_phi']:.4g} N" if s["best_phi"] is not None else "none ran"
            return (
                f"screen: {s['points']} points, {s['finite']} ran, "
                f"{s['holding']} meet every requirement at every training draw; {best}; "
                f"{len(state.theta)} local solves from the best distinct ones"
            )
        if query.derivative != "jacobian":
            return None
        phi = state.current["phi"]
        live = int((state.radius > 0).sum())
        best = min((b for b in state.best if b.holds), key=lambda b: b.value, default=None)
        text = f"best holding solve: merit {best.value:.4g} N" if best else "no solve holds yet"
        first = state.resolved and state.step == 1
        again = "the feasibility polish's answer holds: local solves again from it\n" if first else ""
        return again + (
            f"step {state.step:3d}/{self.steps}  merit of the lanes {np.nanmin(phi):.4g} to "
            f"{np.nanmax(phi[np.isfinite(phi)]) if np.isfinite(phi).any() else float('nan'):.4g} N, "
            f"{live} moving; {text}"
        )

    def expected_evaluations(self, starts):
        return (starts + self._sobol_count(starts)) // (self.local * self.radii) + 2 * self.steps + self.polish

    def candidates(self, state):
        """Each local solve's best evaluated point (holding first, then by merit); the given starts
        if nothing ran."""
        order = sorted(range(len(state.best)), key=lambda k: (not state.best[k].holds, state.best[k].value))
        out = [state.best[k].theta for k in order if np.isfinite(state.best[k].value)]
        if state.polished.theta is not None:
            out = out + [state.polished.theta]  # the selection on validation draws decides between them
        return out or list(state.starts)
