"""The training algebra of a `Problem`: its objective and constraints as pure JAX functions of the
tuned log-parameters, for a batch of starts at a batch of draws, differentiable.

    minimise   f = sum_j weight_j * over_j(metric_j)                 over the draws x scenarios
    subject to c <= 0, one column per requirement and training draw

- In training a `max` term is a smooth maximum (`Problem.aggregate`, `temperature`), so the worst
  draw is pushed down, not the average one; judging takes the hard one (`aggregate` without a
  problem).
- A requirement's constraint is its slack with the sign turned (`Requirement.slack`), in the
  metric's unit except lengths, in mm (`SCALE`). The grip requirement `min_grip >= F_lim` is
  special: on F = F_lim the hard switch slides and min_grip sits exactly there, flat, so training
  uses the RMS shortfall below F_lim over the grip window, `c = sqrt(slip + eps^2) - eps` (zero
  while the grip holds, smooth, growing with the depth and duration of a loss).
- Parameters enter in log space, so every iterate is positive.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from scipy.stats import qmc

from coopjax import devices
from coopjax.config import Config
from coopjax.errors import InputError
from coopjax.objectives import METRICS
from coopjax.params import Params
from coopjax.simulation import metrics_of
from coopjax.stability import stable_dt
from tuning.problem import Problem, Requirement, columns_of, to_log

SCALE = {"m": 1e-3}  # a requirement's constraint is in its metric's unit, except lengths: in mm
EPS_DEFICIT = 0.01  # N: the smoothing of c = sqrt(slip + eps^2) - eps near 0


class Surrogate(NamedTuple):
    """Widths of the smooth switch and contact (docs/model.md, "Smooth surrogates"), with switch != 'hard'."""

    k_F: float  # N
    k_c: float  # N
    eps_delta: float  # m


NARROW = Surrogate(k_F=0.1, k_c=0.1, eps_delta=2e-5)


def params_for(base: Params, problem: Problem, theta, draws) -> Params:
    """Parameter sets for starts x draws: theta is (K, n) log-values, draws (M, p) values of the
    uncertain parameters (or (M,) of the one); batch K * M, sample k * M + m is start k at draw m.
    Per-robot names (`K_GP_L`) set one robot. `base` carries the fixed values (`Problem.base`)."""
    # NumPy for a NumPy theta (the evaluator's queries, on the host): no small program compiled per
    # batch shape for each of these operations, as JAX's eager ones are.
    xp = np if isinstance(theta, np.ndarray) else jnp
    K = theta.shape[0]
    draws = xp.asarray(draws, theta.dtype)
    draws = draws[:, None] if draws.ndim == 1 else draws
    M = draws.shape[0]
    values = {n: xp.repeat(xp.exp(theta[:, i]), M) for i, n in enumerate(problem.names)}
    values |= {u.name: xp.tile(draws[:, i], K) for i, u in enumerate(problem.uncertain)}
    if problem.switch != "hard":
        values |= {k: xp.full((K * M,), v, theta.dtype) for k, v in NARROW._asdict().items()}
    if "M_b" not in values:  # every leaf carries the batch
        values["M_b"] = xp.full((K * M,), np.asarray(base.M_b), theta.dtype)
    return base.replace(**values)


class Terms(NamedTuple):
    """Per start k: the objective f (K,) (N); the constraints c (K, Q), one column per requirement
    and draw (`Problem.constraint_columns`), satisfied at <= 0; the objective terms' weighted values
    per case, `parts` (K, P) (`Problem.objective_columns`, concatenated); the grip margin `min_swi`
    (K, G) at the grip requirement's cases; `holds` (K, Q), each requirement met by the judge's rule;
    `miss` (K, Q), how far each misses by the judge's measure (`Verdict.violation`: the shortfall
    beyond the tolerance over the bound's size, <= 0 when met; the grip's from `min_grip`, not from
    the training shortfall c); and every metric per case (K, S * M) (NaN where its scenario does
    not read it)."""

    f: jax.Array
    c: jax.Array
    parts: jax.Array
    min_swi: jax.Array
    holds: jax.Array
    metrics: dict
    miss: jax.Array


def aggregate(x, over: str, problem: Problem | None = None, axis=-1):
    """`over` of x along `axis`: max, mean or cvar:ALPHA. With a problem (training), a max is its
    `aggregate`: a smooth maximum by default."""
    if over == "mean":
        return x.mean(axis)
    if over.startswith("cvar"):
        alpha = float(over.split(":")[1]) if ":" in over else problem.cvar_alpha
        k = max(1, math.ceil(alpha * x.shape[axis]))
        return jnp.mean(jnp.sort(x, axis=axis)[..., -k:], axis=axis)
    if problem is None or problem.aggregate == "max":
        return x.max(axis)
    if problem.aggregate == "smoothmax":
        T = problem.temperature
        return T * jax.nn.logsumexp(x / T, axis=axis)
    return aggregate(x, problem.aggregate if problem.aggregate == "mean" else "cvar", problem, axis)


def deficit(slip):
    """c = sqrt(slip + eps^2) - eps: the RMS grip shortfall (N), smooth at 0 where sqrt is not."""
    return jnp.sqrt(slip + EPS_DEFICIT**2) - EPS_DEFICIT


def requirement_values(r: Requirement, metrics: dict, bound, slip=None):
    """A requirement's constraint per case (<= 0 when met), whether it is met by the judge's rule
    (`Requirement.met`), and its relative miss (`Terms.miss`)."""
    value = metrics[r.metric]
    scale = SCALE.get(METRICS[r.metric].unit, 1.0)
    c = deficit(slip) if r.is_grip else -r.slack(value, bound) / scale
    miss = (-r.slack(value, bound) - r.tolerance) / jnp.maximum(jnp.abs(bound), 1e-12)
    return c, r.met(value, bound), miss


def run_metrics(config: Config, params: Params, checkpoint: bool | str = True) -> dict:
    """The training metrics of one scenario's runs, as floats (`finite` 1 or 0), over every local
    device; under the caller's jit or derivative."""
    m = devices.run(metrics_of(config, checkpoint), params, shard_traced=True)
    return {n: m[n].astype(params.dtype) for n in config.metrics} | {"finite": m.finite.astype(params.dtype)}


def bound_values(problem: Problem, params: Params) -> dict:
    """Per requirement whose bound names a parameter: its value per sample."""
    return {i: r.bound_values(params) for i, r in enumerate(problem.require) if isinstance(r.bound, str)}


def combine(problem: Problem, runs: list[dict], bounds: dict, K: int) -> Terms:
    """The problem's terms from its runs: `runs[s]` maps each metric of scenario s to its values per
    sample (K starts x M draws, start-major), `bounds` is `bound_values`. Pure JAX: the evaluator
    differentiates it apart from the runs, so that programs of the runs are shared between problems."""
    B = next(iter(runs[0].values())).shape[-1]
    M = B // K
    dtype = next(iter(runs[0].values())).dtype
    nan = jnp.full((K, M), jnp.nan, dtype)
    names = dict.fromkeys(n for m in runs for n in m)
    cases = {n: jnp.concatenate([m[n].reshape(K, M) if n in m else nan for m in runs], axis=1) for n in names}
    parts, f = [], 0.0
    for o, cols in zip(problem.minimise, problem.objective_columns(M)):
        x = o.weight * cases[o.metric][:, cols]
        parts.append(x)
        f = f + aggregate(x, o.over, problem)
    c, holds, miss = [], [], []
    for i, r in enumerate(problem.require):
        cols = columns_of(problem.scenarios, r, M)
        bound = bounds.get(i, r.bound)
        if jnp.ndim(bound):
            bound = jnp.tile(jnp.reshape(bound, (K, M)), (1, len(cols) // M))
        slip = cases["slip"][:, cols] if r.is_grip else None
        ci, hi, mi = requirement_values(r, {r.metric: cases[r.metric][:, cols]}, bound, slip)
        c.append(ci)
        holds.append(hi)
        miss.append(mi)
    grip = problem.grip_columns(M)
    return Terms(
        f=f,
        c=jnp.concatenate(c, axis=1) if c else jnp.zeros((K, 0), dtype),
        parts=jnp.concatenate(parts, axis=1),
        min_swi=cases["min_swi"][:, grip] if len(grip) else jnp.zeros((K, 0), dtype),
        holds=jnp.concatenate(holds, axis=1) if holds else jnp.zeros((K, 0), bool),
        metrics=cases,
        miss=jnp.concatenate(miss, axis=1) if miss else jnp.zeros((K, 0), dtype),
    )


def terms(theta, base: Params, problem: Problem, draws, checkpoint: bool | str = True) -> Terms:
    """Objective and constraints of every start at every draw of every scenario; theta is (K, n)
    log-values, draws (M, p) (or (M,) with one uncertain parameter). Pure: jit it, differentiate it
    (`jax.grad` of a scalar of `f` and `c`, as an optax loop does). The batch is split over every
    local device (`devices.run`).

    Args:
      theta: (K, n) log-values of `problem.names`.
      base: every other parameter, a single set, with the problem's fixed values (`Problem.base`).
      problem: the problem.
      draws: the uncertain parameters' values (`Problem.training_draws`).
      checkpoint: the reverse-mode memory policy of `coopjax.simulate`.

    Returns:
      `Terms`: f (K,), c (K, Q), parts, min_swi, holds and the metrics per case.
    """
    params = params_for(base, problem, theta, draws)
    runs = [run_metrics(config, params, checkpoint) for config in problem.configs]
    return combine(problem, runs, bound_values(problem, params), theta.shape[0])


MAX_HALVINGS = 2  # the training step is halved at most this often (4x the runs)
LEAST_MEASURED = 0.1  # the share of the starts' box that must be measured at the training step
PROBES = 128  # Sobol points of the starts' box whose linearised loops decide the step


def least_limit(problem: Problem, base: Params, thetas, draws) -> np.ndarray:
    """(K,) per candidate (log parameters), the smallest stability limit of its linearised loop over
    the draws and the problem's scenarios, s."""
    params = params_for(base, problem, np.asarray(thetas, np.float64), draws)
    limit = np.min([np.asarray(stable_dt(params, c)[0]) for c in problem.configs], axis=0)
    return limit.reshape(len(thetas), len(draws)).min(1)


def measurable_step(
    problem: Problem, base: Params, first: dict[str, float], spread: float
) -> tuple[Problem, str | None]:
    """The problem with a training step at which some of the starts' box can be measured, and a
    note saying so (None: unchanged).

    A run whose step is beyond its linearised loop's limit is not measured (`Evaluator` prices it),
    and its value is wrong. Over masses 0.3 to 8 kg and gripper damping down to 30 N s/m, every one
    of 128 points of the box x/÷ e^2.5 around Table 1 was beyond the carry's default step (2 ms) at
    some training draw, so every candidate of the run was invalid; the best known's objective read
    76.5 N at that step against 68.3 N at half of it and at a quarter. So while fewer than
    `LEAST_MEASURED` of `PROBES` Sobol points of that box (with the first start) are within the
    limit at every training draw, the step is halved (at most `MAX_HALVINGS` times) for every
    scenario. Where a share is measured, the step is kept: the search moves there (halving it on a
    box 79 % beyond found a worse answer at twice the cost). A step the user set is kept."""
    if problem.dt is not None:
        return problem, None
    lo, hi = problem.log_bounds()
    start = np.clip(to_log(first, problem.names), lo, hi)
    a, b = problem.log_box_around(start, spread)
    probes = np.concatenate([start[None], a + (b - a) * qmc.Sobol(len(a), seed=0).random(PROBES)])
    limit = least_limit(problem, base, probes, problem.fixed_training_draws())
    dt, halvings = problem.train_dt, 0
    while (limit >= dt / 2**halvings).mean() < LEAST_MEASURED and halvings < MAX_HALVINGS:
        halvings += 1
    if halvings == 0:
        return problem, None
    slower = dataclasses.replace(problem, dt=dt / 2**halvings)
    share = (limit >= dt).mean()
    return slower, (
        f"{share:.0%} of the starts' box can be measured at the training step of {dt:g} s (the rest is "
        f"beyond its linearised loop's limit at some training draw): training runs at {slower.train_dt:g} s"
    )


EDGE = 1.1  # an answer whose loop's limit is within this factor of the training step sits on it


def step_edge(problem: Problem, base: Params, values: dict[str, float]) -> float:
    """The smallest stability limit of the answer's linearised loop over the training draws, as a
    multiple of the training step. A run beyond its limit is priced as unmeasured (`Evaluator`), so
    a search whose best answers lie beyond it stops on it: about 1 (`EDGE`) says the search pressed
    against what the training step can measure. On the paper's squeeze with the grip held and the
    peak bounded, the answer trained at 1 ms sat at 1.00, and trained at 0.25 ms and 0.125 ms at 1.00
    again, its peak 21.9 and 16.4 N against 35.5 N."""
    theta = np.clip(to_log(values, problem.names), *problem.log_bounds())[None]
    return float(least_limit(problem, problem.base(base), theta, problem.fixed_training_draws())[0]) / problem.train_dt


def starting_points(
    problem: Problem, base: Params, first: dict[str, float], count: int, spread: float, seed: int
) -> np.ndarray:
    """The first start (log of `first`, clipped to the box), then `count - 1` log-uniform draws within
    x/÷ e^spread of it, each stable at the training step: a draw whose linearised loop needs dt below
    1.5 x the training step is drawn again (up to 50 rounds), so no start begins where its very first
    step would blow up. Every tuner starts from these points."""
    names = problem.names
    lo, hi = problem.log_bounds()
    base = problem.base(base)
    start = np.clip(to_log(first, names), lo, hi)
    rng = np.random.default_rng(seed)
    points = [start]
    a, b = problem.log_box_around(start, spread)
    for _ in range(50):
        if len(points) >= count:
            break
        draws = a + (b - a) * rng.random((4 * count, len(names)))
        params = base.replace(M_b=np.ones(len(draws)), **{n: np.exp(draws[:, i]) for i, n in enumerate(names)})
        limit, _ = stable_dt(params, problem.config)
        points += [d for d, ok in zip(draws, limit >= 1.5 * problem.train_dt) if ok]
    if len(points) < count:
        raise InputError(
            f"found only {len(points)} stable starting points in 50 rounds; try a smaller spread", "spread"
        )
    return np.stack(points[:count])
