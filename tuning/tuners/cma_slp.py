"""CMA-ES with its best candidate polished by exact-Jacobian linear programs, and injected back.

A population sees past the cliffs of this problem (the grip lost abruptly at heavy masses, impacts
in narrow bands of mass) but closes in on an optimum slowly, where the worst masses and the grip
constraint are active at once. A trust-region step on the worst case's epigraph (`screen_slp.program`,
with forward-mode Jacobians of every per-mass output) does that last part in a few iterations. So:

1. `every` generations of CMA-ES (the `CMAES` tuner: IPOP, cma's augmented Lagrangian, fresh draws
   each generation);
2. `polish` Sl1LP iterations from CMA-ES's best holding candidate (or from the last polished point,
   while CMA-ES has found nothing better), on the fixed training draws, with `radii` trial steps
   per iteration in one batch;
3. each accepted polished point is injected into CMA-ES's next population (`cma`'s `inject`), so the
   search distribution moves towards it; then back to 1.
"""

from __future__ import annotations

import copy
import dataclasses

import numpy as np

from tuning.tuners.base import Best, Query, Tuner, least_margin, register, worst_constraint
from tuning.tuners.cmaes import CMAES
from tuning.tuners.screen_slp import ScreenSLP, _outputs, merit, trial_steps, trust_update


@dataclasses.dataclass
class State:
    cma: object  # the CMAES tuner's state
    phase: str  # "cma", "jacobian" or "trials"
    draws: np.ndarray  # the polish's training draws
    problem: object
    generations: int = 0  # since the last polish
    theta: np.ndarray | None = None  # the polished iterate
    origin: np.ndarray | None = None  # the CMA-ES candidate the current polish started from
    radius: float = 0.0
    current: dict | None = None
    trials: np.ndarray | None = None  # (R, n)
    predicted: np.ndarray | None = None  # (R,)
    iterations: int = 0  # of the current polish
    best: Best = Best()  # the best polished point, by merit
    history: dict = dataclasses.field(default_factory=dict)


@register
@dataclasses.dataclass(frozen=True)
class CMAESPolished(Tuner):
    name = "CMA-ES+SLP"
    description = (
        "CMA-ES whose best candidate is polished by trust-region linear programs with exact Jacobians, and "
        "injected back into its population"
    )
    uses_gradient = True

    cma: CMAES = CMAES()
    every: int = 4  # CMA-ES generations between polishes
    polish: int = 2  # Sl1LP iterations (Jacobians) per polish
    # The local step, as in screen-SLP.
    radius: float = 0.25
    radii: int = 4
    max_radius: float = 1.0
    penalty: float = ScreenSLP.penalty
    swi_margin: float = ScreenSLP.swi_margin
    swi_penalty: float = ScreenSLP.swi_penalty
    accept: float = ScreenSLP.accept

    def _phi(self, out, state):
        return merit(out, state.problem, len(state.draws), self.penalty, self.swi_penalty, self.swi_margin)

    def init(self, problem, starts, seed):
        history = {k: [] for k in ("step", "f", "holds", "shortfall", "phi", "radius", "margin", "accepted")}
        return State(
            self.cma.init(problem, starts, seed),
            "cma",
            problem.fixed_training_draws(),
            problem,
            history=history,
        )

    def ask(self, state):
        if state.phase == "cma":
            return self.cma.ask(state.cma)
        if state.phase == "jacobian":
            return Query(state.theta[None].copy(), state.draws, "jacobian")
        return Query(state.trials.copy(), state.draws)

    def tell(self, state, query, ev):
        # The state told is never changed (`Tuner`): the next one starts as a copy (the problem shared).
        state = copy.deepcopy(state, {id(state.problem): state.problem, id(state.cma.problem): state.cma.problem})
        return {"cma": self._tell_cma, "jacobian": self._tell_jacobian, "trials": self._tell_trials}[state.phase](
            state, query, ev
        )

    def _tell_cma(self, state, query, ev):
        state.cma = self.cma.tell(state.cma, query, ev)
        state.generations += 1
        best = state.cma.best
        if state.generations >= self.every and best.holds:
            state.generations = 0
            if state.origin is None or not np.array_equal(best.theta, state.origin):
                state.origin = np.asarray(best.theta).copy()  # a new best from CMA-ES: polish it
                state.theta, state.radius = state.origin.copy(), self.radius
            if state.radius > 0:
                state.iterations, state.phase = 0, "jacobian"
        return state

    def _tell_jacobian(self, state, query, ev):
        out = _outputs(ev)
        ok = bool(ev.valid[0]) and all(np.isfinite(v).all() for v in out.values())
        phi = float(self._phi(out, state)[0]) if ok else np.inf
        self._keep(state, bool(ev.holds[0]), phi, state.theta)
        for key, value in (
            ("step", len(state.history["step"])),
            ("f", [float(ev.f[0])]),
            ("holds", [bool(ev.holds[0])]),
            ("shortfall", [float(worst_constraint(ev)[0])]),
            ("phi", [phi]),
            ("radius", [state.radius]),
            ("margin", [float(least_margin(ev)[0])]),
        ):
            state.history[key].append(value)
        if not ok:
            state.radius, state.phase = 0.0, "cma"
            return state
        here = {k: v[0] for k, v in out.items()} | {"phi": phi}
        state.current = here
        lo, hi = state.problem.log_bounds()
        state.trials, state.predicted = trial_steps(
            self, state.theta, here, state.radius, lo, hi, state.problem, len(state.draws)
        )
        if state.predicted[0] <= 0:  # converged: wait for a better CMA-ES candidate
            state.radius, state.phase = 0.0, "cma"
        else:
            state.phase = "trials"
        return state

    def _tell_trials(self, state, query, ev):
        out = _outputs(ev)
        ok = ev.valid & np.all([np.isfinite(v).reshape(len(ev.f), -1).all(1) for v in out.values()], axis=0)
        phi = np.where(ok, self._phi(out, state), np.inf)
        j, state.radius = trust_update(
            self, state.theta, state.radius, state.trials, state.predicted, state.current["phi"], phi, ok
        )
        state.iterations += 1
        state.history["accepted"].append([j is not None])
        if j is not None:
            state.theta = state.trials[j].copy()
            self._keep(state, bool(ev.holds[j]), float(phi[j]), state.theta)
            state.cma.es.inject([state.theta], force=True)  # CMA-ES's next population starts from it
            state.phase = "jacobian" if state.iterations < self.polish else "cma"
        else:
            state.phase = "jacobian" if state.iterations < self.polish and state.radius > 0 else "cma"
        return state

    @staticmethod
    def _keep(state, holds, phi, theta):
        state.best = state.best.told(holds, phi, theta)

    def history(self, state) -> dict:
        return state.history

    def candidates(self, state):
        polished = [state.best.theta] if state.best.theta is not None else []
        return polished + self.cma.candidates(state.cma)

    def plan_text(self, n_params, starts):
        return (
            f"CMA-ES from {starts} starts; every {self.every} generations its best polished by {self.polish} "
            f"Jacobian steps (forward mode, {n_params} tangents) and injected back"
        )
