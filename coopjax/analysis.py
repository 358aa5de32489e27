"""Linear analysis: the closed loop linearised by `jax.jacfwd` of the model's own field, as a
`control.StateSpace` (python-control), so that Bode plots, poles and margins come from the simulator.

Operating points (`point=`):

- ``"rest"``: every state 0, force control off (w = 0, so gamma = 1): before contact builds up.
- ``"limit"``: every state 0 with the grippers pre-compressed to F = F_lim and force control on
  (w = 1). With ``alpha`` given, gamma is frozen at alpha (the paper's section 2, Eq. 4-7);
  without it, gamma follows Eq. 8 (this is the switch-on point that the dt check linearises).
- a number ``t``: the state a hard-switch simulation of ``scenario`` reaches at time t, with each
  robot's force control on if its grip is at or above F_lim there.

The contact is linearised as in contact (K_g delta + R_g delta_dot) at "rest" and "limit", and as it
is at a simulated state (no force while a gripper is open).

Inputs: ``e_env_L/R`` an external force on a tip along +x (N); ``v_ref_L/R`` a change of the
commanded velocity (m/s); its integral moves the reference position, which adds a state
``x_ref_L/R``, and its derivative the reference acceleration, which becomes a feed-through;
``gamma_L/R`` robot i's compensation gain, with its modulation law cut (for loop margins).
Outputs: any state of `model.STATE_NAMES`, ``F_L/R`` (grip force, N), ``gamma_L/R`` (the value
Eq. 8 computes, which with a ``gamma`` input is the other end of the cut loop) and ``x_ref_L/R``.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from coopjax import model, scenarios
from coopjax.errors import InputError
from coopjax.params import Params, ROBOTS
from coopjax.scenarios import Clock, stacked
from coopjax.simulation import simulate
from coopjax.stability import max_stable_dt

INPUTS = tuple(f"{q}_{r}" for q in ("e_env", "v_ref", "gamma") for r in ROBOTS)
OUTPUTS = model.STATE_NAMES + tuple(f"{q}_{r}" for q in ("F", "gamma", "x_ref") for r in ROBOTS)
POINTS = ("rest", "limit")
ON_LIMIT = 1e-6  # relative: a simulated grip this close to F_lim is on the sliding surface

INSTALL_HINT = "linear analysis needs python-control: pip install 'coopjax[analysis]'"


def _control():
    try:
        import control
    except ImportError:
        raise ImportError(INSTALL_HINT) from None
    return control


def _names(given, allowed, what):
    given = (given,) if isinstance(given, str) else tuple(given)
    if not given:
        raise InputError(f"{what}: name at least one of: {', '.join(allowed)}")
    for name in given:
        if name not in allowed:
            raise InputError(f"unknown {what[:-1]} {name!r}; choose from: {', '.join(allowed)}")
    if len(set(given)) != len(given):
        raise InputError(f"{what}: {', '.join(given)} names one twice")
    return given


@dataclasses.dataclass(frozen=True)
class OperatingPoint:
    """Where the field is linearised: the state, the time, each robot's switch and contact."""

    y: np.ndarray  # (20,)
    t: float
    w: np.ndarray  # (2,) 0 or 1
    contact: np.ndarray  # (2,) 0 or 1
    params: Params  # the parameters the field is evaluated with (delta0, frozen gamma applied)
    description: str


def _single(params: Params) -> Params:
    if params.batch_shape:
        raise InputError(
            f"linearize takes one parameter set; this one has batch shape {params.batch_shape} "
            "(make one with scalar values, e.g. make_params(M_b=2.0), and loop over the batch)"
        )
    return params


def operating_point(params: Params, point="rest", *, alpha=None, scenario="paper", dt=1e-3) -> OperatingPoint:
    """The operating point of `linearize` (see the module docstring)."""
    p = _single(params)
    two = np.ones(2)
    if isinstance(point, str):
        if point not in POINTS:
            raise InputError(f"point {point!r}: choose 'rest', 'limit' or a time in s")
        if point == "rest":
            if alpha is not None:
                raise InputError("alpha freezes gamma with force control on: use point='limit'")
            y = np.zeros(model.N_STATE)
            return OperatingPoint(y, 0.0, 0 * two, two, p, "at rest, force control off (gamma = 1)")
        if alpha is None:
            # Pre-compression delta0 = F_lim / K_g puts the rest state on F = F_lim.
            p = p.with_leaves(delta0=p.F_lim / p.K_g)
            text = "at the force limit, gamma by Eq. 8"
        else:
            # gamma = 1 - w K_ini = alpha with K_GP = K_GI = 0: the field is then affine in the
            # state, so the pre-compression (which could divide by K_g = 0) does not matter.
            if not np.isfinite(alpha):
                raise InputError(f"alpha = {alpha}: it must be a finite number")
            zero = jnp.zeros_like(p.K_GP)
            p = p.with_leaves(K_GP=zero, K_GI=zero, K_ini=jnp.full_like(p.K_ini, 1.0 - alpha))
            text = f"at the force limit, gamma frozen at alpha = {alpha:g}"
        return OperatingPoint(np.zeros(model.N_STATE), 0.0, two, two, p, text)

    t = float(point)
    if not np.isfinite(t) or t < 0:
        raise InputError(f"point t = {point}: a simulated state needs a time >= 0 s")
    if alpha is not None:
        raise InputError("alpha freezes gamma at point='limit'; a simulated state keeps Eq. 8")
    y = np.zeros(model.N_STATE)
    if t > 0:
        solution = simulate(p, scenario, dt=dt, T=t)
        if not bool(solution.metrics.finite):
            raise InputError(f"the {scenario} run diverged before t = {t:g} s; no state to linearise at")
        y = np.asarray(solution.y_final, np.float64).reshape(model.N_STATE)
    st = model.unpack(jnp.asarray(y, p.M_b.dtype)[:, None])
    delta, _, F = model.geometry(jax.tree_util.tree_map(lambda x: x[..., None], p), st, model.sign(1, p.M_b.dtype))
    delta, F = np.asarray(delta, np.float64).reshape(2), np.asarray(F, np.float64).reshape(2)
    F_lim = np.broadcast_to(np.asarray(p.F_lim), (2,))
    contact = ((delta > 0) & (F > 0)).astype(float)
    w = (contact * F >= F_lim * (1 - ON_LIMIT)).astype(float)
    robots = ", ".join(
        f"{r}: F = {F[i] * contact[i]:.4g} N, switch {'on' if w[i] else 'off'}" for i, r in enumerate(ROBOTS)
    )
    return OperatingPoint(y, t, w, contact, p, f"{scenario} run at t = {t:g} s ({robots})")


def _field(p, y_op, t, w, contact, y, u, u_dot, scenario, inputs, outputs):
    """(dy/dt, outputs) at state y (n,) and inputs u, u_dot (m,), all flat float64 vectors."""
    p = jax.tree_util.tree_map(lambda x: jnp.asarray(x, y.dtype)[..., None], p)
    n = model.N_STATE
    st = model.unpack(y[:n, None])
    s = model.sign(1, y.dtype)
    get = lambda v, name: v[inputs.index(name)] if name in inputs else jnp.zeros((), y.dtype)
    per_robot = lambda v, q: jnp.stack([get(v, f"{q}_{r}") for r in ROBOTS])[:, None]

    _, _, F = model.geometry(p, st, s)
    F = F * contact[:, None]
    v_cmd, a_cmd, x_ref = stacked(scenarios.get(scenario).command(p, Clock.at(t)))
    v_cmd = v_cmd + per_robot(u, "v_ref")
    a_cmd = a_cmd + per_robot(u_dot, "v_ref")
    if y.shape[0] > n:
        x_ref = x_ref + y[n:, None]
    w = w[:, None]

    law = lambda st, F: 1.0 - w * (p.K_ini + p.K_GP * (F - p.F_lim) + p.K_GI * st["Z"])  # Eq. 8
    p_run = p
    cut = np.array([f"gamma_{r}" in inputs for r in ROBOTS])[:, None]
    if cut.any():
        # Cut robot i's modulation: its gamma is the operating value plus the input.
        st_op = model.unpack(y_op[:, None])
        gamma_op = law(st_op, model.geometry(p, st_op, s)[2] * contact[:, None])
        K_ini = jnp.where(cut, 1.0 - gamma_op - per_robot(u, "gamma"), p.K_ini)
        zero_if_cut = lambda g: jnp.where(cut, 0.0, g)
        p_run = p.with_leaves(K_ini=K_ini, K_GP=zero_if_cut(p.K_GP), K_GI=zero_if_cut(p.K_GI))
    rates, _ = model.robot_field(
        p_run, st, s, F, w, (v_cmd, a_cmd, x_ref), model.Options(), f_env=per_robot(u, "e_env")
    )
    dy = model.pack({**rates, **model.body_field(p, st, F[0], F[1])})[:, 0]
    if y.shape[0] > n:
        dy = jnp.concatenate([dy, per_robot(u, "v_ref")[:, 0]])
    gamma = law(st, F)
    signals = dict(zip(model.STATE_NAMES, y[:n]))
    signals.update({f"F_{r}": F[i, 0] for i, r in enumerate(ROBOTS)})
    signals.update({f"gamma_{r}": gamma[i, 0] for i, r in enumerate(ROBOTS)})
    signals.update({f"x_ref_{r}": x_ref[i, 0] for i, r in enumerate(ROBOTS)})
    return dy, jnp.stack([signals[o] for o in outputs])


@functools.partial(jax.jit, static_argnums=(5, 6, 7, 8))
def _jacobians(p, y_op, t, w, contact, n, scenario, inputs, outputs):
    y0 = jnp.zeros(n, jnp.float64).at[: model.N_STATE].set(y_op)
    u0 = jnp.zeros(len(inputs), jnp.float64)
    f = lambda y, u, ud: _field(p, y_op, t, w, contact, y, u, ud, scenario, inputs, outputs)
    return jax.jacfwd(f, argnums=(0, 1, 2))(y0, u0, u0)


def linearize(
    params: Params,
    point="rest",
    *,
    inputs=("e_env_L",),
    outputs=("v_r_L",),
    alpha=None,
    scenario: str = "paper",
    dt: float = 1e-3,
):
    """The closed loop linearised at `point`, as a `control.StateSpace` with named signals.

    Args:
      params: one parameter set (`make_params(...)`).
      point: "rest", "limit" or a time t in s of a hard-switch `scenario` run (module docstring).
      inputs, outputs: names from `INPUTS` and `OUTPUTS`.
      alpha: with point="limit", freeze gamma at alpha (the paper's section 2).
      scenario, dt: the run that gives the state when `point` is a time.

    The state is the model's 20 (plus x_ref_L/R when a v_ref input is asked for). A v_ref input also
    drives a_ref = d(v_ref)/dt; with y' = A y + B0 u + B1 u', the state z = y - B1 u gives the proper
    realisation z' = A z + (A B1 + B0) u, out = C z + (C B1 + D) u, which is exact.
    """
    control = _control()
    inputs = _names(inputs, INPUTS, "inputs")
    outputs = _names(outputs, OUTPUTS, "outputs")
    op = operating_point(params, point, alpha=alpha, scenario=scenario, dt=dt)
    cut_gamma = [f"gamma_{r}" in inputs for r in ROBOTS]
    for i, r in enumerate(ROBOTS):
        if cut_gamma[i] and not op.w[i]:
            raise InputError(
                f"input gamma_{r}: robot {r}'s force control is off at this point, so gamma is 1 "
                "and there is no loop to cut (use point='limit' or a time on the limit)"
            )
    if alpha is not None and any(cut_gamma):
        raise InputError("a gamma input cuts Eq. 8's loop; with alpha frozen there is none")
    with_ref = "v_ref_L" in inputs or "v_ref_R" in inputs
    n = model.N_STATE + (2 if with_ref else 0)
    with jax.enable_x64(True):  # the analysis is float64 whatever the runs use
        f64 = lambda x: jnp.asarray(x, jnp.float64)
        p = jax.tree_util.tree_map(f64, op.params)
        jac = _jacobians(p, f64(op.y), f64(op.t), f64(op.w), f64(op.contact), n, scenario, inputs, outputs)
        (A, B0, B1), (C, D, D1) = jax.tree_util.tree_map(lambda m: np.asarray(m, np.float64), jac)
    assert not D1.any()  # no output depends on a_ref
    states = list(model.STATE_NAMES) + ([f"x_ref_{r}" for r in ROBOTS] if with_ref else [])
    return control.ss(A, A @ B1 + B0, C, C @ B1 + D, inputs=list(inputs), outputs=list(outputs), states=states)


def prune(sys):
    """Drop the states that cannot reach an output or be reached from an input, judged from the exact
    zeros of the Jacobians (jacfwd gives exact zeros where there is no coupling). The transfer
    function is unchanged; the dropped ones are, for example, the free-floating bases, which the
    tip never feels with full base compensation (alpha_b = 1). This is what makes a DC gain defined."""
    control = _control()
    A, B, C = (np.asarray(m) != 0 for m in (sys.A, sys.B, sys.C))

    def closure(start, step):
        seen = start.copy()
        while True:
            grown = seen | step(seen)
            if (grown == seen).all():
                return seen
            seen = grown

    reachable = closure(B.any(axis=1), lambda s: A[:, s].any(axis=1))
    observable = closure(C.any(axis=0), lambda s: A[s, :].any(axis=0))
    keep = np.flatnonzero(reachable & observable)
    states = [sys.state_labels[k] for k in keep]
    return control.ss(
        sys.A[np.ix_(keep, keep)],
        sys.B[keep],
        sys.C[:, keep],
        sys.D,
        inputs=sys.input_labels,
        outputs=sys.output_labels,
        states=states,
        name=sys.name,
    )


def static_gain(sys) -> np.ndarray:
    """The final value of the unit-step response from rest, per (output, input).

    `control.dcgain` needs an invertible A; this loop's A is singular even after `prune`, because
    some integrals are conserved (with v_ref = 0, x_r + q_c + (1 - alpha) beta_H x_f is constant). The
    step response then settles where A y + B u = 0 and the conserved quantities keep their value 0
    (n^T y = 0 for every left null vector n of A, which needs n^T B = 0: checked)."""
    A, B, C, D = (np.asarray(m, np.float64) for m in (sys.A, sys.B, sys.C, sys.D))
    if A.size == 0:
        return D
    U, sv, _ = np.linalg.svd(A)
    null = U[:, sv <= 1e-10 * sv[0]]  # left null vectors: null.T @ A = 0
    if null.size and np.abs(null.T @ B).max() > 1e-9 * np.abs(B).max():
        raise InputError("the step response does not settle: an input drives a free integrator")
    M = np.vstack([A, null.T])
    rhs = np.vstack([-B, np.zeros((null.shape[1], B.shape[1]))])
    y, *_ = np.linalg.lstsq(M, rhs, rcond=None)
    if np.abs(M @ y - rhs).max() > 1e-8 * max(1.0, np.abs(rhs).max()):
        raise InputError("the step response does not settle: there is no rest state for a constant input")
    if np.linalg.eigvals(A).real.max() > 1e-9 * sv[0]:
        raise InputError("the step response does not settle: the linearised loop is unstable")
    return C @ y + D


def free_robot(params: Params) -> Params:
    """The robot of the paper's section 2: the grip cut (K_g = R_g = 0), so the tip feels only e_env."""
    zero = jnp.zeros_like(params.K_g)
    return params.with_leaves(K_g=zero, R_g=zero)


def k_rob(params: Params, alpha: float, robot: str = "L") -> float:
    """Driving-point stiffness (N/m) of one robot with gamma frozen at alpha: the static deflection of
    its tip under a constant environment effort, from the linearised simulator (Eq. 5's quantity)."""
    sys = prune(linearize(free_robot(params), "limit", alpha=alpha, inputs=f"e_env_{robot}", outputs=f"x_r_{robot}"))
    return 1.0 / float(static_gain(sys)[0, 0])


def k_rob_eq5(params: Params, alpha, robot: str = "L"):
    """The paper's Eq. 5: 1/K_rob = 1/(mu_H K_c) + beta_H (1 - alpha) / (mu_H K_f)."""
    i = ROBOTS.index(robot)
    g = lambda name: float(np.asarray(getattr(params, name))[i])
    alpha = np.asarray(alpha, np.float64)
    return 1.0 / (1.0 / (g("mu_H") * g("K_c")) + g("beta_H") * (1 - alpha) / (g("mu_H") * g("K_f")))


def admittance_eq4(params: Params, alpha, s, robot: str = "L"):
    """The paper's Eq. 4, Y = R [1 + beta_H (1-alpha) F C] / [1 + mu_H C R + beta_H (1-alpha) F C],
    evaluated pointwise at complex frequencies s (no polynomial algebra that could blur it)."""
    i = ROBOTS.index(robot)
    g = lambda name: float(np.asarray(getattr(params, name))[i])
    s = np.asarray(s, complex)
    R = 1 / (g("M_r") * s)
    C = (g("M_c") * s**2 + g("R_c") * s + g("K_c")) / s
    F = s / (g("M_f") * s**2 + g("R_f") * s + g("K_f"))
    b = g("beta_H") * (1 - alpha)
    return R * (1 + b * F * C) / (1 + g("mu_H") * C * R + b * F * C)


def grip_loop(params: Params, point=None, robot: str = "L", *, scenario="paper", dt=1e-3):
    """Loop transfer L(s) of robot `robot`'s gain-modulation loop (Eq. 8), cut at gamma, in the
    negative-feedback convention of `control.stability_margins` (closed loop: 1 + L = 0).

    The cut: gamma is driven from outside and the law's output is read. Closing gamma_in = gamma_law
    gives 1 - G = 0 with G = gamma_law / gamma_in, so L = -G. `point` is "limit" (default) or a time.
    """
    point = "limit" if point is None else point
    G = linearize(params, point, inputs=f"gamma_{robot}", outputs=f"gamma_{robot}", scenario=scenario, dt=dt)
    return -G


def margins(loop, omega=None) -> dict:
    """`control.stability_margins` of a loop, from its frequency response on a grid that avoids
    omega = 0 (where the loop's cancelled integrators make the state-space evaluation singular)."""
    control = _control()
    omega = np.logspace(-3, 5, 4001) if omega is None else omega
    gm, pm, sm, w_pc, w_gc, w_sm = control.stability_margins(control.frd(loop, omega))
    at_gc = complex(np.asarray(loop(1j * w_gc)).reshape(-1)[0]) if np.isfinite(w_gc) else complex("nan")
    return dict(
        gain_margin=float(gm),
        phase_margin_deg=float(pm),
        stability_margin=float(sm),
        w_phase_crossover=float(w_pc),
        w_gain_crossover=float(w_gc),
        w_stability_margin=float(w_sm),
        loop_at_gain_crossover=[at_gc.real, at_gc.imag],
    )


def poles_summary(poles: np.ndarray, dt: float) -> dict:
    """The figures a user checks a step against: the fastest and slowest modes and RK4's limit."""
    poles = np.asarray(poles)
    moving = poles[np.abs(poles) > 1e-9 * np.abs(poles).max()]
    oscillatory = moving[moving.imag > 1e-9]
    least_damped = oscillatory[np.argmin(-oscillatory.real / np.abs(oscillatory))] if oscillatory.size else None
    limit = float(max_stable_dt(poles[None])[0])
    return dict(
        fastest=float(np.abs(poles).max()),
        max_real=float(poles.real.max()),
        least_damped=None if least_damped is None else [float(least_damped.real), float(least_damped.imag)],
        damping_ratio=None if least_damped is None else float(-least_damped.real / abs(least_damped)),
        rk4_dt_limit=limit,
        dt=dt,
        dt_inside=bool(dt <= limit),
    )


def report(params: Params, alphas=(1.0, 0.5, 0.1), dt: float = 1e-3, robot: str = "L", omega=None) -> dict:
    """Everything `coopjax analyze` prints and draws, as plain numbers and arrays.

    - bode: the driving-point admittance v_r / e_env of the free robot (grip cut) with gamma frozen
      at each alpha, from the linearised simulator and from Eq. 4;
    - k_rob: the static stiffness against alpha, simulator and Eq. 5;
    - poles: the closed loop's poles at rest and at the force limit (gamma by Eq. 8), with RK4's
      stability limit on dt (the check `simulate` makes);
    - margins: of robot `robot`'s gain-modulation loop at the force limit, cut at gamma.
    """
    omega = np.logspace(-2, 4, 400) if omega is None else np.asarray(omega)
    alphas = [float(a) for a in alphas]
    bode = []
    for alpha in alphas:
        sys = linearize(free_robot(params), "limit", alpha=alpha, inputs=f"e_env_{robot}", outputs=f"v_r_{robot}")
        ours = np.asarray(sys(1j * omega)).reshape(-1)  # SISO
        bode.append(dict(alpha=alpha, simulator=np.asarray(ours), eq4=admittance_eq4(params, alpha, 1j * omega, robot)))
    grid = np.unique(np.concatenate([np.linspace(0.0, 1.0, 41), 1 - np.logspace(-3, -1.4, 5), alphas]))
    k_sim = np.array([k_rob(params, a, robot) for a in grid])
    fine = np.linspace(min(grid.min(), 0.0), max(grid.max(), 1.0), 2001)
    poles = {pt: np.asarray(linearize(params, pt).poles()) for pt in POINTS}
    loop = grip_loop(params, "limit", robot)
    closed = poles["limit"]
    return dict(
        robot=robot,
        omega=omega,
        bode=bode,
        k_rob=dict(
            alpha=grid,
            simulator=k_sim,
            eq5=k_rob_eq5(params, grid, robot),
            alpha_fine=fine,
            eq5_fine=k_rob_eq5(params, fine, robot),
        ),
        poles=poles,
        poles_summary={pt: poles_summary(v, dt) for pt, v in poles.items()},
        margins=margins(loop),
        loop_dc_gain=float(np.real(np.asarray(loop(1e-9j)).reshape(-1)[0])),
        closed_loop_stable=bool(closed.real.max() <= 1e-9 * np.abs(closed).max()),
        dt=dt,
    )
