"""The gradient tuner: optax Adam on log-gains, surrogate annealing, checkpoints, rejected steps.

    init -> state;  step(state) -> state;  a run is `tune`, which loops `step` and saves a checkpoint.

Each step draws a fresh stratified batch of body masses from a key derived from (seed, step), so a
resumed run draws exactly what an uninterrupted one would. A step whose loss or gradient is not
finite is never applied: the previous move is halved and the step is tried again.
"""

from __future__ import annotations

import dataclasses
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
from coopjax.params import Params
from coopjax.progress import Progress
from tuning.objective import (GAINS, NARROW, WIDE, Objective, Surrogate, draw_masses, from_log, held_out_masses,
                              log_bounds, to_log, training_loss)

MODES = ("forward", "reverse")
PAPER_GAINS = {n: cj.params.PARAMETERS[n].default for n in GAINS}
MAX_SKIPS = 3  # consecutive skipped steps before a run gives up
CHECK_WIDTHS = Surrogate(k_F=1.0, k_c=1.0, eps_delta=5e-4)  # where the loss is smooth on the scale of h


@dataclasses.dataclass(frozen=True)
class TuneConfig:
    """Everything that fixes a tuning run's result. Stored in the checkpoint to guard --resume."""

    objective: Objective = Objective()
    masses: tuple = ("loguniform", 0.5, 5.0)  # the range the gains must hold over (and are judged on)
    margin: float = 0.15  # training draws span [low / (1 + margin), high (1 + margin)]
    batch: int = 16
    steps: int = 60
    mode: str = "forward"  # forward: jacfwd, memory flat in the horizon; reverse: grad + checkpoint
    anneal: bool = True  # surrogate widths shrink WIDE -> NARROW; otherwise NARROW throughout
    anneal_fraction: float = 0.75  # share of the steps over which the widths shrink
    seed: int = 0
    learning_rate: float = 0.3  # peak rate, in log-gain units (Adam moves each log-gain by about this)
    clip: float = 1.0  # global-norm clip of the log-gain gradient
    max_retries: int = 8  # halvings of a rejected move before the run gives up
    start: tuple = tuple(PAPER_GAINS.items())  # ((name, value), ...): Table 1 by default

    def validate(self) -> "TuneConfig":
        self.objective.validate()
        if self.mode not in MODES:
            raise ValueError(f"--mode must be forward or reverse, not {self.mode!r}")
        if not isinstance(self.batch, int) or self.batch < 1:
            raise ValueError(f"--batch is {self.batch!r}: it must be a whole number of masses, at least 1")
        if not isinstance(self.steps, int) or self.steps < 1:
            raise ValueError(f"--steps is {self.steps!r}: it must be at least 1")
        if not (self.margin >= 0 and math.isfinite(self.margin)):
            raise ValueError(f"--margin is {self.margin:g}: it must be 0 or more")
        if not (self.learning_rate > 0 and math.isfinite(self.learning_rate)):
            raise ValueError(f"--lr is {self.learning_rate:g}: it must be positive")
        start = dict(self.start)
        missing = [n for n in self.objective.names if n not in start]
        if missing:
            raise ValueError(f"no starting value for {', '.join(missing)}")
        for n in self.objective.names:
            if not (start[n] > 0 and math.isfinite(start[n])):
                raise ValueError(f"the starting value of {n} is {start[n]:g}: it must be positive")
        return self

    def to_json(self) -> str:
        d = dataclasses.asdict(self)
        return json.dumps(d, sort_keys=True, default=list)

    @property
    def training_masses(self) -> tuple:
        """The drawn range: the judged range widened by the margin.

        The grip is lost first at the heaviest mass, right at the range's end, and training draws
        rarely land there; the optimiser then settles on the edge of the cliff where the surrogate
        and the hard model disagree by a little. Training a little beyond the range buys that back.
        """
        kind, low, high = self.masses
        return kind, low / (1.0 + self.margin), high * (1.0 + self.margin)

    def widths(self, step: int) -> Surrogate:
        """The surrogate widths at a step: wide to narrow, geometrically, then held."""
        if not self.anneal:
            return NARROW
        s = min(1.0, step / max(1.0, self.anneal_fraction * (self.steps - 1)))
        return WIDE.interpolate(NARROW, s)


def make_optimizer(config: TuneConfig) -> optax.GradientTransformation:
    """Adam with global-norm clipping; the rate warms up over 10% of the run, then decays (cosine)."""
    schedule = optax.warmup_cosine_decay_schedule(
        init_value=0.1 * config.learning_rate, peak_value=config.learning_rate,
        warmup_steps=max(1, config.steps // 10), decay_steps=config.steps, end_value=0.05 * config.learning_rate,
    )
    return optax.chain(optax.clip_by_global_norm(config.clip), optax.adam(schedule))


def value_and_grad_fn(objective: Objective, mode: str) -> Callable:
    """(theta, masses, widths, base) -> (loss, grad, per-mass metrics), jitted.

    forward: `jax.jacfwd`, one tangent per tuned gain; its memory does not grow with the horizon.
    reverse: `jax.grad`; the scanned step is under `jax.checkpoint`, so only the carry is stored.
    """

    def f(theta, masses, widths, base):
        loss, metrics = training_loss(theta, masses, widths, base, objective)
        return loss, (loss, metrics)

    if mode == "forward":
        def vg(theta, masses, widths, base):
            grad, (loss, metrics) = jax.jacfwd(f, has_aux=True)(theta, masses, widths, base)
            return loss, grad, metrics
    else:
        def vg(theta, masses, widths, base):
            (loss, (_, metrics)), grad = jax.value_and_grad(f, has_aux=True)(theta, masses, widths, base)
            return loss, grad, metrics
    return jax.jit(vg)


def loss_fn(objective: Objective) -> Callable:
    return jax.jit(lambda theta, masses, widths, base: training_loss(theta, masses, widths, base, objective)[0])


class TuneState(NamedTuple):
    """Everything a checkpoint holds; a resumed run continues from exactly here."""

    step: int  # steps applied so far
    theta: np.ndarray  # log-gains of the current iterate
    theta_prev: np.ndarray  # the iterate the last applied move started from
    move: np.ndarray  # that move, theta - theta_prev (halved on each rejection)
    opt_state: optax.OptState
    key: np.ndarray  # the run's PRNG key data; step keys are fold_in(key, step)
    history: dict  # per applied step: loss, trajectories, wall time, gains, widths, rejections
    trajectories: int  # simulated (gain set, mass) trajectories so far, gradient checks included
    elapsed: float  # s of tuning so far, summed over resumed sessions


def init(config: TuneConfig) -> TuneState:
    names = config.objective.names
    lo, hi = log_bounds(names)
    theta = np.clip(to_log(dict(config.start), names), lo, hi)
    opt_state = make_optimizer(config).init(jnp.asarray(theta))
    key = np.asarray(jax.random.key_data(jax.random.key(config.seed)))
    history = {k: [] for k in ("step", "loss", "trajectories", "wall", "rejected", "k_F", "k_c", "eps_delta")}
    history.update({n: [] for n in names})
    return TuneState(0, theta, theta, np.zeros_like(theta), opt_state, key, history, 0, 0.0)


def step_masses(config: TuneConfig, state: TuneState, step: int):
    key = jax.random.fold_in(jax.random.wrap_key_data(jnp.asarray(state.key)), step)
    return draw_masses(key, config.training_masses, config.batch)


class Rejected(RuntimeError):
    pass


def tune(config: TuneConfig, base: Params | None = None, checkpoint: str | None = None, resume: bool = False,
         log: Callable[[str], None] = print, stop_after: int | None = None, check_gradient: bool = True,
         progress: bool = False) -> TuneState:
    """Run (or resume) a tuning run; returns the final state. Checkpoints after every step.

    `stop_after` ends the session after that many applied steps, as an interruption would (tests).
    """
    if not jax.config.jax_enable_x64:
        raise ValueError("tuning runs in float64: call jax.config.update('jax_enable_x64', True) first")
    config = config.validate()
    base = (base if base is not None else cj.make_params()).astype(jnp.float64)
    names = config.objective.names
    lo, hi = log_bounds(names)
    optimizer = make_optimizer(config)
    vg = value_and_grad_fn(config.objective, config.mode)

    state = None
    if checkpoint and os.path.exists(checkpoint):
        if not resume:
            raise ValueError(f"{checkpoint} holds an earlier tuning run: add --resume to continue it, or delete it")
        state = load_checkpoint(checkpoint, config)
        log(f"resumed from {checkpoint} at step {state.step} of {config.steps}")
    if state is None:
        state = init(config)
        if check_gradient:
            state = state._replace(trajectories=state.trajectories + _gradient_check(config, state, base, vg, log))

    session_start = time.perf_counter() - state.elapsed
    bar = Progress(config.steps, True, "tune", "steps") if progress else None
    if bar:
        bar.done = state.step  # resumed steps count as done, not towards the rate
    applied_this_session = 0
    while state.step < config.steps:
        if stop_after is not None and applied_this_session >= stop_after:
            break
        k = state.step
        masses = step_masses(config, state, k)
        widths = jnp.asarray(config.widths(k), jnp.float64)
        theta, rejected, skipped = state.theta, 0, False
        while True:
            loss, grad, _ = vg(jnp.asarray(theta), masses, widths, base)
            state = state._replace(trajectories=state.trajectories + config.batch)
            if np.isfinite(float(loss)) and np.isfinite(np.asarray(grad)).all():
                break
            if k == 0:
                raise Rejected(f"the loss or its gradient is not finite at the starting gains {from_log(theta, names)}; "
                               "try other starting gains or a smaller training --dt")
            rejected += 1
            if rejected > config.max_retries or not np.any(state.move):
                skipped = True
                break
            theta = np.clip(state.theta_prev + state.move * 0.5**rejected, lo, hi)
            log(f"step {k}: loss or gradient not finite; move rejected, retrying with it halved "
                f"({rejected}/{config.max_retries}) at {_fmt_gains(from_log(theta, names))}")
        if skipped:
            # Even the last good iterate fails on this batch of masses: the batch, not the move, is
            # the trouble. Keep the last good iterate, apply nothing, and go on to the next batch.
            run_of_skips = 1 + next((i for i, x in enumerate(reversed(state.history["loss"])) if np.isfinite(x)),
                                    len(state.history["loss"]))
            if run_of_skips >= MAX_SKIPS:
                raise Rejected(f"step {k}: {MAX_SKIPS} steps in a row are not finite even at the last good gains "
                               f"{_fmt_gains(from_log(state.theta_prev, names))}; try smaller --lr or a smaller "
                               "training --dt (the checkpoint keeps the last good step for --resume)")
            log(f"step {k}: not finite even after halving; this batch is skipped and the gains stay at the last good iterate")
            theta = theta_next = state.theta_prev
            opt_state, loss = state.opt_state, float("nan")
        else:
            updates, opt_state = optimizer.update(grad, state.opt_state, jnp.asarray(theta))
            theta_next = np.clip(theta + np.asarray(updates), lo, hi)
        elapsed = time.perf_counter() - session_start
        h = state.history
        for name, value in (("step", k), ("loss", float(loss)), ("trajectories", state.trajectories),
                            ("wall", elapsed), ("rejected", rejected), *config.widths(k)._asdict().items(),
                            *from_log(theta, names).items()):
            h[name].append(value)
        state = state._replace(step=k + 1, theta=theta_next, theta_prev=theta, move=theta_next - theta,
                               opt_state=opt_state, elapsed=elapsed)
        applied_this_session += 1
        if checkpoint:
            save_checkpoint(checkpoint, config, state)
        if bar:
            bar.update(1)
        else:
            log(f"step {k + 1:4d}/{config.steps}  loss {float(loss):10.4g}  {_fmt_gains(from_log(theta_next, names))}")
    return state


def _fmt_gains(gains: dict) -> str:
    return "  ".join(f"{n} {v:.4g}" for n, v in gains.items())


def _gradient_check(config, state, base, vg, log) -> int:
    """AD against central differences of the training loss at the start; returns trajectories used.

    It uses three light masses from the bottom of the range and the surrogate widths `CHECK_WIDTHS`.
    At the training widths (k_F <= 0.5 N) the surrogate's sliding layer makes the loss rough on the
    scale of any usable h (central differences then change sign from h = 1e-4 to 1e-6), so there they
    would measure that roughness rather than the AD; the same code is differentiated either way.
    """
    f = loss_fn(config.objective)
    kind, low, high = config.masses
    masses = jnp.asarray(held_out_masses((kind, low, low * (high / low) ** 0.3), 3))
    widths = jnp.asarray(CHECK_WIDTHS, jnp.float64)
    theta = jnp.asarray(state.theta)
    _, grad, _ = vg(theta, masses, widths, base)
    h = 1e-6
    fd = np.array([(float(f(theta.at[i].add(h), masses, widths, base)) - float(f(theta.at[i].add(-h), masses, widths, base))) / (2 * h)
                   for i in range(theta.shape[0])])
    grad = np.asarray(grad)
    scale = np.abs(fd).max() or 1.0
    log(f"gradient check ({config.mode} mode against central differences, h = {h:g} in log-gain) at the starting "
        f"gains, masses {', '.join(f'{m:.3g}' for m in np.asarray(masses))} kg, k_F = {CHECK_WIDTHS.k_F:g} N:")
    for name, g, d in zip(config.objective.names, grad, fd):
        log(f"  d loss / d log {name:<6} AD {g: .6e}   FD {d: .6e}   |AD - FD| / max|FD| = {abs(g - d) / scale:.1e}")
    return len(masses) * (1 + 2 * theta.shape[0])


# ----------------------------------------------------------------------------------------------
# Checkpoints: one .npz, written atomically


def save_checkpoint(path: str, config: TuneConfig, state: TuneState) -> None:
    leaves = jax.tree_util.tree_leaves(state.opt_state)
    arrays = {f"opt_{i}": np.asarray(x) for i, x in enumerate(leaves)}
    meta = dict(config=config.to_json(), step=state.step, trajectories=state.trajectories, elapsed=state.elapsed,
                history=state.history)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, theta=state.theta, theta_prev=state.theta_prev, move=state.move, key=state.key,
                     meta=np.frombuffer(json.dumps(meta).encode(), np.uint8), **arrays)


def load_checkpoint(path: str, config: TuneConfig) -> TuneState:
    try:
        data = np.load(path)
        meta = json.loads(bytes(data["meta"]).decode())
    except Exception as error:  # a foreign or damaged file: say so rather than crash
        raise ValueError(f"--resume: {path} is not a coopjax tuning checkpoint ({error})") from None
    if meta["config"] != config.to_json():
        raise ValueError(f"--resume: {path} belongs to a run with other options; use the same flags, or delete it")
    template = init(config).opt_state
    treedef = jax.tree_util.tree_structure(template)
    leaves = [jnp.asarray(data[f"opt_{i}"]) for i in range(treedef.num_leaves)]
    opt_state = jax.tree_util.tree_unflatten(treedef, leaves)
    return TuneState(meta["step"], data["theta"], data["theta_prev"], data["move"], opt_state, data["key"],
                     meta["history"], meta["trajectories"], meta["elapsed"])
