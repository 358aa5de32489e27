"""Everything `import coopjax` offers, imported here once (coopjax/__init__.py loads it on first use)."""

from coopjax.config import Config
from coopjax.cache import use_cache
from coopjax.devices import use_all_cores
from coopjax.errors import InputError
from coopjax.integration import INTEGRATORS, Integrator, Observation, Solution, Trajectory, integrate, rk4, step
from coopjax.integration import register as register_integrator
from coopjax.model import STATE_NAMES, Aux, Options, momentum, vector_field
from coopjax.objectives import METRICS, Metric, Metrics, Weights, loss
from coopjax.objectives import register as register_metric
from coopjax.params import PARAMETERS, Params, make_params
from coopjax.scenarios import SCENARIOS, Scenario
from coopjax.scenarios import register as register_scenario
from coopjax.simulation import simulate
from coopjax.sweeps import sweep
from coopjax.analysis import linearize

__all__ = [
    "Aux",
    "Config",
    "INTEGRATORS",
    "InputError",
    "Integrator",
    "METRICS",
    "Metric",
    "Metrics",
    "Observation",
    "Options",
    "PARAMETERS",
    "Params",
    "SCENARIOS",
    "STATE_NAMES",
    "Scenario",
    "Solution",
    "Trajectory",
    "Weights",
    "integrate",
    "linearize",
    "loss",
    "make_params",
    "momentum",
    "register_integrator",
    "register_metric",
    "register_scenario",
    "rk4",
    "simulate",
    "step",
    "sweep",
    "use_all_cores",
    "use_cache",
    "vector_field",
]
