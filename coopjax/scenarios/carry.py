"""Pick, carry, release, settle: the tuning scenario (4 s).

Each phase is a rest-to-rest bump, and they add up (s_L = +1, s_R = -1):
- grip [0, 1): each tip's reference goes A_g into the body;
- carry [1, 2): both move A_c in +x;
- release [2, 3): each tip backs away, A_g beyond where it first touched;
- settle [3, 4]: no command.
"""

from coopjax.params import Spec
from coopjax.scenarios.base import Clock, Scenario, bump, register


def command(params, clock: Clock):
    # Unit bumps (functions of t alone, so one value per step, not per sample) times the amplitudes.
    grip, carry, release = (bump(clock, t0, 1.0) for t0 in (0.0, 1.0, 2.0))
    return tuple(
        tuple(s * params.A_g * g + params.A_c * c - 2.0 * s * params.A_g * r for g, c, r in zip(grip, carry, release))
        for s in (1.0, -1.0)
    )


CARRY = register(
    Scenario(
        name="carry",
        T=4.0,
        command=command,
        # hold: squeeze, carry and release, not the settling after it (where the drifting body can come back).
        windows={"grip": (0.5, 2.0), "lag": (2.5, 4.0), "hold": (0.0, 3.0)},
        description="pick, carry 0.5 m, release, settle: the tuning scenario, T = 4 s",
        parameters={
            "A_g": Spec(0.1, "m/s", False, "finite", "carry scenario: grip amplitude"),
            "A_c": Spec(0.5, "m/s", False, "finite", "carry scenario: carry amplitude"),
        },
    )
)
