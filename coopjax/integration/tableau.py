"""Classical RK4 as data: its stage nodes, its weights and its continuous extension.

`plain_rk4`, `filippov` and the benchmark's numba peer read these numbers, so the three cannot
disagree on the method.
"""

from __future__ import annotations

from typing import NamedTuple


class Tableau(NamedTuple):
    """An explicit Runge-Kutta method whose Butcher matrix is all on its subdiagonal (as RK4's is).

    Stage j is evaluated at t + a[j] h and y + a[j] h k[j-1]; the step is
    y + h / denominator * sum_j b[j] k[j]. Its continuous extension at a share theta of the step is
    y + h sum_j b_j(theta) k[j], with b_j(theta) = sum_p dense[j][p] theta^(p + 1).
    """

    a: tuple[float, ...]
    b: tuple[float, ...]
    denominator: float
    dense: tuple[tuple[float, ...], ...]

    def dense_groups(self) -> tuple[tuple[tuple[float, ...], tuple[int, ...]], ...]:
        """The stages grouped by their dense-output polynomial, in order: (coefficients, stages).
        Stages that share b_j(theta) (RK4's second and third) are summed before they are weighted,
        one multiplication fewer per row."""
        groups: dict = {}
        for j, row in enumerate(self.dense):
            groups.setdefault(row, []).append(j)
        return tuple((row, tuple(stages)) for row, stages in groups.items())

    @staticmethod
    def polynomial(coefficients, theta):
        """sum_p coefficients[p] theta^(p + 1), zero terms left out."""
        return sum(c * theta ** (p + 1) for p, c in enumerate(coefficients) if c != 0.0)


# The dense output is the cubic Hermite-type extension of classical RK4 (third order); at theta = 1
# it gives the step's own weights, 1/6, 1/3, 1/3, 1/6.
RK4 = Tableau(
    a=(0.0, 0.5, 0.5, 1.0),
    b=(1.0, 2.0, 2.0, 1.0),
    denominator=6.0,
    dense=((1.0, -1.5, 2.0 / 3.0), (0.0, 1.0, -2.0 / 3.0), (0.0, 1.0, -2.0 / 3.0), (0.0, -0.5, 2.0 / 3.0)),
)
