"""The paper's Fig. 6: equal and opposite squeezing velocities, never stopping (Table 1 gains, 3 s)."""

from coopjax.params import Spec
from coopjax.scenarios.base import Clock, Scenario, profile, register


def command(params, clock: Clock):
    """v_cmd,L = V(t; 0, A_1) and v_cmd,R = V(t; 0, A_2) for all t >= 0."""
    unit = profile(clock, 0.0, 1.0)  # V is linear in A: one profile for both robots
    return tuple(tuple(A * x for x in unit) for A in (params.A_1, params.A_2))


PAPER = register(
    Scenario(
        name="paper",
        T=3.0,
        command=command,
        # The paper's claim is about the grip once established: its window counts each robot from the
        # moment its force first reaches F_lim.
        # No lag window: its references run away from the squeezed body, so a tracking lag means nothing.
        windows={"grip": (0.0, 3.0), "hold": (0.0, 3.0)},
        after_reach=True,
        description="the paper's Fig. 6: +-10 m/s squeeze commands, Table 1 gains, T = 3 s",
        parameters={
            "A_1": Spec(10.0, "m/s", False, "finite", "paper scenario: left command amplitude"),
            "A_2": Spec(-10.0, "m/s", False, "finite", "paper scenario: right command amplitude"),
        },
    )
)
