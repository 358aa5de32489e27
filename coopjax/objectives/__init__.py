"""Metrics, declared once each, and accumulated while the scan runs.

A metric is one `Metric`: its name, unit and meaning, and how it folds the samples of a run into a
small accumulator (`init`, `update`, `finalize`). `register` makes it known to `simulate`, the sweep
table (its columns and units), the command line's help and the tuner. The built-in metrics of the
grip and of tracking are in `grip.py`, `margin.py` and `tracking.py`.

Sweeps keep no trajectory: each step folds its `Observation` (the state and signals at the sample
time t_k = k dt, k = 0..N) into the accumulators. Window membership is decided on the integer k, so
float32 rounding of t cannot move a sample in or out of a window.
"""

from coopjax.objectives.base import (
    METRICS,
    STATUS_FIELDS,
    Context,
    Metric,
    Metrics,
    MetricSet,
    Weights,
    check_names,
    loss,
    mark_unusable,
    on_grid,
    register,
)
from coopjax.objectives import grip, margin, tracking  # noqa: E402,F401  (the built-in metrics register themselves)

__all__ = [
    "Context",
    "METRICS",
    "Metric",
    "MetricSet",
    "Metrics",
    "STATUS_FIELDS",
    "Weights",
    "check_names",
    "loss",
    "mark_unusable",
    "on_grid",
    "register",
]
