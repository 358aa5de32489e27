"""Adam on an augmented Lagrangian: K starts in one batch, exact gradients of the hard model.

Each start is its own problem side by side: its own multipliers, Adam moments and step scale. A start
whose loss or gradient is not finite goes back halfway to its last finite iterate and halves its step
scale; after `max_retries` rejections in a row it is frozen there. Each start keeps its best iterate
that met every requirement at every training draw; those and the final iterates are its candidates.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from coopjax.errors import InputError
from tuning import constrained
from tuning.tuners.base import Query, Tuner, register, setting, worst_constraint

# Forward mode's cost grows with the number of tuned parameters, reverse mode's does not, but it
# compiles longer: measured, forward wins below 4 parameters and in short runs, reverse at 8 and 14
# (the derivative cost table of docs/tuning.md, `python -m benchmarks.derivative_cost`).
AUTO_FORWARD_UP_TO = 4
MODES = ("auto", "forward", "reverse")


class State(NamedTuple):
    step: int  # steps applied so far
    theta: np.ndarray  # (K, n) log-parameters of the current iterates
    good: np.ndarray  # (K, n) each start's last iterate with a finite loss and gradient
    scale: np.ndarray  # (K,) step scale of each start (halves on each rejection)
    retries: np.ndarray  # (K,) consecutive rejections; a start beyond max_retries is frozen
    opt_state: optax.OptState
    mult: constrained.Multipliers
    best_theta: np.ndarray  # (K, n) best iterate that met every requirement at every training draw
    best_f: np.ndarray  # (K,) its objective (inf: none yet)
    history: dict  # per step: f, holds, worst shortfall, L (each a list over starts), rejected
    seed: int
    problem: object


def _lagrangian(problem, f, c, mult):
    return constrained.lagrangian(f, c, mult)


@register
@dataclasses.dataclass(frozen=True)
class AdamAL(Tuner):
    """Adam (optax) on the augmented Lagrangian of the problem, `steps` steps from each start."""

    name = "gradient"
    description = "Adam on an augmented Lagrangian, exact gradients of the hard model, K starts in one batch"
    uses_gradient = True
    scalar = staticmethod(_lagrangian)
    plain_run = True

    steps: int = setting(40, "optimiser steps", "--steps")
    mode: str = setting("auto", "forward, reverse, or auto: forward up to 4 parameters, reverse above", "--mode", MODES)
    # Adam moves each log-parameter by about this per step.
    learning_rate: float = setting(0.3, "peak learning rate, log units", "--lr")
    beta2: float = 0.9  # Adam's second-moment decay: short memory, as the penalty's scale changes (docs/tuning.md)
    al_every: int = setting(3, "steps between multiplier updates", "--al-every")
    rho: float = setting(10.0, "initial penalty of the augmented Lagrangian, 1/N", "--rho")
    max_retries: int = 6  # consecutive rejections before a start is frozen

    def __post_init__(self):
        if self.mode not in MODES:
            raise InputError(f"mode is {self.mode!r}: one of {', '.join(MODES)}", "mode")
        for field in ("steps", "al_every"):
            value = getattr(self, field)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise InputError(f"{field} is {value!r}: a whole number, at least 1", field)
        for field in ("learning_rate", "rho"):
            value = getattr(self, field)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise InputError(f"{field} is {value!r}: it must be positive", field)

    def history(self, state) -> dict:
        return state.history

    def resolved_mode(self, n_params: int) -> str:
        if self.mode != "auto":
            return self.mode
        return "forward" if n_params <= AUTO_FORWARD_UP_TO else "reverse"

    def optimizer(self) -> optax.GradientTransformation:
        """Adam; the rate warms up over 10% of the run, then decays (cosine) to 10%."""
        warmup = max(1, self.steps // 10)
        schedule = optax.warmup_cosine_decay_schedule(
            init_value=0.2 * self.learning_rate,
            peak_value=self.learning_rate,
            warmup_steps=warmup,
            decay_steps=max(self.steps, warmup + 1),
            end_value=0.1 * self.learning_rate,
        )
        return optax.adam(schedule, b2=self.beta2)

    def init(self, problem, starts, seed):
        theta = np.asarray(starts, np.float64)
        K = theta.shape[0]
        history = {k: [] for k in ("step", "theta", "f", "holds", "shortfall", "L", "rejected")}
        return State(
            0,
            theta,
            theta.copy(),
            np.ones(K),
            np.zeros(K, int),
            self.optimizer().init(jnp.asarray(theta)),
            constrained.init((K, problem.n_constraints(len(problem.training_draws()))), self.rho),
            theta.copy(),
            np.full(K, np.inf),
            history,
            seed,
            problem,
        )

    def ask(self, state):
        if state.step >= self.steps:
            return None
        return Query(
            state.theta,
            state.problem.training_draws(state.seed, state.step),
            "gradient",
            self.resolved_mode(state.theta.shape[1]),
            state.mult,
        )

    def tell(self, state, query, ev):
        K = state.theta.shape[0]
        lo, hi = state.problem.log_bounds()
        L, grad, f, c = ev.value, ev.gradient, ev.f, ev.c
        ok = np.isfinite(L) & np.isfinite(grad).all(1) & np.isfinite(c).all(1)
        holds = ok & ev.holds
        better = holds & (f < state.best_f)
        best_theta = np.where(better[:, None], state.theta, state.best_theta)
        best_f = np.where(better, f, state.best_f)
        # Rejected starts go back halfway to their last finite iterate; frozen ones stay there.
        retries = np.where(ok, 0, state.retries + 1)
        frozen = retries > self.max_retries
        scale = np.where(ok, state.scale, state.scale / 2)
        updates, opt_state = self.optimizer().update(jnp.asarray(np.where(ok[:, None], grad, 0.0)), state.opt_state)
        good = np.where(ok[:, None], state.theta, state.good)
        halfway = (state.theta + good) / 2
        theta = np.where(
            ok[:, None], state.theta + np.asarray(updates) * scale[:, None], np.where(frozen[:, None], good, halfway)
        )
        theta = np.clip(theta, lo, hi)
        mult = state.mult
        k = state.step
        if (k + 1) % self.al_every == 0:
            new = constrained.update(mult, jnp.asarray(np.where(ok[:, None], c, 0.0)))
            keep = lambda a, b: jnp.where(jnp.asarray(ok).reshape((K,) + (1,) * (a.ndim - 1)), a, b)
            mult = jax.tree_util.tree_map(keep, new, mult)
        h = {name: list(v) for name, v in state.history.items()}
        for name, value in (
            ("step", k),
            ("theta", state.theta.tolist()),
            ("f", _floats(f)),
            ("holds", holds.tolist()),
            ("shortfall", _floats(worst_constraint(ev))),
            ("L", _floats(L)),
            ("rejected", int((~ok).sum())),
        ):
            h[name].append(value)
        return state._replace(
            step=k + 1,
            theta=theta,
            good=good,
            scale=scale,
            retries=retries,
            opt_state=opt_state,
            mult=mult,
            best_theta=best_theta,
            best_f=best_f,
            history=h,
        )

    def plan_text(self, n_params, starts):
        return f"{starts} starts, {self.resolved_mode(n_params)} mode, {self.steps} steps"

    def progress_text(self, state, query, ev):
        i = int(np.argmin(np.where(ev.holds, ev.f, np.inf))) if ev.holds.any() else None
        best = f"best holding start {i}: f {ev.f[i]:.4g} N" if i is not None else "no start holds yet"
        return (
            f"step {state.step:4d}/{self.steps}  {int(ev.holds.sum())}/{len(ev.holds)} starts meet every requirement "
            "at every "
            f"training draw, {state.history['rejected'][-1]} rejected; {best}"
        )

    def expected_evaluations(self, starts):
        return self.steps

    def candidates(self, state):
        """Each start's best holding iterate (where it has one) and its final iterate."""
        out = []
        for k in range(state.theta.shape[0]):
            if np.isfinite(state.best_f[k]):
                out.append(state.best_theta[k])
            out.append(state.theta[k])
        return out


def _floats(x) -> list:
    return [float(v) for v in np.asarray(x)]
