"""The default calibration solver (Marquardt-scaled Levenberg-Marquardt, optionally with geodesic
acceleration, tofjax.fit.solve): it finds the least-squares optimum, a vmapped batch of fits
equals the fits one by one, and failures are result codes. Toy problems: each test compiles in
well under a second."""

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from scipy.optimize import least_squares

from tofjax.fit.solve import MarquardtLM, solve_marquardt

T = np.linspace(0.0, 4.0, 60)
TRUE = np.array([2.0, 1.3, 0.4, 3.0])


def _model(p, t):
    # a sloppy model: two decays with a badly separated pair of rates, in log coordinates
    return jnp.exp(p[0]) * jnp.exp(-jnp.exp(p[1]) * t) + jnp.exp(p[2]) * jnp.exp(-jnp.exp(p[3]) * t)


def _data(seed):
    rng = np.random.default_rng(seed)
    clean = np.asarray(_model(jnp.log(jnp.asarray(TRUE)), jnp.asarray(T)))
    return clean + 0.01 * rng.standard_normal(T.size)


def residuals(p, data):
    return (_model(p, jnp.asarray(T)) - data) / 0.01


Y0 = jnp.log(jnp.asarray([1.5, 1.0, 0.6, 2.0]))


@pytest.mark.parametrize("geodesic", [False, True])
def test_marquardt_finds_the_least_squares_optimum(geodesic):
    data = jnp.asarray(_data(0))
    solver = MarquardtLM(rtol=1e-12, atol=1e-12, geodesic=geodesic)
    out = jax.jit(lambda y, d: solve_marquardt(residuals, solver, y, d, max_steps=200))(Y0, data)
    assert out.result == optx.RESULTS.successful
    ref = least_squares(lambda p: np.asarray(residuals(jnp.asarray(p), data)), np.asarray(Y0), xtol=1e-15, ftol=1e-15, gtol=1e-15)
    np.testing.assert_allclose(np.asarray(out.value), ref.x, rtol=0, atol=1e-7)
    h = np.asarray(out.history)
    steps = int(out.steps)
    assert np.all(np.isfinite(h[: steps + 1])) and np.all(np.isnan(h[steps + 1 :]))
    assert np.all(np.diff(h[: steps + 1]) <= 0)  # rejected steps repeat the loss, never raise it


def test_batched_fits_equal_separate_fits():
    solver = MarquardtLM()
    data = jnp.stack([jnp.asarray(_data(s)) for s in range(5)])

    def one(d):
        return solve_marquardt(residuals, solver, Y0, d, max_steps=100, loss_tol=1e-6)

    batch = jax.jit(jax.vmap(one))(data)
    single = jax.jit(one)
    for i in range(5):
        s = single(data[i])
        np.testing.assert_allclose(np.asarray(batch.value[i]), np.asarray(s.value), rtol=0, atol=1e-9)
        assert int(batch.steps[i]) == int(s.steps)
        assert int(jax.tree_util.tree_leaves(batch.result)[0][i]) == int(jax.tree_util.tree_leaves(s.result)[0])


def test_step_limit_and_non_finite_start_are_result_codes():
    data = jnp.asarray(_data(1))
    run = jax.jit(lambda y: solve_marquardt(residuals, MarquardtLM(rtol=1e-14, atol=1e-14), y, data, max_steps=2))
    out = run(Y0)
    assert out.result == optx.RESULTS.nonlinear_max_steps_reached and int(out.steps) == 2
    bad = run(Y0.at[0].set(jnp.nan))
    assert bad.result == optx.RESULTS.nonfinite and int(bad.steps) == 0
