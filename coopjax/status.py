"""Why a sample's answer is, or is not, trusted: one vocabulary for runs, sweeps and the tuner's judge.

In the manner of diffrax's `RESULTS`: a small integer code per sample, carried in arrays, with one
message per value. `Metrics.finite` is the run's own outcome (it did not diverge); the other codes
come from the checks a sweep or the judge adds (the linearised loop, the two-step check).
"""

from __future__ import annotations

import enum

import numpy as np


class Status(enum.IntEnum):
    """A sample's status, most basic cause first: where several apply, the first is reported."""

    OK = 0
    DIVERGED = 1
    UNSTABLE_LOOP = 2
    STEP_BEYOND_LIMIT = 3
    STEP_ARTEFACT = 4

    @property
    def label(self) -> str:
        """The name in tables and files: `ok`, `diverged`, ..."""
        return self.name.lower()

    @property
    def message(self) -> str:
        return MESSAGES[self]

    @property
    def measured(self) -> bool:
        """The run reached its horizon within the step's stability limit, so its values stand for
        the run (a step artefact's are shown too, and flagged)."""
        return self in (Status.OK, Status.STEP_ARTEFACT)


MESSAGES = {
    Status.OK: "trusted: the run ended, the loop is stable, the step is within its limit (and passed the two-step "
    "check, where it ran)",
    Status.DIVERGED: "the run left the finite states or passed the force bound (see t_diverged)",
    Status.UNSTABLE_LOOP: "the linearised closed loop has a growing mode: no step size can make it settle",
    Status.STEP_BEYOND_LIMIT: "dt is beyond the largest stable step of the linearised loop (see dt_limit)",
    Status.STEP_ARTEFACT: "the answer moved by more than the accuracy tolerances between dt and dt/2 (see step_error)",
}
LABELS = tuple(s.label for s in Status)


def labels(codes) -> np.ndarray:
    """Status codes (any integer array) as their labels."""
    return np.asarray(LABELS)[np.asarray(codes, int)]
