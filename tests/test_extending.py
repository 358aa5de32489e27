"""Each kind of change is one file plus its test: a scenario, a metric, an integrator and a tuner,
registered from this file alone, run through `simulate`, a sweep (Python and the command line) and
the race, without touching a library file (docs/architecture.md, "How to add")."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

import coopjax as cj
from coopjax import cli, integration, model, objectives, params, scenarios, stability, sweeps
from coopjax.integration.plain_rk4 import PlainRK4
from coopjax.scenarios import Clock
from tuning import cli as tune_cli
from tuning import problem as pb
from tuning import session
from tuning.studies import race
from tuning.tuners import Query, Tuner
from tuning.tuners import register as register_tuner
from tuning.tuners import setting
from tuning.tuners import TUNERS
from tuning.tuners.random_search import RandomSearch

from test_tuning_cli import SMALL_TUNE


# --- a scenario with an amplitude parameter of its own: grip, then hold still -------------------


def hold_command(p, clock: Clock):
    grip = scenarios.bump(clock, 0.0, 1.0)
    return tuple(tuple(s * p.A_hold * x for x in grip) for s in (1.0, -1.0))


HOLD = scenarios.Scenario(
    name="hold",
    T=1.5,
    command=hold_command,
    windows={"grip": (0.5, 1.5), "lag": (1.0, 1.5)},
    description="grip, then hold still (a test scenario)",
    parameters={"A_hold": params.Spec(0.1, "m/s", False, "finite", "hold scenario: grip amplitude")},
)


# --- a metric on a signal no built-in metric uses: the body's largest speed ----------------------


def _speed_update(peak, obs, p, ctx):
    return jnp.maximum(peak, jnp.abs(obs.y[model.STATE_NAMES.index("v_o")]))


BODY_SPEED = objectives.Metric(
    "body_speed",
    "m/s",
    "largest |v_o| over the run",
    lambda b, d, ctx: jnp.zeros(tuple(b), d),
    _speed_update,
    lambda peak, ctx: peak,
)


# --- an integrator: Heun's method (second order), with its own stability function ---------------


class Heun(integration.Integrator):
    name = "heun"
    description = "Heun's second-order method (a test integrator)"
    switches = ("smooth", "blend")

    @staticmethod
    def amplification(z):
        return np.abs(1 + z + z**2 / 2)

    def step(self, ps, y, t, dt, scenario, options):
        f = lambda t, y: model.vector_field(ps, y, Clock.at(t), scenario, options)
        k1, aux = f(t, y)
        k2, _ = f(t + dt, y + dt * k1)
        return y + dt / 2 * (k1 + k2), aux, None  # no path: the loop takes the step as one piece

    def observe(self, ps, y, t, dt, scenario, options):
        return model.vector_field(ps, y, Clock.at(t), scenario, options)[1]


# --- a tuner: evaluate the starts once and keep the best -----------------------------------------


@dataclasses.dataclass
class StartsState:
    starts: np.ndarray
    problem: object
    done: bool = False
    best: np.ndarray | None = None


@dataclasses.dataclass(frozen=True)
class BestStart(Tuner):
    name = "best start"
    description = "the best of the starting points (a test tuner)"
    plain_run = True  # it ends on its own: `coopjax tune --method "best start"`

    pick: int = setting(0, "which of the ranked starts to hand over (0: the best)", "--pick")

    def init(self, problem, starts, seed):
        return StartsState(np.asarray(starts), problem)

    def ask(self, state):
        return None if state.done else Query(state.starts, state.problem.training_draws(0, 0))

    def tell(self, state, query, ev):
        order = np.lexsort((ev.f, ~ev.holds))  # holding first, then the lowest objective
        return dataclasses.replace(state, best=query.thetas[order[min(self.pick, len(order) - 1)]], done=True)

    def candidates(self, state):
        return [] if state.best is None else [state.best]


@pytest.fixture(scope="module")
def registered():
    scenarios.register(HOLD)
    objectives.register(BODY_SPEED)
    integration.register(Heun)
    register_tuner(BestStart)
    yield
    # Leave the registries as the other test files expect them.
    del scenarios.SCENARIOS["hold"], objectives.METRICS["body_speed"], integration.INTEGRATORS["heun"]
    del TUNERS["best start"], params.PARAMETERS["A_hold"], params.OWNER["A_hold"]


def test_a_new_scenario_metric_and_integrator_run_through_simulate(registered):
    p = cj.make_params(A_hold=0.05, M_b=np.array([1.0, 3.0]))  # the scenario's own parameter
    config = cj.Config("hold", switch="smooth", integrator="heun", dt=2.5e-4)
    solution = cj.simulate(p, config, every=400)
    m = solution.metrics
    assert {"body_speed", "min_grip", "rms_lag"} <= set(m._fields)
    assert np.all(np.asarray(m.finite)) and np.all(np.asarray(m.body_speed) > 0)
    # The metric sees what the trajectory records: its value is the recorded speed's maximum (the
    # record is every 400th step, so it can only be below).
    v_o = np.abs(np.asarray(solution.trajectory.state("v_o")))
    assert np.all(v_o.max(0) <= np.asarray(m.body_speed) * (1 + 1e-12))
    # Heun against RK4 on the same model: second order, close at this step. Its steps carry no path,
    # so the loop takes each as one piece: the path metrics are RK4's too, not a believable 0.
    rk4 = cj.simulate(p, config, integrator="rk4").metrics
    np.testing.assert_allclose(m.peak_grip, rk4.peak_grip, rtol=1e-3)
    assert np.all(np.asarray(m.slip) > 1e-3)  # the grip builds up through the window: a real shortfall
    for name in ("slip", "crush", "impact"):
        ours, theirs = np.asarray(getattr(m, name)), np.asarray(getattr(rk4, name))
        np.testing.assert_allclose(ours, theirs, rtol=1e-2, atol=1e-9, err_msg=name)
    # Its own stability function sets the step check: its region is smaller than RK4's.
    limit_heun = integration.INTEGRATORS["heun"].stable_dt(stability.fastest_modes(p, config))
    limit_rk4 = PlainRK4().stable_dt(stability.fastest_modes(p, config))
    assert np.all(limit_heun < limit_rk4)
    with pytest.raises(cj.InputError, match="too large for heun"):
        cj.simulate(p, config, dt=1.05 * float(limit_heun.min()))
    # The integrator refuses the switch it does not integrate, by its own declaration.
    with pytest.raises(cj.InputError, match="the heun integrator does not integrate the hard switch"):
        cj.simulate(p, "hold", integrator="heun")


def test_they_run_through_a_sweep_and_the_command_line(registered, fresh_dir, capsys):
    table = cj.sweep(
        cj.Config("hold", switch="smooth", integrator="heun", dt=5e-4), 4, vary={"A_hold": "uniform:0.05:0.1"}
    )
    assert "body_speed" in table.columns and "A_hold" in table.columns and (table["status"] == "ok").all()
    assert sweeps.column_units()["body_speed"] == "m/s"
    code = cli.main(
        [
            "sweep",
            "--scenario",
            "hold",
            "--switch",
            "smooth",
            "--integrator",
            "heun",
            "--dt",
            "5e-4",
            "--n",
            "4",
            "--vary",
            "A_hold=uniform:0.05:0.1",
            "--devices",
            "1",
            "--quiet",
            "--out",
            "s.csv",
        ]
    )
    assert code == 0, capsys.readouterr().err
    header = open("s.csv").readline().strip().split(",")
    assert "body_speed" in header and "A_hold" in header
    # The command line's help lists what is registered.
    parser = cli.build_parser()
    text = next(a for a in parser._actions if a.dest == "command").choices["sweep"].format_help()
    assert "hold" in text and "heun" in text and "body_speed [m/s]" in text


def test_an_incomplete_extension_is_refused_when_it_is_registered():
    class NoObserve(integration.Integrator):
        name, switches = "no observe", ("smooth",)

        def step(self, ps, y, t, dt, scenario, options):
            return y, None, None

    with pytest.raises(TypeError, match="observe"):
        integration.register(NoObserve)

    @dataclasses.dataclass(frozen=True)
    class NoCandidates(Tuner):
        name = "no candidates"

        def init(self, problem, starts, seed):
            return None

        def ask(self, state):
            return None

        def tell(self, state, query, ev):
            return state

    with pytest.raises(TypeError, match="candidates"):
        register_tuner(NoCandidates)
    assert "no observe" not in integration.INTEGRATORS and "no candidates" not in TUNERS


def test_a_new_tuner_runs_as_a_plain_tune_with_its_own_flag(registered, fresh_dir, capsys):
    # Its flag is its own: another method refuses it, in one line, before any work.
    code = cli.main(["tune", "--pick", "1", *SMALL_TUNE, "--out", "other.json"])
    err = capsys.readouterr().err
    assert code == 2 and "--pick sets the best start tuner" in err and len(err.strip().splitlines()) == 1
    parser = cli.build_parser()
    text = next(a for a in parser._actions if a.dest == "command").choices["tune"].format_help()
    assert "best start" in text and "--pick" in text
    args = parser.parse_args(["tune", "--method", "best start", "--pick", "1"])
    assert tune_cli.make_tuner(args) == BestStart(pick=1)


@pytest.mark.slow  # a whole session (18 s); the registry, the flag and the command's choice stay in CI (above)
def test_a_new_tuner_runs_through_a_session(registered):
    problem = pb.Problem(
        names=pb.GAINS, n_draws=2, uncertain=(("M_b", "loguniform", 0.8, 4.5),), margin=0.0, jitter=False
    )
    options = session.Options(starts=2, held_out=2, judge_dt=2e-3)
    prepared = session.prepare(problem, BestStart(pick=1), options)
    tuned = session.run(prepared)
    assert set(tuned.params) == set(pb.GAINS) and tuned.result.evaluations == 1
    assert tuned.params in [pb.from_log(s, pb.GAINS) for s in prepared.starts()]  # the start it picked
    assert tuned.verdict.requirements and tuned.selection["candidates"] == 1


@pytest.mark.slow  # the race runs the same sessions (tests/test_session.py races in CI)
def test_a_new_tuner_runs_through_the_race(registered):
    problem = pb.Problem(
        names=pb.GAINS, n_draws=2, uncertain=(("M_b", "loguniform", 0.8, 4.5),), margin=0.0, jitter=False
    )
    options = session.Options(starts=2, held_out=2, judge_dt=2e-3)
    # A value-only reference keeps the race to value compiles.
    sessions = {"random search": session.prepare(problem, RandomSearch(block=2, generations=1), options)}
    sessions["best start"] = session.prepare(problem, BestStart(pick=1), options)
    result = race.run(sessions, "random search", seeds=[0], log=lambda s: None)
    row = result["per_seed"][0]
    assert row["evaluations"]["best start"] == 2 and row["chosen"]["best start"] is not None
    assert result["tuners"] == ["random search", "best start"]
