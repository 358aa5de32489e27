"""The evaluator every tuner shares: a `Query` in, an `Evaluation` out, on the problem's model.

An evaluation is two kinds of compiled program:

- **the runs**: per scenario, the batch of (candidate, draw) runs' metrics, with their forward
  tangents along the tuned parameters (a Jacobian) or their reverse-mode pull-back (a gradient).
  These programs depend on the scenario's training configuration, the tuned names and the batch
  shape, not on the problem's terms, so problems that differ only in what they minimise and require
  share them (and the compile cache keeps them between runs). The values alone (no derivative) run
  in the judge's program wherever the training step lies on its grid (`_judged`): the step is traced
  there, so training, validation, the verdict and the search between draws compile one program;
- **the problem's algebra** (`tuning.problem.combine`): aggregates, requirements, the tuner's scalar,
  and their derivatives with respect to the metrics: small programs, quick to compile.

The chain rule joins them. Each program is compiled once per kind and shape, ahead of the first
call, and its compile time kept apart from the clock, so that tuners are compared on the time they
spend evaluating. The batch is split over every local device inside the run programs
(`coopjax.devices.run`).
"""

from __future__ import annotations

import dataclasses
import functools
import threading
import time

import jax
import jax.numpy as jnp
import numpy as np

from coopjax import devices, evaluation
from coopjax.config import Config
from coopjax.params import ROBOTS, split_name
from coopjax.stability import stable_dt
from tuning.judging import JUDGE_BLOCK, judge_config, judged_metrics
from tuning.problem import Problem
from tuning.training import bound_values, combine, params_for, run_metrics
from tuning.tuners import Evaluation, Query

OUTPUTS = ("f", "c", "parts", "min_swi")  # what a Jacobian is taken of


def _direction(values: dict, name: str) -> dict:
    """d (the tuned leaves, by name) / d log(name): the named leaf's own value (one robot's row for
    `K_GP_L`), else 0."""
    base, robot = split_name(name)
    tangent = {k: jnp.zeros_like(v) for k, v in values.items()}
    leaf = values[base]
    if robot is None:
        tangent[base] = leaf
    else:
        rows = jnp.arange(leaf.shape[0]).reshape((-1,) + (1,) * (leaf.ndim - 1))
        tangent[base] = jnp.where(rows == ROBOTS.index(robot), leaf, 0.0)
    return tangent


@functools.lru_cache(maxsize=64)
def _runs(config: Config, kind: str | None, names: tuple, checkpoint):
    """The jitted runs of one scenario: params -> metrics; with kind "jvp" also their tangents
    (n, B) along each tuned name; with "vjp", (params, cotangents of the metrics) -> (n, B)."""

    def metrics(params):  # a name of its own in JAX's and XLA's logs and timers
        return run_metrics(config, params, checkpoint)

    if kind is None:
        return jax.jit(metrics)
    leaves = tuple(dict.fromkeys(split_name(n)[0] for n in names))  # the tuned names' own leaves

    def tuned(params):
        """The runs as a function of the tuned leaves alone, and those leaves (by name): every other
        leaf is a constant, so its tangent or cotangent is a symbolic zero and nothing computes its
        (zero) contribution."""
        moving = lambda *values: metrics(params.with_leaves(**dict(zip(leaves, values))))
        return moving, {k: params.leaves()[k] for k in leaves}

    if kind == "jvp":

        def jvp(params):
            # All n tangents through one forward pass (vmap).
            moving, values = tuned(params)
            directions = [_direction(values, n) for n in names]
            stacked = tuple(jnp.stack([d[k] for d in directions]) for k in leaves)
            primals = tuple(values.values())
            out, tangents = jax.vmap(lambda *d: jax.jvp(moving, primals, d), out_axes=(None, 0))(*stacked)
            return out, tangents

        return jax.jit(jvp)

    def vjp(params, cotangent):
        moving, values = tuned(params)
        out, pull = jax.vjp(moving, *values.values())
        grad = dict(zip(leaves, pull(cotangent)))
        return out, jnp.stack([_pick(grad, values, n) for n in names])

    return jax.jit(vjp)


def _pick(grad: dict, values: dict, name: str):
    """d / d log(name) from the gradient with respect to the tuned leaves (both by leaf name): (B,)."""
    base, robot = split_name(name)
    g, value = grad[base], values[base]
    if robot is not None:
        return (g * value)[ROBOTS.index(robot)]
    return g * value if g.ndim == 1 else (g * value).sum(0)


@functools.lru_cache(maxsize=64)
def _judged(problem: Problem, config: Config) -> Config | None:
    """The judge's configuration of a training run, where the two differ only in their step and
    metrics: the training values then run in the judge's shared program. Where the training step
    lies on the judge's grid (`coopjax.evaluation.grid`: the carry's 2 ms, the judge's 1 ms), that is
    the program validation, the verdict and the search between draws run, and one compile serves
    them all (values move by round-off, 1e-11 relative). None: the training run keeps a program of
    its own (a smooth surrogate)."""
    judged = judge_config(config.dt, config.scenario, judged_metrics(problem, config.scenario)).validate()
    plain = lambda c: dataclasses.replace(c, integrator=c.method, metrics=())
    if plain(config) != plain(judged) or not evaluation.shares_program(judged):
        return None
    return judged


@functools.lru_cache(maxsize=32)
def _algebra(problem: Problem, kind: str | None, scalar, K: int):
    """The problem's terms from the runs (and their derivatives with respect to the runs' metrics)."""

    def outputs(runs, bounds):
        t = combine(problem, runs, bounds, K)
        return dict(f=t.f, c=t.c, parts=t.parts, min_swi=t.min_swi), dict(
            holds=t.holds, finite=t.metrics["finite"], miss=t.miss
        )

    if kind is None:
        return jax.jit(lambda runs, bounds: outputs(runs, bounds))
    if kind == "jacobian":

        def jacobian(runs, tangents, bounds):
            # tangents: per scenario, metric -> (n, B); one jvp per tuned name (vmap).
            real = lambda r: outputs(r, bounds)[0]
            out, jac = jax.vmap(lambda t: jax.jvp(real, (runs,), (t,)), in_axes=(0,), out_axes=(None, 0))(tangents)
            return out, outputs(runs, bounds)[1], {k: jnp.moveaxis(v, 0, -1) for k, v in jac.items()}

        return jax.jit(jacobian)
    if kind == "forward":

        def forward(runs, tangents, bounds, weights):
            value = lambda r: scalar(problem, *(lambda t: (t.f, t.c))(combine(problem, r, bounds, K)), weights)
            L, dL = jax.vmap(lambda t: jax.jvp(value, (runs,), (t,)), out_axes=(None, 0))(tangents)
            return L, dL.T, outputs(runs, bounds)

        return jax.jit(forward)

    def reverse(runs, bounds, weights):
        # The candidates are separable (L_k depends on candidate k alone): the gradient of their sum.
        value = lambda r: scalar(problem, *(lambda t: (t.f, t.c))(combine(problem, r, bounds, K)), weights)
        L, pull = jax.vjp(value, runs)
        return L, pull(jnp.ones_like(L))[0], outputs(runs, bounds)

    return jax.jit(reverse)


class Evaluator:
    """Runs queries for one problem and base; counts trajectories and keeps compile time apart.
    `base` is every parameter the problem neither tunes nor draws (its fixed values are applied here)."""

    def __init__(self, problem: Problem, base, scalar=None, checkpoint: bool | str = True):
        self.problem, self.base, self.scalar, self.checkpoint = problem, problem.base(base), scalar, checkpoint
        self.compile_s = 0.0
        self.trajectories = 0
        self.programs: dict = {}  # every compiled program this evaluator called, by its key

    def _call(self, key, fn, args, execute: bool, clock: bool = True):
        """`fn` at `args`, compiled once per key and shapes in this process (`devices.compiled`; its
        compile time counted on `clock`); with execute False, only compiled, and the outputs' shapes
        returned."""
        start = time.perf_counter()
        executable = self.programs[key] = devices.compiled(fn, *args, key=key)
        if clock:
            self.compile_s += time.perf_counter() - start
        if execute:
            with devices.EXCLUSIVE:  # one multi-device program at a time (see `coopjax.devices`)
                return jax.block_until_ready(executable(*args))
        return jax.eval_shape(fn, *args)

    def _kinds(self, query: Query) -> tuple[str | None, str | None]:
        """(the runs' kind, the algebra's kind) of a query."""
        if query.derivative == "jacobian":
            return "jvp", "jacobian"
        if query.derivative == "gradient":
            return ("jvp", "forward") if query.mode == "forward" else ("vjp", "reverse")
        return None, None

    def _params(self, query: Query):
        thetas = np.asarray(query.thetas, np.float64)
        draws = np.asarray(query.draws, np.float64)
        draws = draws[:, None] if draws.ndim == 1 else draws
        params = params_for(self.base, self.problem, thetas, draws)
        return thetas.shape[0], len(draws), params

    def _runs(self, params, kind, execute, cotangents=None, clock=True) -> list:
        """Every scenario's runs: metrics (and tangents, or pulled-back gradients with `cotangents`)."""
        out = []
        for i, config in enumerate(self.problem.configs):
            judged = _judged(self.problem, config) if kind is None else None
            if judged is not None:
                out.append(self._judge_program(params, config, judged, execute, clock))
                continue
            fn = _runs(config, kind, self.problem.names, self.checkpoint)
            args = (params,) if kind != "vjp" else (params, cotangents[i])
            result = self._call(("runs", config, kind, self.problem.names, self.checkpoint), fn, args, execute, clock)
            # On the host: the runs' outputs are split over the devices, the algebra runs on one.
            out.append(jax.device_get(result) if execute else result)
        return out

    def _judge_program(self, params, config: Config, judged: Config, execute: bool, clock: bool):
        """A scenario's training values in the judge's program (`_judged`): its metrics, as floats."""
        start = time.perf_counter()
        # Compiled apart first, so that its compile time is counted as every program's is.
        program = evaluation.shared_runs(params, judged, JUDGE_BLOCK, compile_only=True)
        self.programs[("runs", judged, None, params.batch_shape)] = program
        if clock:
            self.compile_s += time.perf_counter() - start
        B = params.batch_shape[0]
        if not execute:
            return {n: jax.ShapeDtypeStruct((B,), params.dtype) for n in (*config.metrics, "finite")}
        out = evaluation.shared_runs(params, judged, JUDGE_BLOCK)
        return {n: out[n].astype(params.dtype) for n in (*config.metrics, "finite")}

    def warm_up(self, query: Query) -> None:
        """Compile for this query's kind and shapes now (not on anyone's clock)."""
        self._evaluate(query, execute=False)

    def prepare(self, queries) -> threading.Thread | None:
        """Compile for these queries' kinds and shapes in a background thread, while the run goes on
        (a tuner's later queries, `Tuner.later_queries`). Its compile time counts nowhere: what the
        run waits for it counts where the run asks for the program. An error is left to that call,
        which compiles again and meets it."""
        if not queries:
            return None

        def compile_all():
            for query in queries:
                try:
                    self._evaluate(query, execute=False, clock=False)
                except Exception:  # noqa: BLE001 (the run's own call raises it)
                    return

        thread = threading.Thread(target=compile_all, daemon=True, name="coopjax-prepare")
        thread.start()
        return thread

    def __call__(self, query: Query) -> Evaluation:
        return self._evaluate(query)

    def _evaluate(self, query: Query, execute: bool = True, clock: bool = True) -> Evaluation | None:
        run_kind, kind = self._kinds(query)
        K, M, params = self._params(query)
        bounds = bound_values(self.problem, params)
        scalar = self.scalar if kind in ("forward", "reverse") else None
        program = _algebra(self.problem, kind, scalar, K)
        algebra = lambda *args: self._call(("algebra", self.problem, kind, scalar, K), program, args, execute, clock)
        value = gradient = jac = None
        if run_kind is None:
            real, rest = algebra(self._runs(params, None, execute, clock=clock), bounds)
        elif kind == "jacobian":
            metrics, tangents = zip(*self._runs(params, "jvp", execute, clock=clock))
            real, rest, jac = algebra(list(metrics), list(tangents), bounds)
        elif kind == "forward":
            metrics, tangents = zip(*self._runs(params, "jvp", execute, clock=clock))
            value, gradient, (real, rest) = algebra(list(metrics), list(tangents), bounds, query.weights)
        else:  # the values, their cotangents from the algebra, then the pull-back through the runs
            runs = self._runs(params, None, execute, clock=clock)
            value, cotangents, (real, rest) = algebra(runs, bounds, query.weights)
            pulled = self._runs(params, "vjp", execute, cotangents, clock)
            # Per sample (n, K * M), start-major: each candidate's gradient sums over its draws.
            gradient = sum(g for _, g in pulled).reshape(-1, K, M).sum(2).T if execute else None
        if not execute:
            return None
        self.trajectories += K * M * len(self.problem.scenarios)
        real, rest, value, gradient, jac = jax.device_get((real, rest, value, gradient, jac))
        f, c, parts = np.asarray(real["f"]), np.asarray(real["c"]), np.asarray(real["parts"])
        # Every run of the candidate is measured (it did not diverge, its step is within its loop's
        # limit), and its objective and constraints are finite.
        finite = np.nan_to_num(np.asarray(rest["finite"], float), nan=0.0) > 0.5
        unmeasured = (~finite).mean(1) + self._beyond(params, K, M)
        valid = (unmeasured == 0) & np.isfinite(f) & np.isfinite(c).all(1) & np.isfinite(parts).all(1)
        return Evaluation(
            f=f,
            c=c,
            parts=parts,
            valid=valid,
            holds=valid & np.asarray(rest["holds"]).all(1),
            min_swi=np.asarray(real["min_swi"]),
            value=None if value is None else np.asarray(value),
            gradient=None if gradient is None else np.asarray(gradient),
            jacobian=None if jac is None else {k: np.asarray(v) for k, v in jac.items()},
            unmeasured=np.where(valid, 0.0, np.maximum(unmeasured, 1.0 / (M * len(self.problem.configs)))),
            miss=np.asarray(rest["miss"]),
        )

    def _beyond(self, params, K: int, M: int) -> np.ndarray:
        """(K,) per candidate, the mean over its runs of how far each run's training step is beyond
        its linearised loop's stability limit: 0 within it, 1 + log2(dt / limit) beyond, 4 with a
        growing mode. A value the training step cannot measure is not a value to train on."""
        out = np.zeros(K)
        for config in self.problem.configs:
            limit, growth = stable_dt(params, config)
            with np.errstate(divide="ignore"):
                over = np.where(config.dt > limit, 1.0 + np.log2(config.dt / np.maximum(limit, 1e-300)), 0.0)
            out += np.where(growth > 0, 4.0, np.minimum(over, 1e3)).reshape(K, M).mean(1)
        return out / len(self.problem.configs)
