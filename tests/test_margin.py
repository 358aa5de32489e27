"""The grip margin min_swi: zero exactly where the grip is lost, above zero where it holds, and a
derivative that is the converged model's."""

import jax
import jax.numpy as jnp
import numpy as np

import coopjax as cj

# Table 1's gains hold the grip at the light masses and lose it at the heavy ones (the tuning problem).
MASSES = np.array([0.5, 1.0, 3.0, 5.0])


def metrics(K_GP, dt=2e-3):
    params = cj.make_params(M_b=jnp.asarray(MASSES), K_GP=K_GP * jnp.ones(len(MASSES)))
    return cj.simulate(params, "carry", dt=dt, check_dt=False).metrics


def test_the_margin_is_zero_exactly_where_the_grip_is_lost():
    m = metrics(0.8)
    holds = np.asarray(m.min_grip) >= 10.0 - 0.01  # F_lim, less the judge's tolerance
    assert holds.any() and (~holds).any(), "the masses must include both cases"
    swi = np.asarray(m.min_swi)
    assert np.all(swi[~holds] == 0.0)
    assert np.all((swi[holds] > 0.0) & (swi[holds] <= 1.0))
    # Where it holds, the least force over the grip window is F_lim (sliding there) ...
    np.testing.assert_allclose(np.asarray(m.min_grip)[holds], 10.0, atol=1e-5)
    # ... and a lighter body leaves more margin (less force is needed to carry it).
    assert np.all(np.diff(swi[holds]) < 0)


def test_its_derivative_is_the_slope_of_the_converged_model():
    # At a mass where the grip holds: AD at the training step against central secants of the model
    # at a four times finer step, with two widths that agree.
    k = 0.8
    _, ad = jax.jvp(lambda x: metrics(x).min_swi, (jnp.asarray(k),), (jnp.asarray(1.0),))
    fine = lambda x: np.asarray(metrics(x, dt=5e-4).min_swi)
    secants = [(fine(k + h) - fine(k - h)) / (2 * h) for h in (1e-2, 3e-3)]
    holds = np.asarray(metrics(k).min_grip) >= 10.0 - 0.01
    np.testing.assert_allclose(secants[0][holds], secants[1][holds], rtol=0.03)
    np.testing.assert_allclose(np.asarray(ad)[holds], secants[1][holds], rtol=0.05)
    assert np.all(np.abs(np.asarray(ad)[holds]) > 1e-3)  # not a flat constraint: there is a slope to follow
