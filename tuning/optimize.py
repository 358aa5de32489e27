"""The multi-start gradient tuner: K starts in one batch, Adam on an augmented Lagrangian.

    init -> state;  a run is `tune`, which loops steps and saves a checkpoint after each.

Every step simulates all K starts at all M training masses as one batch of K * M trajectories of the
hard model, and differentiates it (forward or reverse mode). The starts are independent problems
side by side: each has its own multipliers, its own Adam moments (Adam is elementwise) and its own
step scale. A start whose loss or gradient is not finite (a step into an unstable loop) is not
moved by that gradient: it goes back halfway to its last finite iterate, and its step scale halves.

Each start remembers its best iterate that held the grip at every training mass; at the end those
and the final iterates are judged on validation masses, and the best one wins.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import time
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

import coopjax as cj
from coopjax.io import atomic_path
from coopjax.params import PARAMETERS, Params, split_name
from coopjax.progress import Progress
from tuning import constrained
from tuning.objective import GAINS, HOLD_TOLERANCE, Problem, from_log, log_bounds, terms, to_log

MODES = ("auto", "forward", "reverse")
# Forward mode costs about one primal run per tuned parameter on top of the primal, reverse mode
# (with per-step checkpointing) about 10 primal runs whatever the count, but compiles 2-3x longer:
# measured, forward wins below 4 parameters and in short runs, reverse at 8 and 14 (docs/tuning.md).
AUTO_FORWARD_UP_TO = 4
PAPER_GAINS = {n: PARAMETERS[n].default for n in GAINS}


@dataclasses.dataclass(frozen=True)
class TuneConfig:
    """Everything that fixes a tuning run's result. Stored in the checkpoint to guard --resume."""

    problem: Problem = Problem()
    starts: int = 8  # K: starting points run as one batch
    steps: int = 40
    mode: str = "auto"  # "forward", "reverse", or "auto": forward up to 4 parameters
    seed: int = 0  # of the K - 1 random starts
    learning_rate: float = 0.3  # log units: Adam moves each log-parameter by about this per step
    beta2: float = 0.9  # Adam's second-moment decay: short memory, as the penalty's scale changes (docs/tuning.md)
    al_every: int = 3  # steps between multiplier updates
    rho: float = 10.0  # the initial penalty, 1 / N (of objective per N^2 of grip shortfall)
    spread: float = 2.5  # random starts: log-uniform within x/÷ e^spread of the first, inside the box
    max_retries: int = 6  # consecutive rejections before a start is frozen
    start: tuple = ()  # ((name, value), ...): the first start; a name not given starts at its default (Table 1)

    def validate(self) -> "TuneConfig":
        self.problem.validate()
        if self.mode not in MODES:
            raise ValueError(f"--mode must be one of {', '.join(MODES)}, not {self.mode!r}")
        for flag, value in (("--starts", self.starts), ("--steps", self.steps), ("--al-every", self.al_every)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{flag} is {value!r}: it must be a whole number, at least 1")
        for flag, value in (("--lr", self.learning_rate), ("--rho", self.rho)):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{flag} is {value:g}: it must be positive")
        if not (math.isfinite(self.spread) and self.spread >= 0):
            raise ValueError(f"--spread is {self.spread:g}: it must be 0 or more")
        start = self.start_values
        for n in self.problem.names:
            if not (start[n] > 0 and math.isfinite(start[n])):
                raise ValueError(f"the starting value of {n} is {start[n]:g}: it must be positive")
        return self

    @property
    def start_values(self) -> dict[str, float]:
        """The first start: `start` where it names a parameter, else the parameter's default."""
        given = dict(self.start)
        return {n: float(given.get(n, given.get(split_name(n)[0], PARAMETERS[split_name(n)[0]].default)))
                for n in self.problem.names}

    @property
    def resolved_mode(self) -> str:
        if self.mode != "auto":
            return self.mode
        return "forward" if len(self.problem.names) <= AUTO_FORWARD_UP_TO else "reverse"

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), sort_keys=True, default=list)


def make_optimizer(config: TuneConfig) -> optax.GradientTransformation:
    """Adam; the rate warms up over 10% of the run, then decays (cosine) to 10%."""
    schedule = optax.warmup_cosine_decay_schedule(
        init_value=0.2 * config.learning_rate, peak_value=config.learning_rate,
        warmup_steps=max(1, config.steps // 10), decay_steps=max(config.steps, max(1, config.steps // 10) + 1),
        end_value=0.1 * config.learning_rate,
    )
    return optax.adam(schedule, b2=config.beta2)


@functools.lru_cache(maxsize=8)
def value_and_grad_fn(problem: Problem, mode: str) -> Callable:
    """(theta (K, n), masses (M,), mult, base) -> (L (K,), dL/dtheta (K, n), Terms), jitted.

    The starts are separable (L_k depends on theta_k alone), so reverse mode takes the gradient of
    sum_k L_k, and forward mode pushes n tangents, one per parameter column of every start at once,
    one after another (`lax.map`; vmapped tangents ran 1.8x slower, measured).
    """

    def f(theta, masses, mult, base):
        t = terms(theta, base, problem, masses)
        return constrained.lagrangian(t.f, t.c, mult), t

    if mode == "forward":
        def vg(theta, masses, mult, base):
            n = theta.shape[1]
            basis = jnp.eye(n, dtype=theta.dtype)[:, None, :] * jnp.ones_like(theta)[None]  # (n, K, n)
            L, t = f(theta, masses, mult, base)
            tangents = jax.lax.map(lambda v: jax.jvp(lambda th: f(th, masses, mult, base)[0], (theta,), (v,))[1], basis)
            return L, tangents.T, t
    else:
        def vg(theta, masses, mult, base):
            (_, (L, t)), grad = jax.value_and_grad(lambda th: (lambda L, t: (L.sum(), (L, t)))(*f(th, masses, mult, base)),
                                                   has_aux=True)(theta)
            return L, grad, t
    return jax.jit(vg)


class TuneState(NamedTuple):
    """Everything a checkpoint holds; a resumed run continues from exactly here."""

    step: int  # steps applied so far
    theta: np.ndarray  # (K, n) log-parameters of the current iterates
    good: np.ndarray  # (K, n) each start's last iterate with a finite loss and gradient
    scale: np.ndarray  # (K,) step scale of each start (halves on each rejection)
    retries: np.ndarray  # (K,) consecutive rejections; a start at max_retries is frozen
    opt_state: optax.OptState
    mult: constrained.Multipliers
    best_theta: np.ndarray  # (K, n) best iterate that held the grip at every training mass
    best_f: np.ndarray  # (K,) its objective (inf: none yet)
    history: dict  # per step: f, worst shortfall, L (each a list of K), trajectories, wall time
    trajectories: int  # simulated (parameter set, mass) trajectories so far
    elapsed: float  # s of tuning so far, summed over resumed sessions


def starting_points(config: TuneConfig, base: Params) -> np.ndarray:
    """The first start, then K - 1 log-uniform draws near it, each stable at the training step.

    A draw whose linearised loop needs dt below 1.5 x the training step is drawn again (up to 50
    rounds), so no start begins where its very first step would blow up.
    """
    from coopjax.stability import fastest_modes, max_stable_dt

    names, K = config.problem.names, config.starts
    lo, hi = log_bounds(names)
    first = np.clip(to_log(config.start_values, names), lo, hi)
    rng = np.random.default_rng(config.seed)
    points = [first]
    a, b = np.maximum(lo, first - config.spread), np.minimum(hi, first + config.spread)
    for _ in range(50):
        if len(points) >= K:
            break
        draws = a + (b - a) * rng.random((4 * K, len(names)))
        params = base.replace(M_b=np.ones(len(draws)), **{n: np.exp(draws[:, i]) for i, n in enumerate(names)})
        limit = max_stable_dt(fastest_modes(params, config.problem.config))
        points += [d for d, ok in zip(draws, limit >= 1.5 * config.problem.dt) if ok]
    if len(points) < K:
        raise ValueError(f"found only {len(points)} stable starting points in 50 rounds; try a smaller --spread")
    return np.stack(points[:K])


def init(config: TuneConfig, base: Params) -> TuneState:
    theta = starting_points(config, base)
    K, n = theta.shape
    M = config.problem.n_masses
    history = {k: [] for k in ("step", "theta", "f", "holds", "shortfall", "L", "rejected", "trajectories", "wall")}
    return TuneState(0, theta, theta.copy(), np.ones(K), np.zeros(K, int),
                     make_optimizer(config).init(jnp.asarray(theta)), constrained.init((K, M), config.rho),
                     theta.copy(), np.full(K, np.inf), history, 0, 0.0)


def tune(config: TuneConfig, base: Params | None = None, checkpoint: str | None = None, resume: bool = False,
         log: Callable[[str], None] = print, stop_after: int | None = None, progress: bool = False) -> TuneState:
    """Run (or resume) a tuning run; returns the final state. Checkpoints after every step.

    `stop_after` ends the session after that many steps, as an interruption would (tests).
    """
    if not jax.config.jax_enable_x64:
        raise ValueError("tuning runs in float64: call jax.config.update('jax_enable_x64', True) first")
    config = config.validate()
    base = (base if base is not None else cj.make_params()).astype(jnp.float64)
    lo, hi = log_bounds(config.problem.names)
    optimizer = make_optimizer(config)
    vg = value_and_grad_fn(config.problem, config.resolved_mode)
    F_lim = float(np.asarray(base.F_lim).min())

    state = None
    if checkpoint and os.path.exists(checkpoint):
        if not resume:
            raise ValueError(f"{checkpoint} holds an earlier tuning run: add --resume to continue it, or delete it")
        state = load_checkpoint(checkpoint, config)
        log(f"resumed from {checkpoint} at step {state.step} of {config.steps}")
    if state is None:
        state = init(config, base)

    session_start = time.perf_counter() - state.elapsed
    bar = Progress(config.steps, True, "tune", "steps") if progress else None
    if bar:
        bar.done = state.step
    done_this_session = 0
    K = config.starts
    while state.step < config.steps:
        if stop_after is not None and done_this_session >= stop_after:
            break
        k = state.step
        masses = config.problem.training_masses(config.seed, k)
        L, grad, t = vg(jnp.asarray(state.theta), jnp.asarray(masses), state.mult, base)
        L, grad, f, c = (np.asarray(x) for x in (L, grad, t.f, t.c))
        min_grip = np.asarray(t.metrics.min_grip).min(1)
        ok = np.isfinite(L) & np.isfinite(grad).all(1) & np.isfinite(c).all(1)
        holds = ok & (min_grip >= F_lim - HOLD_TOLERANCE)
        better = holds & (f < state.best_f)
        best_theta = np.where(better[:, None], state.theta, state.best_theta)
        best_f = np.where(better, f, state.best_f)

        # Rejected starts go back halfway to their last finite iterate; frozen ones stay there.
        retries = np.where(ok, 0, state.retries + 1)
        frozen = retries > config.max_retries
        scale = np.where(ok, state.scale, state.scale / 2)
        updates, opt_state = optimizer.update(jnp.asarray(np.where(ok[:, None], grad, 0.0)), state.opt_state)
        good = np.where(ok[:, None], state.theta, state.good)
        halfway = (state.theta + good) / 2
        theta = np.where(ok[:, None], state.theta + np.asarray(updates) * scale[:, None],
                         np.where(frozen[:, None], good, halfway))
        theta = np.clip(theta, lo, hi)
        mult = state.mult
        if (k + 1) % config.al_every == 0:
            new = constrained.update(mult, jnp.asarray(np.where(ok[:, None], c, 0.0)))
            mult = jax.tree_util.tree_map(lambda a, b: jnp.where(jnp.asarray(ok).reshape((K,) + (1,) * (a.ndim - 1)), a, b),
                                          new, mult)
        elapsed = time.perf_counter() - session_start
        trajectories = state.trajectories + K * config.problem.n_masses
        h = state.history
        for name, value in (("step", k), ("theta", state.theta.tolist()), ("f", _list(f)), ("holds", holds.tolist()),
                            ("shortfall", _list(c.max(1))), ("L", _list(L)), ("rejected", int((~ok).sum())),
                            ("trajectories", trajectories), ("wall", elapsed)):
            h[name].append(value)
        state = TuneState(k + 1, theta, good, scale, retries, opt_state, mult, best_theta, best_f, h, trajectories,
                          elapsed)
        done_this_session += 1
        if checkpoint:
            save_checkpoint(checkpoint, config, state)
        if bar:
            bar.update(1)
        else:
            i = int(np.argmin(np.where(holds, f, np.inf))) if holds.any() else None
            best = f"best holding start {i}: f {f[i]:.4g} N" if i is not None else "no start holds yet"
            log(f"step {k + 1:4d}/{config.steps}  {int(holds.sum())}/{K} starts hold at every training mass, "
                f"{int((~ok).sum())} rejected; {best}")
    return state


def candidates(state: TuneState, names) -> list[dict]:
    """Each start's best holding iterate (where it has one) and its final iterate."""
    out = []
    for k in range(state.theta.shape[0]):
        if np.isfinite(state.best_f[k]):
            out.append(from_log(state.best_theta[k], names))
        out.append(from_log(state.theta[k], names))
    return out


def _list(x) -> list:
    return [float(v) for v in np.asarray(x)]


# ----------------------------------------------------------------------------------------------
# Checkpoints: one .npz, written atomically


def save_checkpoint(path: str, config: TuneConfig, state: TuneState) -> None:
    leaves = jax.tree_util.tree_leaves(state.opt_state)
    arrays = {f"opt_{i}": np.asarray(x) for i, x in enumerate(leaves)}
    arrays.update({f"mult_{k}": np.asarray(v) for k, v in state.mult._asdict().items()})
    meta = dict(config=config.to_json(), step=state.step, trajectories=state.trajectories, elapsed=state.elapsed,
                history=state.history)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, theta=state.theta, good=state.good, scale=state.scale, retries=state.retries,
                     best_theta=state.best_theta, best_f=state.best_f,
                     meta=np.frombuffer(json.dumps(meta).encode(), np.uint8), **arrays)


def load_checkpoint(path: str, config: TuneConfig) -> TuneState:
    try:
        data = np.load(path)
        meta = json.loads(bytes(data["meta"]).decode())
    except Exception as error:  # a foreign or damaged file: say so rather than crash
        raise ValueError(f"--resume: {path} is not a coopjax tuning checkpoint ({error})") from None
    if meta.get("config") != config.to_json():
        raise ValueError(f"--resume: {path} belongs to a run with other options; use the same flags, or delete it")
    template = make_optimizer(config).init(jnp.asarray(data["theta"]))
    treedef = jax.tree_util.tree_structure(template)
    opt_state = jax.tree_util.tree_unflatten(treedef, [jnp.asarray(data[f"opt_{i}"]) for i in range(treedef.num_leaves)])
    mult = constrained.Multipliers(*(jnp.asarray(data[f"mult_{k}"]) for k in constrained.Multipliers._fields))
    return TuneState(meta["step"], data["theta"], data["good"], data["scale"], data["retries"], opt_state, mult,
                     data["best_theta"], data["best_f"], meta["history"], meta["trajectories"], meta["elapsed"])
