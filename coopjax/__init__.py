"""coopjax: a JAX-vectorised, differentiable simulator of two cooperating space robots.

The public API (`coopjax.simulate`, `coopjax.make_params`, ...) is loaded on first use, so that the
`coopjax` command starts (and answers Ctrl-C) before JAX is imported. `coopjax.api` lists it.
"""

import importlib

__version__ = "0.1.0"

_API = frozenset(
    {
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
    }
)


def __getattr__(name):
    if name in _API:
        return getattr(importlib.import_module("coopjax.api"), name)
    raise AttributeError(f"module 'coopjax' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | _API)
