"""The sliding-mode integrator against the dt -> 0 limit of the hard model (docs/model.md, "Step size").

The limit is computed two independent ways: `filippov` at dt = 2.5e-4, and plain `rk4` at dt = 1e-6
(slow). benchmarks/convergence.json has the evidence that 2.5e-4 is the limit for this purpose: on
16 samples filippov there is within 1.9e-6 N (min grip), 6.1e-6 (peak) and 3.2e-4 (lag, relative)
of filippov at 1e-5, under 2 % of each tolerance, and filippov at 1e-5 agrees with rk4 at 1e-6.
Each check below is run on `rk4` at dt = 1e-3 too, where it must fail: that shows the check can
tell a converged answer from a chattering one.
"""

import jax.numpy as jnp
import numpy as np
import pytest

import coopjax as cj

TOLERANCE = {"min_grip": 0.05, "peak_grip": 0.02, "rms_lag": 0.02}  # N, relative, relative
LIMIT_DT = 2.5e-4  # see the docstring
# Ten (gain set, mass) samples over 0.5-5 kg, plus Table 1 at 1 kg, whose peak is a re-contact after
# release: there the located impact force is the peak, and the step grid alone misses 13 % of it.
TABLE1 = dict(K_GP=0.5, K_GI=0.1, tau=1.25, G_e=600.0)
HOLDS = dict(K_GP=0.054, K_GI=0.078, tau=2.93, G_e=1224.0)  # holds the grip at every mass
RANDOM = [
    dict(K_GP=0.18, K_GI=0.04, tau=0.6, G_e=250.0),
    dict(K_GP=1.1, K_GI=0.3, tau=4.0, G_e=2000.0),
    dict(K_GP=0.09, K_GI=0.5, tau=8.0, G_e=90.0),
]
SAMPLES = (
    [dict(TABLE1, M_b=m) for m in (0.5, 1.0, 2.5, 5.0)]
    + [dict(HOLDS, M_b=m) for m in (0.5, 1.2, 2.5, 5.0)]
    + [dict(g, M_b=m) for g, m in zip(RANDOM, (0.8, 3.3, 1.7))]
)


def columns(samples):
    return {k: np.array([s[k] for s in samples]) for k in samples[0]}


def metrics(samples, **kwargs):
    m = cj.simulate(cj.make_params(**columns(samples)), "carry", check_dt=False, **kwargs).metrics
    return {k: np.asarray(getattr(m, k)) for k in ("min_grip", "peak_grip", "rms_lag", "finite")}


def misses(got, limit):
    """Per sample: which accuracy tolerance each metric misses (empty where all are met)."""
    error = {
        "min_grip": np.abs(got["min_grip"] - limit["min_grip"]),
        "peak_grip": np.abs(got["peak_grip"] / limit["peak_grip"] - 1),
        "rms_lag": np.abs(got["rms_lag"] / limit["rms_lag"] - 1),
    }
    return [[k for k in TOLERANCE if error[k][i] > TOLERANCE[k]] for i in range(len(got["min_grip"]))], error


@pytest.fixture(scope="module")
def limit():
    return metrics(SAMPLES, integrator="filippov", dt=LIMIT_DT)


def test_filippov_at_1e_3_is_within_tolerance_of_the_limit_and_plain_rk4_is_not(limit):
    assert limit["finite"].all()
    assert np.ptp(limit["min_grip"]) > 5.0 and limit["peak_grip"].max() > 100.0  # holding and losing samples
    missed, error = misses(metrics(SAMPLES, integrator="filippov", dt=1e-3), limit)
    assert missed == [[]] * len(SAMPLES), (missed, error)
    chattering, _ = misses(metrics(SAMPLES, integrator="rk4", dt=1e-3), limit)
    assert sum(map(bool, chattering)) >= len(SAMPLES) - 2, chattering


def test_the_impact_force_is_in_the_peak(limit):
    """Table 1 at 1 kg peaks at a re-contact: sampled only on the 1 ms grid, the peak is 13 % low."""
    i = 1
    run = cj.simulate(cj.make_params(**SAMPLES[i]), "carry", dt=1e-3, every=1)
    on_grid = float(np.max(run.trajectory.aux.F))
    assert on_grid < 0.9 * limit["peak_grip"][i]
    assert float(run.metrics.peak_grip) == pytest.approx(limit["peak_grip"][i], rel=TOLERANCE["peak_grip"])


@pytest.mark.slow
def test_plain_rk4_at_1e_6_reaches_the_same_limit(limit):
    """The second, independent route to the limit: no sliding-mode logic, just a tiny step (about 1 min)."""
    pick = [2, 5]  # Table 1 at 2.5 kg loses the grip; the holding set at 1.2 kg slides
    reference = metrics([SAMPLES[i] for i in pick], integrator="rk4", dt=1e-6)
    missed, error = misses(reference, {k: v[pick] for k, v in limit.items()})
    assert missed == [[], []], (missed, error)


def test_during_sliding_the_force_stays_on_the_limit_to_round_off():
    sol = cj.simulate(cj.make_params(**HOLDS, M_b=2.5), "carry", dt=1e-3, every=1)
    F, w = np.asarray(sol.trajectory.aux.F), np.asarray(sol.trajectory.aux.w)
    for i in range(2):
        sliding = (w[:, i] > 0) & (w[:, i] < 1)  # the Filippov weight strictly inside (0, 1)
        settled = sliding & np.roll(sliding, 1) & np.roll(sliding, 2)  # two steps after the entry step
        settled[:2] = False
        assert settled.sum() > 300
        # The entry is located by a linear root of the force's rate, so the force lands on F_lim to
        # about 1e-8 N there; round-off would be 1e-12, plain RK4's chatter is 1e-3 and more.
        assert np.abs(F[settled, i] - 10.0).max() < 1e-7
    plain = cj.simulate(cj.make_params(**HOLDS, M_b=2.5), "carry", integrator="rk4", dt=1e-3, every=1)
    F_plain = np.asarray(plain.trajectory.aux.F)
    assert np.abs(F_plain[settled, 1] - 10.0).max() > 1e-3  # plain RK4 chatters around it


def test_paper_scenario_is_unchanged():
    """Fig. 6 does not slide: filippov at 1e-3 gives plain RK4's forces at 1e-4 (the reference values of
    docs/model.md)."""
    times = (0.5, 1.0, 2.0, 3.0)

    def forces(**kwargs):
        sol = cj.simulate(cj.make_params(), "paper", every=int(round(0.5 / kwargs["dt"])), **kwargs)
        t, F = np.asarray(sol.trajectory.t), np.asarray(sol.trajectory.aux.F)
        return np.array([F[np.argmin(np.abs(t - tq))] for tq in times]), float(sol.metrics.min_grip)

    ours, min_grip = forces(integrator="filippov", dt=1e-3)
    theirs, their_min_grip = forces(integrator="rk4", dt=1e-4)
    np.testing.assert_allclose(ours, theirs, atol=1e-3)
    np.testing.assert_allclose(ours[:, 0], [71.835, 65.342, 50.839, 55.000], atol=1e-3)
    assert abs(min_grip - their_min_grip) < 0.05  # the crossing counts, not the first grid sample after it


def test_filippov_is_the_default_for_the_hard_switch_and_refuses_smooth_ones():
    p = cj.make_params()
    default = cj.simulate(p, "carry", T=0.8).metrics
    explicit = cj.simulate(p, "carry", T=0.8, integrator="filippov").metrics
    assert float(default.min_grip) == float(explicit.min_grip)
    with pytest.raises(cj.InputError, match="the smooth switch runs with rk4"):
        cj.simulate(p, "carry", switch="smooth", integrator="filippov")
    with pytest.raises(ValueError, match="unknown integrator 'euler'"):
        cj.simulate(p, "carry", integrator="euler")


@pytest.mark.parametrize("dtype", [pytest.param(jnp.float32, marks=pytest.mark.slow), jnp.float64])
def test_filippov_runs_in_either_precision(dtype):
    p = cj.make_params(**HOLDS, M_b=np.array([0.5, 5.0])).astype(dtype)
    m = cj.simulate(p, "carry").metrics
    assert m.rms_lag.dtype == dtype and bool(m.finite.all())
    # Both hold the grip on F_lim = 10 N; the least force includes the cuts at located events, which
    # a first-order location leaves up to 1e-4 N off the surface (the tolerance is 0.05 N).
    assert np.all(np.abs(np.asarray(m.min_grip) - 10.0) < 1e-3)
    if dtype == jnp.float32:
        reference = cj.simulate(p.astype(jnp.float64), "carry").metrics
        np.testing.assert_allclose(np.asarray(m.rms_lag), np.asarray(reference.rms_lag), rtol=1e-3)


@pytest.mark.slow
def test_a_blown_up_sample_is_flagged_frozen_and_its_neighbours_untouched():
    K_GP = np.array([0.054, 100.0, 0.5])  # 100 is unstable in this loop
    batch = cj.simulate(cj.make_params(K_GP=K_GP, M_b=np.array([2.5, 2.5, 1.0])), "carry", check_dt=False)
    assert np.asarray(batch.metrics.finite).tolist() == [True, False, True]
    assert 0 < float(batch.metrics.t_diverged[1]) < 4.0
    assert np.all(np.isfinite(np.asarray(batch.y_final)))  # frozen at its last good state
    for b in (0, 2):
        single = cj.simulate(cj.make_params(K_GP=K_GP[b], M_b=[2.5, 2.5, 1.0][b]), "carry").metrics
        for name in ("min_grip", "peak_grip", "rms_lag", "impact"):
            assert float(getattr(batch.metrics, name)[b]) == pytest.approx(float(getattr(single, name)), rel=1e-12)


def test_the_step_check_covers_the_sliding_mode_step():
    """The step evaluates the w = 0 and w = 1 fields with RK4 stages over at most dt: the check's
    limit is RK4's for the fastest of their linearised modes, and it refuses filippov beyond it."""
    from coopjax.stability import fastest_modes, max_stable_dt, rk4_amplification

    p = cj.make_params(K_GP=5.0)
    modes = fastest_modes(p, cj.Config("carry", integrator="filippov"))
    limit = float(max_stable_dt(modes)[0])
    assert 1e-4 < limit < 1e-3
    assert rk4_amplification(modes * limit).max() == pytest.approx(1.0, abs=1e-6)
    assert rk4_amplification(modes * 1.01 * limit).max() > 1.0
    with pytest.raises(ValueError, match="too large for filippov .* stable only for dt <="):
        cj.simulate(p, "carry", dt=1e-3)
    assert bool(cj.simulate(p, "carry", dt=0.5 * limit, T=1.0).metrics.finite)


def test_crossing_is_the_root_of_the_quadratic_through_the_piece():
    from coopjax.integration.filippov import crossing

    h, rate, curvature = 2e-3, 150.0, 4e5  # an accelerating approach: the first-order time is 0.33 / 150 > h
    sigma_n = -0.33
    root = (-rate + np.sqrt(rate**2 - 4 * curvature * sigma_n)) / (2 * curvature)
    assert root < h < -sigma_n / rate
    sigma_end = sigma_n + rate * h + curvature * h**2
    assert float(crossing(jnp.array(sigma_n), jnp.array(rate), jnp.array(sigma_end), jnp.array(h))) == pytest.approx(
        root, rel=1e-12
    )
    # no crossing in the piece: a finite placeholder (the caller masks it), and no NaN in its gradient
    import jax

    f = lambda s_end: crossing(jnp.array(sigma_n), jnp.array(rate), s_end, jnp.array(h))
    assert float(f(jnp.array(-0.01))) == h
    assert np.isfinite(float(jax.grad(f)(-0.01)))
    # A sigma that first moves away from the surface (rate <= 0, from sigma_n <= 0) and comes back:
    # the return time, continuous as sigma_n -> 0 (where the other root tends to 0).
    for s_n in (-1e-13, 0.0):
        rate, curvature = -20.0, 4e4  # returns at 5e-4 s
        root = (-rate + np.sqrt(rate**2 - 4 * curvature * s_n)) / (2 * curvature)
        s_end = s_n + rate * h + curvature * h**2
        located = crossing(jnp.array(s_n), jnp.array(rate), jnp.array(s_end), jnp.array(h))
        assert float(located) == pytest.approx(root, rel=1e-12) and root == pytest.approx(5e-4, rel=1e-9)
    # sigma_n = 0 with no rate: a double root at 0, where the square root's derivative is infinite.
    at_rest = lambda s_n, s_end: crossing(s_n, jnp.array(0.0), s_end, jnp.array(h))
    assert np.all(np.isfinite(np.asarray(jax.grad(at_rest, argnums=(0, 1))(0.0, 0.01))))


def test_a_crossing_the_first_order_prediction_puts_beyond_the_step_is_located_at_the_true_time():
    """The force falls to F_lim faster than its rate at the step's start says (it accelerates), so a
    first-order prediction puts the crossing beyond the step. The step finds it on its own RK4
    solution, at the time an independent solve_ivp of the switch-on field finds."""
    import jax
    from scipy.integrate import solve_ivp

    from coopjax import model
    from coopjax.integration import filippov
    from coopjax.scenarios import Clock, get
    from tests import reference_model as ref

    dt, k = 2e-3, 734  # Table 1 at 3 kg: robot L's force falls through F_lim at t = 1.4699 s
    params = cj.make_params(M_b=np.array([3.0]))
    y = np.array(cj.simulate(params, "carry", dt=dt, every=1, check_dt=False).trajectory.y[k, :, 0])
    y[model.STATE_NAMES.index("x_r_R")] += 0.05  # robot R 4 cm clear of the body: one robot's event only
    t0, ps, scenario = k * dt, model.robots(params), get("carry")
    options = cj.Config("carry", dt=dt).options

    # Reference: robot L on the switch-on field (its force above F_lim), robot R free, hard contact.
    p = dict(ref.TABLE1, M_b=3.0)

    def rhs(t, z):
        x_o, v_o = z[18], z[19]
        dz = np.zeros(20)
        yL, yR = z[:9], z[9:18]
        F = p["K_g"] * (yL[0] - x_o) + p["R_g"] * (yL[1] - v_o)
        dz[:9] = ref.robot_rates(p, 1.0, yL, F, 1.0, max(F, p["F_lim"]), *ref.command("carry", 0, t))
        dz[9:18] = ref.robot_rates(p, -1.0, yR, 0.0, 0.0, 0.0, *ref.command("carry", 1, t))
        dz[18], dz[19] = v_o, F / p["M_b"]
        return dz

    def surface(t, z):
        return p["K_g"] * (z[0] - z[18]) + p["R_g"] * (z[1] - z[19]) - p["F_lim"]

    surface.terminal = True
    z0 = np.concatenate([y[:18].reshape(9, 2).T.reshape(18), y[18:]])  # coopjax's layout -> robot-major
    sol = solve_ivp(rhs, (t0, t0 + 2 * dt), z0, method="DOP853", rtol=1e-12, atol=1e-12, events=surface)
    t_star = sol.t_events[0][0] - t0

    fs, _ = filippov.fields(ps, filippov.Rows.of(jnp.asarray(y)[:, None]), Clock.at(t0), None, scenario, options)
    first_order = float(fs[0].sigma[0] / -fs[0].sd1[0])
    assert t_star < 0.99 * first_order  # the case: the start's rate puts the crossing later

    h = 0.5 * (t_star + first_order)  # a step that holds the crossing, but not its first-order time
    _, _, path = jax.jit(lambda y: filippov.step(ps, y, t0, h, scenario, options))(jnp.asarray(y)[:, None])
    ends = np.cumsum(np.asarray(path.fraction[:, 0])) * h
    located = np.asarray(path.surface[:, 0, 0])
    assert located.sum() == 1, path
    assert ends[located][0] == pytest.approx(t_star, abs=2e-3 * h)


def test_the_end_of_a_sliding_mode_is_located_at_the_true_time():
    """Both robots slide on F = F_lim, and robot R's Filippov weight falls to 0 inside a step: its
    sliding ends there and its force leaves the surface downwards. The step ends a piece there (the
    field's kink), at the time an independent solve_ivp of the sliding motion finds."""
    import jax
    from scipy.integrate import solve_ivp

    from coopjax import model
    from coopjax.integration import filippov
    from coopjax.scenarios import get
    from tests import reference_model as ref

    dt, k = 1e-3, 2448  # the README's example (Table 1 at 1 kg): robot R's sliding ends at t = 2.4488 s
    params = cj.make_params(M_b=np.array([1.0]))
    solution = cj.simulate(params, "carry", dt=dt, every=1, check_dt=False)
    w = np.asarray(solution.trajectory.aux.w[:, :, 0])
    assert w[k, 1] > 0 and w[k + 1, 1] == 0 and 0 < w[k + 1, 0] < 1  # R slides, then does not; L slides on
    y = np.array(solution.trajectory.y[k, :, 0])
    t0, ps, scenario = k * dt, model.robots(params), get("carry")
    options = cj.Config("carry", dt=dt).options
    p = ref.TABLE1

    def sliding(t, z):
        """Both robots on their surfaces, each with its Filippov weight; (rates, R's weight)."""
        v_o = z[19]
        dz, weights = np.zeros(20), []
        for i, s in enumerate((1.0, -1.0)):
            yi = z[9 * i : 9 * i + 9]
            F = p["F_lim"]
            off = ref.robot_rates(p, s, yi, F, 0.0, F, *ref.command("carry", i, t))
            on = ref.robot_rates(p, s, yi, F, 1.0, F, *ref.command("carry", i, t))
            delta_dot = s * (yi[1] - v_o)  # the body's acceleration is 0: both forces are F_lim
            sd0, sd1 = p["K_g"] * delta_dot + p["R_g"] * s * off[1], p["K_g"] * delta_dot + p["R_g"] * s * on[1]
            lam = sd0 / (sd0 - sd1)
            dz[9 * i : 9 * i + 9] = off + lam * (on - off)
            weights.append(lam)
        dz[18] = v_o
        return dz, weights[1]

    exit_R = lambda t, z: sliding(t, z)[1]
    exit_R.terminal = True
    z0 = np.concatenate([y[:18].reshape(9, 2).T.reshape(18), y[18:]])  # coopjax's layout -> robot-major
    sol = solve_ivp(
        lambda t, z: sliding(t, z)[0], (t0, t0 + dt), z0, method="DOP853", rtol=1e-12, atol=1e-12, events=exit_R
    )
    t_star = sol.t_events[0][0] - t0
    assert 0.05 * dt < t_star < 0.95 * dt

    _, _, path = jax.jit(lambda y: filippov.step(ps, y, t0, dt, scenario, options))(jnp.asarray(y)[:, None])
    ends = np.cumsum(np.asarray(path.fraction[:, 0])) * dt
    located = np.asarray(path.surface[:, 1, 0])  # robot R's pieces that end on the surface
    assert located.sum() == 1, path
    # The time is lambda*'s linear interpolation through the piece (filippov.sliding_exit), O(dt^2):
    # measured here 1.1 % of the step early.
    assert ends[located][0] == pytest.approx(t_star, abs=0.03 * dt)


# Two samples whose step, before the surface's side was decided by the rates, jumped by O(dt) when
# the body mass moved by 1e-15 and 1e-13 relative: the force on the surface to round-off, with
# lambda* just above 1 (an impact of the other robot, and a sliding exit).
ROUND_OFF_JUMPS = dict(
    M_b=[4.247574395009304, 0.9331055493261957],
    K_GP=[0.5803716038956519, 0.7964010263953576],
    K_GI=[0.28873584454412243, 0.08626336688937561],
    tau=[1.1020025798727022, 1.0082307541733402],
    G_e=[763.5063919366245, 795.9660435769277],
)


def random_samples(n, seed=7):
    """n samples: the two above, then random gains over the tuner's ranges, an eighth of them heavy."""
    rng = np.random.default_rng(seed)
    m = n - 2
    drawn = dict(
        M_b=np.where(np.arange(m) % 8 == 0, rng.uniform(10.0, 50.0, m), rng.uniform(0.5, 5.0, m)),
        K_GP=rng.uniform(0.2, 1.0, m),
        K_GI=rng.uniform(0.02, 0.3, m),
        tau=rng.uniform(0.5, 3.0, m),
        G_e=rng.uniform(200.0, 1000.0, m),
    )
    return {k: np.concatenate([ROUND_OFF_JUMPS[k], drawn[k]]) for k in drawn}


def carry_metrics(columns_):
    return cj.simulate(cj.make_params(**columns_), "carry", check_dt=False).metrics


METRICS = ("min_grip", "peak_grip", "peak_hold", "slip", "crush", "impact", "min_swi", "rms_lag")


def moved_by_round_off(n, moves=(1e-12,)):
    """For n samples, per metric and per relative move of the body mass, the change of each
    sample's carry metric over its size (or the batch's median size, for metrics that are round-off
    themselves, as slip is while the force slides on F_lim): {name: (moves, samples) array}."""
    columns_ = random_samples(n)
    before = carry_metrics(columns_)
    afters = [carry_metrics(dict(columns_, M_b=columns_["M_b"] * (1.0 + move))) for move in moves]
    changes = {}
    for name in METRICS:
        x = np.asarray(getattr(before, name))
        ys = np.stack([np.asarray(getattr(after, name)) for after in afters])
        ok = np.isfinite(x) & np.isfinite(ys).all(0)
        size = np.maximum(np.abs(x[ok]), max(np.median(np.abs(x[ok])), np.finfo(x.dtype).tiny))
        changes[name] = np.abs(ys[:, ok] - x[ok]) / size
    return changes


def test_a_round_off_move_of_a_parameter_moves_no_metric_by_more_than_round_off():
    """The step is continuous: no decision in it turns on round-off (for the two samples above, the
    side of the surface a robot on it is on). A 1e-12 relative move of the mass changes every carry
    metric of these 64 samples by at most 1e-9 relative, where the two samples jumped by 7e-6."""
    worst = {name: float(c.max()) for name, c in moved_by_round_off(64).items()}
    assert max(worst.values()) <= 1e-9, worst


@pytest.mark.slow
def test_a_round_off_move_moves_every_metric_in_proportion_on_a_thousand_samples():
    """On 1000 samples a metric can move by more than 1e-9 relative for a 1e-12 move (6e-9 measured:
    a least grip force of 0.03 N, whose relative sensitivity to the mass is about 6000), but only in
    proportion to the move, as a continuous function does: ten times the move, ten times the change
    (a jump is the same for both)."""
    changes = moved_by_round_off(1000, moves=(1e-12, 1e-11))
    for name, (small, large) in changes.items():
        moved = small > 1e-9
        assert np.all(large[moved] / small[moved] > 5.0), (name, small[moved], large[moved])
        assert np.all(small <= 1e-8), (name, small.max())


def test_a_sample_never_depends_on_the_others_in_its_batch():
    """A batch with a diverging sample gives every other sample bit-identical metrics to the same
    batch without it: nothing in the step decides for the batch what a sample's answer is."""
    columns_ = random_samples(64)
    diverging = dict(columns_, K_GP=np.where(np.arange(64) == 5, 100.0, columns_["K_GP"]))
    a, b = carry_metrics(columns_), carry_metrics(diverging)
    assert not bool(b.finite[5]) and bool(np.all(np.delete(np.asarray(a.finite), 5)))
    for name in a._fields:
        np.testing.assert_array_equal(
            np.delete(np.asarray(getattr(a, name)), 5), np.delete(np.asarray(getattr(b, name)), 5)
        )


@pytest.mark.slow
def test_reverse_mode_through_the_step_equals_forward_mode():
    """`grad` and `jvp` of the carry's peak force through the sliding-mode step (impacts, sliding,
    located crossings) agree: no branch that a `where` leaves out puts an infinite derivative, and
    so a NaN, into the reverse pass (a square root at 0 did; `crossing`'s own test guards that one
    in every run). Slow: the two programs take 45 s to compile."""
    import jax

    peak = lambda k: cj.simulate(cj.make_params(K_GP=k), "carry", T=0.5).metrics.peak_grip
    reverse = float(jax.jit(jax.grad(peak))(0.5))
    forward = float(jax.jit(lambda k: jax.jvp(peak, (k,), (jnp.ones_like(k),))[1])(0.5))
    assert np.isfinite(reverse) and reverse == pytest.approx(forward, rel=1e-10)
