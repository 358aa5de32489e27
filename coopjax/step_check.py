"""The two-step check: is an answer a property of the model, or of one step size?

A fixed-step answer can be accurate to O(dt) on average and still be wrong at the one point a user or
an optimiser picks out of thousands. An event the grid does not resolve there (a re-contact near the
end of the run, a brief loss of grip between samples) changes that answer by far more than the step's
usual accuracy, and a search over parameters is drawn to exactly such points, because they look good.

The check runs the same parameters again at dt / 2 and compares the three answers a user reads:
min grip (absolute), peak grip and RMS lag (relative), against the accuracy tolerances. Where the
step is converged the two runs differ by far less than the tolerances (at dt = 1e-3 by under a tenth
of them on random samples); a sample whose answers move by more is a step artefact, and a sweep marks
it so (status `step_artefact`). The tuner's judge runs such a sample again at dt / 2, dt / 4, ... and
reads its values at the first step that agrees with its half; one that never agrees is rejected.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from coopjax import scenarios
from coopjax.objectives.base import missing_windows

from coopjax.config import Config

# The accuracy tolerances against the dt -> 0 limit: min grip in N, peak grip and RMS lag relative.
TOLERANCE = {"min_grip": ("absolute", 0.05), "peak_grip": ("relative", 0.02), "rms_lag": ("relative", 0.02)}
METRICS = tuple(TOLERANCE)


def checked(config: Config) -> tuple[str, ...]:
    """The checked metrics the configuration's scenario has windows for (the paper scenario has no
    lag window: its RMS lag is NaN, and would make every sample's check NaN)."""
    scenario = scenarios.get(config.scenario)
    return tuple(m for m in METRICS if not missing_windows(m, scenario))


def halved(config: Config) -> Config:
    """The check's configuration: the same run at half the step, with (at least) the checked metrics."""
    metrics = tuple(config.metrics) + tuple(m for m in checked(config) if m not in config.metrics)
    return dataclasses.replace(config, dt=config.dt / 2, metrics=metrics)


def step_error(coarse: dict, fine: dict) -> np.ndarray:
    """Per sample, the largest of the disagreements of the metrics in `coarse` (those of `METRICS`,
    `checked`), in units of their tolerances (1 = at the tolerance; NaN where either run is not
    finite). `coarse` and `fine` map metric names to arrays."""
    names = [n for n in METRICS if n in coarse]
    ratios = []
    for name in names:
        kind, tol = TOLERANCE[name]
        a, b = np.asarray(coarse[name], np.float64), np.asarray(fine[name], np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            gap = np.abs(a - b) if kind == "absolute" else np.abs(a - b) / np.abs(b)
            gap = np.where((kind == "relative") & (a == b), 0.0, gap)  # 0/0 where both are 0
        ratios.append(gap / tol)
    out = np.max(ratios, axis=0)
    bad = np.any(
        [
            ~np.isfinite(np.asarray(coarse[n], np.float64)) | ~np.isfinite(np.asarray(fine[n], np.float64))
            for n in names
        ],
        axis=0,
    )
    return np.where(bad, np.nan, out)


def artefacts(error: np.ndarray) -> np.ndarray:
    """Where the two-step check fails: the answers moved by more than a tolerance."""
    return np.nan_to_num(np.asarray(error, np.float64), nan=0.0) > 1.0
