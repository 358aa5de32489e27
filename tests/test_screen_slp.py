"""The screen-and-SLP tuner: the local solver on minimax problems with known answers (through the
ask/tell interface, with an analytic evaluator: no simulation), the grip margin it keeps, the
screen's choice, resume by replay; and its exact Jacobians against central differences on the hard
model, where the grip constraint is active and where it is not."""

import dataclasses
import math

import numpy as np
import pytest
from scipy.optimize import minimize

from tuning import driver
from tuning.problem import Problem
from tuning.tuners import Evaluation, Query
from tuning.tuners.screen_slp import ScreenSLP, diverse_best, polish_merit

# Charalambous and Conn's CB2: max of three smooth functions, minimum 1.9522245 at (1.1390, 0.8996),
# where all three are active (a kink that a smooth maximum's gradient zigzags across).
CB2_MIN, CB2_AT = 1.9522245, np.array([1.1390383, 0.8995599])


def cb2(x):
    x1, x2 = x
    values = np.array([x1**2 + x2**4, (2 - x1) ** 2 + (2 - x2) ** 2, 2 * math.exp(x2 - x1)])
    jac = np.array(
        [[2 * x1, 4 * x2**3], [-2 * (2 - x1), -2 * (2 - x2)], [-2 * math.exp(x2 - x1), 2 * math.exp(x2 - x1)]]
    )
    return values, jac


class Analytic:
    """An evaluator of the driver's shape: peak_m = CB2's f_m (three 'masses'; a query with more
    draws, as the polish's, sees them in turn again), no lag, no shortfall, and a grip margin
    min_swi_m = x1 - floor at every mass (1 when there is no floor)."""

    compile_s = 0.0

    def __init__(self, floor=None, broken=()):
        self.floor, self.broken, self.calls, self.queries = floor, set(broken), 0, []

    def warm_up(self, query):
        pass

    def prepare(self, queries):
        self.prepared = list(queries)

    def __call__(self, query):
        self.queries.append(query)
        C, n = query.thetas.shape
        M, piece = len(query.draws), np.arange(len(query.draws)) % 3
        peak, J_peak = np.zeros((C, M)), np.zeros((C, M, n))
        swi, J_swi = np.ones((C, M)), np.zeros((C, M, n))
        for i, x in enumerate(query.thetas):
            values, jac = cb2(x)
            peak[i], J_peak[i] = values[piece], jac[piece]
            if self.floor is not None:
                swi[i], J_swi[i, :, 0] = x[0] - self.floor, 1.0
        finite = np.ones(C, bool)
        if self.calls in self.broken:  # a sample that diverged: NaN outputs, not finite
            peak[0], finite[0] = np.nan, False
        self.calls += 1
        zeros = np.zeros((C, M))
        jac = None
        if query.derivative == "jacobian":
            jac = {
                "parts": np.concatenate([J_peak, np.zeros_like(J_peak)], axis=1),  # the peak term, the lag term
                "c": np.zeros_like(J_peak),
                "min_swi": J_swi,
                "f": J_peak[:, 0],
            }
        return Evaluation(
            f=peak.max(1),
            c=zeros,
            parts=np.concatenate([peak, zeros], axis=1),
            valid=finite,
            holds=finite & (swi > 0).all(1),
            min_swi=swi,
            jacobian=jac,
        )


# The default problem's terms (max peak_grip, max rms_lag) and grip requirement, on three draws.
PROBLEM = Problem(names=("K_GP", "K_GI"), n_draws=3)


def solve(tuner, starts, evaluator, **kwargs):
    return driver.run(tuner, PROBLEM, None, np.asarray(starts, float), seed=0, evaluator=evaluator, **kwargs)


def test_the_local_solve_finds_the_minimax_optimum_where_three_pieces_are_active():
    result = solve(ScreenSLP(screen=0, local=2, steps=40), [[2.0, 2.0], [0.0, -1.0]], Analytic())
    best = result.tuner.candidates(result.state)[0]
    assert np.allclose(best, CB2_AT, atol=1e-4)
    assert cb2(best)[0].max() == pytest.approx(CB2_MIN, abs=1e-6)


@pytest.mark.parametrize("finer", [1, 2])
def test_what_is_compiled_in_the_background_is_the_program_the_local_solves_ask_for(finer):
    """The driver compiles the tuner's `later_queries` while the screen runs: each must have the kind
    and shapes (the compiled program's key) of a query the run then asks (with a finer polish, its
    shape too)."""
    evaluator, asked = Analytic(), []
    solve(
        ScreenSLP(screen=6, local=2, steps=3, polish_finer=finer),
        [[2.0, 2.0], [0.0, -1.0]],
        evaluator,
        on_step=lambda s, q, e: asked.append(q),
    )
    signature = lambda q: (q.derivative, q.mode, np.shape(q.thetas), np.shape(q.draws))
    assert evaluator.prepared and asked[0].derivative is None  # the screen comes first
    later = {signature(q) for q in asked[1:]}
    assert all(signature(q) in later for q in evaluator.prepared)
    assert any(q.derivative == "jacobian" for q in evaluator.prepared)
    assert len(evaluator.prepared) == finer  # the polish's program is the screen's unless its draws are finer


def test_the_grip_margin_is_kept_exactly_as_an_independent_solver_keeps_it():
    """With min_swi = x1 - 1.4 and a margin of 0.1, x1 >= 1.5: the answer is scipy SLSQP's on the epigraph."""
    tuner = ScreenSLP(screen=0, local=2, steps=40, swi_margin=0.1)
    reference = minimize(
        lambda z: z[2],
        x0=[2.0, 2.0, 10.0],
        method="SLSQP",
        constraints=[
            {"type": "ineq", "fun": lambda z: z[2] - cb2(z[:2])[0]},
            {"type": "ineq", "fun": lambda z: z[0] - 1.5},
        ],
        options={"ftol": 1e-12},
    )
    result = solve(tuner, [[2.0, 2.0], [0.5, 0.0]], Analytic(floor=1.4))
    best = result.tuner.candidates(result.state)[0]
    assert best[0] >= 1.5 - 1e-9
    assert np.allclose(best, reference.x[:2], atol=1e-4)
    assert cb2(best)[0].max() == pytest.approx(reference.fun, abs=1e-6)


def test_the_screen_hands_the_best_distinct_points_to_the_local_solve():
    thetas = np.array([[0.0, 0.0], [0.1, 0.0], [3.0, 3.0], [1.0, -1.0]])
    phi = np.array([2.0, 1.0, np.inf, 5.0])
    assert diverse_best(thetas, phi, 3, 0.5) == [1, 3]  # 0 is within 0.5 of the better 1; 2 did not run
    tuner = ScreenSLP(screen=16, local=3, radii=4, steps=1, search="sobol")
    state = tuner.init(PROBLEM, np.array([[2.0, 2.0]]), 0)
    asked, told = [], []
    while state.phase == "screen":  # in batches of the trials' shape (3 lanes x 4 radii)
        query = tuner.ask(state)
        assert query.derivative is None and len(query.thetas) == 12
        asked.append(query.thetas)
        told.append(Analytic()(query))
        state = tuner.tell(state, query, told[-1])
    thetas = np.concatenate(asked)
    assert len(thetas) == 24 and np.array_equal(thetas[0], [2.0, 2.0])  # the start, then 23 Sobol points
    phi = np.concatenate([ev.parts[:, :3].max(1) for ev in told])
    assert np.array_equal(state.theta[0], thetas[np.argmin(phi)])  # the best point starts the first solve
    assert tuner.ask(state).derivative == "jacobian"


def screen(tuner, starts):
    """Every batch of the tuner's screen on CB2: (points, merits), one entry per batch."""
    state = tuner.init(PROBLEM, np.asarray(starts, float), 0)
    batches = []
    while state.phase == "screen":
        query = tuner.ask(state)
        ev = Analytic()(query)
        batches.append((query.thetas, ev.parts[:, :3].max(1)))
        state = tuner.tell(state, query, ev)
    return batches


def test_the_cma_screen_spends_its_batches_where_the_merit_is_low():
    cma = screen(ScreenSLP(screen=116, local=3, radii=4, steps=1, search="cma", strategies=1), [[2.0, 2.0]])
    sobol = screen(ScreenSLP(screen=116, local=3, radii=4, steps=1, search="sobol"), [[2.0, 2.0]])
    assert [len(x) for x, _ in cma] == [len(x) for x, _ in sobol] == [12] * 10  # the same runs, the same batches
    assert np.array_equal(cma[0][0], sobol[0][0])  # the first batch: the start and Sobol points, for both
    lo, hi = np.array([-0.5, -0.5]), np.array([4.5, np.log(10.0)])  # the box: e^2.5 around the start, in bounds
    assert all(((x >= lo - 1e-12) & (x <= hi + 1e-12)).all() for x, _ in cma)
    # Later generations concentrate near the minimum (they would not if CMA-ES were never told): the
    # merit's median falls from about 11 in the first generation to within 0.5 of CB2's minimum.
    assert np.median(cma[-1][1]) < CB2_MIN + 0.5 < 5.0 < np.median(cma[1][1])
    assert max(np.median(phi) for _, phi in sobol) > 8.0  # Sobol points stay spread over the box
    best = lambda batches: min(phi.min() for _, phi in batches)
    assert best(cma) - CB2_MIN < 0.05 < 0.2 < best(sobol) - CB2_MIN


def test_the_screens_strategies_share_each_batch_and_each_is_told_its_own_half():
    tuner = ScreenSLP(screen=236, local=3, radii=4, steps=1, strategies=2)
    state = tuner.init(PROBLEM, np.array([[2.0, 2.0]]), 0)
    assert [es.popsize for es in state.es] == [6, 6]
    # The first from the start, the second from another point of the screen's box.
    assert np.allclose(state.es[0].mean, [2.0, 2.0]) and not np.allclose(state.es[1].mean, [2.0, 2.0])
    batches = screen(tuner, [[2.0, 2.0]])
    assert [len(x) for x, _ in batches] == [12] * 20
    # Each half of the last generation has concentrated near CB2's minimum, so each strategy was told
    # its own half (`told` refuses a population it did not ask for).
    for half in (slice(0, 6), slice(6, 12)):
        assert np.median(batches[-1][1][half]) < CB2_MIN + 0.5 < 5.0 < np.median(batches[1][1][half])
    with pytest.raises(Exception, match="strategies"):
        ScreenSLP(strategies=0)
    # A batch too small for two points per run runs fewer: here one, of the whole batch of 2.
    assert [es.popsize for es in ScreenSLP(local=1, radii=2).init(PROBLEM, np.array([[2.0, 2.0]]), 0).es] == [2]


def test_a_trial_that_breaks_is_not_taken_and_the_solve_goes_on():
    tuner = ScreenSLP(screen=0, local=2, steps=40)
    starts = [[2.0, 2.0], [0.0, -1.0]]
    clean = solve(tuner, starts, Analytic())
    broken = solve(tuner, starts, Analytic(broken={2}))  # the first start's widest first trial diverges
    assert clean.state.history["radius"][1][0] >= tuner.radius  # unbroken, that trial is taken
    assert broken.state.history["radius"][1][0] <= tuner.radius / 2  # broken, a shorter one (or none) is
    best = broken.tuner.candidates(broken.state)[0]
    assert np.allclose(best, CB2_AT, atol=1e-4)


@pytest.mark.parametrize(
    "screened, stop",
    [(8, 2 * 8 * 3 + 2 * 3 + 8 * 3 + 2 * 3), (40, 3 * 8 * 3)],
    ids=["in the local solves", "among the CMA-ES generations"],
)
def test_resume_replays_to_the_same_iterates(tmp_path, screened, stop):
    starts = [[2.0, 2.0], [0.0, -1.0]]
    tuner = ScreenSLP(screen=screened, local=2, steps=8)
    whole = solve(tuner, starts, Analytic())
    path = str(tmp_path / "run.ckpt")
    first = solve(tuner, starts, Analytic(), recorder=driver.Checkpoint(path), budget=driver.Budget(trajectories=stop))
    assert (first.state.phase == "screen") == (screened == 40)  # stopped among the generations, or after
    resumed = solve(tuner, starts, Analytic(), recorder=driver.Checkpoint(path, resume=True))
    assert resumed.evaluations == whole.evaluations
    assert np.array_equal(resumed.state.theta, whole.state.theta)
    assert resumed.state.history == whole.state.history


def test_finite_difference_jacobians_solve_the_same_problem():
    """The ablation's central differences: on a smooth problem the same optimum as exact Jacobians."""
    result = solve(
        ScreenSLP(screen=0, local=2, steps=40, jacobian="fd", fd_step=1e-5), [[2.0, 2.0], [0.0, -1.0]], Analytic()
    )
    best = result.tuner.candidates(result.state)[0]
    assert np.allclose(best, CB2_AT, atol=1e-4)


def test_without_the_local_solve_the_screen_goes_on_with_new_points():
    from tuning.tuners.ablation import ScreenOnly

    tuner = ScreenOnly(screen=8, local=2, radii=4)
    result = solve(tuner, [[2.0, 2.0]], Analytic(), budget=driver.Budget(trajectories=6 * 8 * 3))
    assert result.evaluations == 6  # 2 batches of the screen, then 4 more
    thetas = np.asarray(result.record.thetas)
    assert len(np.unique(thetas, axis=0)) == len(thetas) == 48  # every point is new
    best = result.tuner.candidates(result.state)[0]
    assert cb2(best)[0].max() == pytest.approx(min(cb2(t)[0].max() for t in thetas))


def test_the_jacobians_are_the_central_differences_of_the_hard_model():
    """Every per-draw output the local solve linearises, at a mass where the grip holds (the margin
    min_swi is the active measure) and one where it is lost (the shortfall c is): forward mode
    against central differences of the same discretised model (training step, float64)."""
    from test_tuning import BASE, PROBLEM, THETA

    from tuning.evaluate import Evaluator

    masses = np.asarray([1.0, 5.0])
    evaluate = Evaluator(PROBLEM, BASE)
    ev = evaluate(Query(THETA, masses, "jacobian"))
    assert (ev.min_swi[:, 0] > 0.05).all() and (ev.c[:, 1] > 0.1).any(), "one mass holds, the other loses the grip"
    h, n = 1e-6, THETA.shape[1]
    shifted = np.concatenate([THETA + h * e for e in np.eye(n)] + [THETA - h * e for e in np.eye(n)])
    values = evaluate(Query(shifted, masses))
    K = len(THETA)
    for name in ("parts", "c", "min_swi"):
        v = getattr(values, name).reshape(2, n, K, -1)
        fd = np.moveaxis((v[0] - v[1]) / (2 * h), 0, -1)  # (K, M, n)
        scale = np.abs(fd).max() + 1e-12
        np.testing.assert_allclose(ev.jacobian[name], fd, rtol=1e-4, atol=1e-5 * scale, err_msg=name)


def test_the_linear_program_is_the_model_of_any_problem_at_its_minimum():
    """The trust-region program of a problem with a cvar term, a mean term and a bound on a metric
    (no grip requirement): its step minimises the linearised merit over the box, and its predicted
    fall is the merit's fall in that model."""
    from tuning.problem import Objective, Requirement
    from tuning.tuners.screen_slp import merit, program, segments

    problem = Problem(
        names=("K_GP", "K_GI", "tau"),
        minimise=(Objective("peak_grip", "cvar:0.5", 1.0), Objective("rms_lag", "mean", 1000.0)),
        require=(Requirement("peak_grip", "at_most", 30.0),),
    )
    M, n = 4, 3
    rng = np.random.default_rng(0)
    out = {
        "parts": rng.normal(30.0, 3.0, 2 * M),
        "J_parts": rng.normal(0.0, 5.0, (2 * M, n)),
        "c": rng.normal(0.0, 2.0, M),
        "J_c": rng.normal(0.0, 5.0, (M, n)),
        "swi": np.zeros(0),
        "J_swi": np.zeros((0, n)),
    }
    settings = dict(penalty=100.0, swi_penalty=20.0, swi_margin=0.1)
    model = lambda d: merit(
        {
            "parts": (out["parts"] + out["J_parts"] @ d)[None],
            "c": (out["c"] + out["J_c"] @ d)[None],
            "swi": np.zeros((1, 0)),
        },
        problem,
        M,
        **settings,
    )[0]
    out["phi"] = model(np.zeros(n))
    assert [over for _, over in segments(problem, M)] == ["cvar:0.5", "mean"]
    theta, lo, hi, radius = np.zeros(n), np.full(n, -1.0), np.full(n, 1.0), 0.3
    d, fall = program(theta, out, radius, lo, hi, problem, M, **settings)
    assert np.abs(d).max() <= radius + 1e-9
    assert fall == pytest.approx(out["phi"] - model(d), rel=1e-7, abs=1e-7)
    others = rng.uniform(-radius, radius, (4000, n))
    assert min(model(x) for x in others) >= model(d) - 1e-7


def test_where_no_solve_holds_the_polish_minimises_the_judges_violation():
    """A misses the grip by 3 N (0.3 of F_lim) at all three draws, B by 6 N at one. The priced sum
    of misses prefers B; the judge's violation (the largest relative miss) prefers A, and so does the
    polish where no local solve held."""
    M, zeros = 3, np.zeros((2, 3))
    shortfall = np.array([[3.0, 3.0, 3.0], [6.0, 0.0, 0.0]])
    ev = Evaluation(
        f=np.zeros(2),
        c=shortfall,
        parts=np.concatenate([zeros, zeros], axis=1),
        valid=np.ones(2, bool),
        holds=np.zeros(2, bool),
        min_swi=zeros,
        miss=(shortfall - 0.01) / 10.0,
    )
    tuner = ScreenSLP()
    assert np.argmin(polish_merit(tuner, ev, PROBLEM, M)) == 1
    assert np.argmin(polish_merit(tuner, ev, PROBLEM, M, infeasible=True)) == 0


class Recording:
    """An evaluator with nothing to compile that keeps the queries it was asked."""

    compile_s = 0.0

    def __init__(self):
        self.queries = []

    def warm_up(self, query):
        pass

    def prepare(self, queries):
        pass


class Banded(Recording):
    """An evaluator for any draws: the peak (x0 - log M_b)^2 at each, and the grip lost (by 10 N per
    log unit of x0 below 0.5) only at the body mass 2 kg, a band between the training draws."""

    def __call__(self, query):
        self.queries.append(query)
        x0 = query.thetas[:, :1]
        mass = np.asarray(query.draws, float).reshape(-1)
        peak = (x0 - np.log(mass)) ** 2
        c = np.where(np.isclose(mass, 2.0), 10.0 * np.maximum(0.5 - x0, 0.0), 0.0)
        jac = None
        if query.derivative == "jacobian":  # along x0 alone
            along = lambda d: np.stack([d, np.zeros_like(d)], axis=-1)
            J_peak = along(2.0 * (x0 - np.log(mass)))
            jac = {
                "parts": np.concatenate([J_peak, np.zeros_like(J_peak)], axis=1),
                "c": along(np.where(c > 0, -10.0, 0.0)),
                "min_swi": np.zeros_like(J_peak),
                "f": J_peak[:, 0],
            }
        return Evaluation(
            f=peak.max(1),
            c=c,
            parts=np.concatenate([peak, np.zeros_like(peak)], axis=1),
            valid=np.ones(len(x0), bool),
            holds=(c <= 0).all(1),
            min_swi=np.ones_like(c),
            miss=c / 10.0 - 1e-3,
            jacobian=jac,
        )


def test_going_on_polishes_from_the_answer_with_the_added_draw_and_meets_the_requirement_there():
    """`go_on` after a run: every query of the round has the training draws with the added one in
    place of the nearest, the round ends after `polish_again` generations, and its answer holds at
    the added draw, which the run before never saw (its answer misses there)."""
    tuner = ScreenSLP(screen=0, local=2, steps=2, polish=2, polish_again=6)
    before = solve(tuner, [[0.0, 0.0]], Banded())
    answer = np.array([0.0, 0.0])  # misses at 2 kg: x0 < 0.5
    state = tuner.go_on(before.state, answer, np.array([[2.0]]))
    evaluator = Banded()
    after = solve(tuner, [[0.0, 0.0]], evaluator, state=state)
    trained = before.state.draws.reshape(-1)
    assert not np.isclose(trained, 2.0).any()
    nearest = np.argmin(np.abs(np.log(trained) - np.log(2.0)))  # its place: the shapes stay
    assert len(evaluator.queries) == 6
    for query in evaluator.queries:
        assert np.array_equal(
            np.asarray(query.draws).reshape(-1), np.where(np.arange(len(trained)) == nearest, 2.0, trained)
        )
    (best,) = tuner.candidates(after.state)
    assert best[0] >= 0.5 - 1e-12
    assert np.abs(evaluator.queries[0].thetas - answer).max() < 2.0  # a polish near the answer, sigma 0.3


class Between(Recording):
    """An evaluator for any draws: the peak (x0 - 1)^2 at the training draws and (x0 + 1)^2 at every
    other draw. On the training draws alone the best is x0 = 1; over a finer grid, x0 = 0."""

    def __init__(self, trained):
        super().__init__()
        self.trained = np.asarray(trained, float).reshape(-1)

    def __call__(self, query):
        self.queries.append(query)
        x0 = query.thetas[:, :1]
        mass = np.asarray(query.draws, float).reshape(-1)
        at_training = np.isclose(mass[:, None], self.trained[None, :], rtol=1e-12).any(1)
        peak = np.where(at_training, (x0 - 1.0) ** 2, (x0 + 1.0) ** 2)
        jac = None
        if query.derivative == "jacobian":  # along x0 alone
            J = np.where(at_training, 2.0 * (x0 - 1.0), 2.0 * (x0 + 1.0))
            J_peak = np.stack([J, np.zeros_like(J)], axis=-1)
            jac = {
                "parts": np.concatenate([J_peak, np.zeros_like(J_peak)], axis=1),
                "c": np.zeros_like(J_peak),
                "min_swi": np.zeros_like(J_peak),
                "f": J_peak[:, 0],
            }
        zeros = np.zeros_like(peak)
        return Evaluation(
            f=peak.max(1),
            c=zeros,
            parts=np.concatenate([peak, zeros], axis=1),
            valid=np.ones(len(x0), bool),
            holds=np.ones(len(x0), bool),
            min_swi=np.ones_like(peak),
            jacobian=jac,
        )


@pytest.mark.parametrize("finer", [1, 2])
def test_a_polish_on_finer_draws_keeps_the_screens_runs_per_batch_and_does_not_overfit_the_training(finer):
    """The local solves, on the training draws alone, end at x0 = 1, whose peak between those draws
    is 4. The polish on twice the draws (a finer grid over the same widened box) finds x0 = 0, the
    minimax over that grid (peak 1); with `polish_finer=1` it stays where the training draws put it.
    Its population is cut so that a generation runs the screen batch's simulations."""
    trained = PROBLEM.fixed_training_draws()
    tuner = ScreenSLP(screen=0, local=2, steps=3, polish=30, polish_finer=finer)
    evaluator = Between(trained)
    result = solve(tuner, [[0.9, 0.0]], evaluator)
    assert all(np.isclose(b.theta[0], 1.0, atol=0.05) for b in result.state.best if np.isfinite(b.value))
    polish = evaluator.queries[-30:]
    runs = tuner.local * tuner.radii * len(trained)
    assert all(len(q.draws) == finer * len(trained) and len(q.thetas) * len(q.draws) == runs for q in polish)
    assert len(evaluator.queries[-31].draws) == len(trained)  # the last one before the polish
    assert tuner.run_text(result.state) is None  # a solve held: the plain polish
    x0 = result.state.polished.theta[0]
    assert abs(x0 - (0.0 if finer == 2 else 1.0)) < 0.05


class MissedBetween(Between):
    """`Between` with a requirement missed everywhere, by (peak + 1) / 10 relative to its bound: no
    candidate holds, and the least violation is the minimax peak over the draws."""

    def __call__(self, query):
        ev = super().__call__(query)
        peak = ev.parts[:, : len(query.draws)]
        jac = ev.jacobian
        if jac is not None:
            jac = jac | {"c": jac["parts"][:, : len(query.draws)]}
        return ev._replace(c=peak + 1.0, holds=np.zeros(len(peak), bool), miss=(peak + 1.0) / 10.0, jacobian=jac)


@pytest.mark.parametrize("finer", [1, 2])
def test_where_no_solve_holds_the_polish_minimises_the_violation_on_finer_draws_with_a_wide_step(finer):
    """No candidate holds. The local solves, on the training draws alone, end at x0 = 1, whose miss
    between those draws is 0.5. The feasibility polish runs on `feasibility_finer` times the draws at
    the screen's population (so that many times its runs), from an initial step of
    `feasibility_sigma`, and finds x0 = 0 (a miss of 0.2 over the finer grid); on the training draws
    alone it stays at x0 = 1. A problem that holds keeps the plain polish (`test_a_polish_on_finer...`)."""
    trained = PROBLEM.fixed_training_draws()
    tuner = ScreenSLP(screen=0, local=2, steps=3, polish=30, feasibility_finer=finer)
    evaluator, said = MissedBetween(trained), []
    result = solve(tuner, [[0.9, 0.0]], evaluator, on_step=lambda *step: said.append(tuner.progress_text(*step)))
    assert result.state.infeasible
    (start,) = [text for text in said if text and "polish:" in text]  # said once, as it starts
    assert f"of {tuner.local * tuner.radii} on {finer * len(trained)} training draws" in start
    assert "minimises the judge's violation, from an initial step of 1 in log units" in start
    assert f"on {finer * len(trained)} training draws" in tuner.run_text(result.state)  # the history figure's title
    polish = evaluator.queries[-30:]
    assert all(len(q.draws) == finer * len(trained) and len(q.thetas) == tuner.local * tuner.radii for q in polish)
    assert len(evaluator.queries[-31].draws) == len(trained)  # the last one before the polish
    spread = polish[0].thetas[:, 1].std()  # K_GI: no pull, so the first generation shows the step
    assert 0.7 * tuner.feasibility_sigma < spread < 1.3 * tuner.feasibility_sigma
    x0 = result.state.polished.theta[0]
    assert abs(x0 - (0.0 if finer == 2 else 1.0)) < 0.05


def test_a_polish_afresh_starts_a_new_strategy_from_the_answer_with_the_first_steps_reach():
    """`polish_afresh` (for a round at a finer step, `session.run`): `polish` generations of a new
    strategy centred on the given answer, whose first generation spreads by the polish's initial step
    (the feasibility polish's where no solve held), not by the shrunken step the polish ended with;
    its candidates are that round's best alone."""
    trained = PROBLEM.fixed_training_draws()
    tuner = ScreenSLP(screen=0, local=2, steps=3, polish=20)
    before = solve(tuner, [[0.9, 0.0]], MissedBetween(trained))
    assert before.state.infeasible
    answer = before.state.polished.theta
    ended = Analytic()
    solve(tuner, [[0.9, 0.0]], ended, state=tuner.polish_further(before.state, answer))
    state = tuner.polish_afresh(before.state, answer)
    assert state.generation == 0 and state.polished.theta is None and before.state.polished.theta is answer
    again = MissedBetween(trained)
    after = solve(tuner, [[0.9, 0.0]], again, state=state)
    assert after.evaluations == tuner.polish
    first = again.queries[0].thetas
    assert np.allclose(first.mean(0), answer, atol=0.6)  # centred on the answer
    # K_GI (no pull): the new strategy's first spread is the feasibility step, far above where the
    # old one had shrunk to.
    assert 0.6 * tuner.feasibility_sigma < first[:, 1].std() < 1.4 * tuner.feasibility_sigma
    assert first[:, 1].std() > 3 * ended.queries[0].thetas[:, 1].std()
    (best,) = tuner.candidates(after.state)
    assert np.array_equal(best, after.state.polished.theta)
    assert dataclasses.replace(tuner, polish=0).polish_afresh(before.state, answer) is None


def test_where_only_the_feasibility_polish_holds_the_local_solves_run_again_from_its_answer():
    """No solve held, and the feasibility polish's best holds at its training draws: going on from it
    (`polish_further`) runs the local solves again, from it and points around it, on the training
    draws in the first solves' shapes (nothing compiled again), then the plain polish; the solves
    then reach the minimax optimum the polish's answer is far from."""
    trained = PROBLEM.fixed_training_draws()
    tuner = ScreenSLP(screen=0, local=2, steps=30, polish=4)
    first = MissedBetween(trained)
    before = solve(tuner, [[0.9, 0.0]], first)
    assert before.state.infeasible and not before.state.polished.holds
    answer = before.state.polished.theta
    assert tuner.polish_further(before.state, answer).phase == "polish"  # nothing holds: the polish goes on
    held = dataclasses.replace(before.state, polished=before.state.polished._replace(holds=True))
    state = tuner.polish_further(held, answer)
    assert state.phase == "jacobian" and not state.infeasible and state.resolved
    assert np.array_equal(state.theta[0], answer) and np.abs(state.theta[1:] - answer).max() < 1.0
    again, said = Analytic(), []
    after = solve(tuner, [[0.9, 0.0]], again, state=state, on_step=lambda *s: said.append(tuner.progress_text(*s)))
    shape = lambda q: (q.derivative, np.shape(q.thetas), np.shape(q.draws))
    assert shape(again.queries[0]) == ("jacobian", (tuner.local, 2), trained.shape)
    assert {shape(q) for q in again.queries} <= {shape(q) for q in first.queries}
    assert any(text and "local solves again" in text for text in said)
    assert tuner.run_text(after.state) is None  # the plain polish followed
    best = after.tuner.candidates(after.state)[0]
    assert np.allclose(best, CB2_AT, atol=1e-3) and cb2(answer)[0].max() > CB2_MIN + 0.1


def test_a_further_polish_goes_on_with_the_same_strategy_whichever_answer_was_chosen():
    """`polish_further`: the next `polish` generations ask exactly what a run with twice the polish
    would have asked (the strategy goes on, it does not restart), and its only candidate is the
    polish's best, no worse on the training draws; the same where the chosen answer is a local
    solve's (the validation preferred it to the polish's)."""
    tuner, starts = ScreenSLP(screen=0, local=2, steps=2, polish=3), [[2.0, 2.0], [0.0, -1.0]]
    before = solve(tuner, starts, Analytic())
    longer = Analytic()
    solve(dataclasses.replace(tuner, polish=6), starts, longer)
    polished = before.state.polished.theta
    state = tuner.polish_further(before.state, before.state.polished.theta)
    other = tuner.polish_further(before.state, polished + 1e-3)  # a local solve's answer
    assert other.phase == "polish" and other.until == state.until
    assert np.array_equal(other.polish_es.mean, state.polish_es.mean)
    further = Analytic()
    after = solve(tuner, starts, further, state=state)
    assert after.evaluations == 3
    for ours, theirs in zip(further.queries, longer.queries[-3:]):
        assert np.array_equal(ours.thetas, theirs.thetas) and np.array_equal(ours.draws, theirs.draws)
    (best,) = tuner.candidates(after.state)
    assert cb2(best)[0].max() <= cb2(polished)[0].max()
    assert tuner.polish_further(after.state, best) is not None  # and it can go on again
    assert dataclasses.replace(tuner, polish=0).polish_further(before.state, polished) is None
