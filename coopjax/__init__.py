"""coopjax: a JAX-vectorised, differentiable simulator of two cooperating space robots."""

from coopjax.integration import INTEGRATORS, SimConfig, Solution, Trajectory, integrate, rk4, simulate, step
from coopjax.model import STATE_NAMES, Aux, Options, momentum, vector_field
from coopjax.objectives import Metrics, Weights, loss
from coopjax.params import PARAMETERS, Params, make_params
from coopjax.scenarios import SCENARIOS
from coopjax.sweeps import sweep
from coopjax.analysis import linearize
from coopjax.devices import use_all_cores

__version__ = "0.1.0"
