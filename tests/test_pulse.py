"""The instrument response (EMG): closed forms, limits, exact bin integration, stability."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy import stats

from tofjax.model.pulse import apply_kernels, bin_kernels, emg_cdf, emg_pdf


@given(sigma=st.floats(10e-12, 500e-12), tau=st.floats(5e-12, 2e-9))
def test_cdf_matches_scipy_exponnorm(sigma, tau):
    x = np.linspace(-5 * sigma, 10 * tau + 5 * sigma, 201)
    ref = stats.exponnorm.cdf(x, tau / sigma, scale=sigma)
    np.testing.assert_allclose(np.asarray(emg_cdf(jnp.asarray(x), sigma, tau)), ref, atol=1e-9)
    np.testing.assert_allclose(
        np.asarray(emg_pdf(jnp.asarray(x), sigma, tau)) * sigma, stats.exponnorm.pdf(x, tau / sigma, scale=sigma) * sigma, atol=1e-8
    )


def test_limits_gaussian_and_exponential():
    x = jnp.linspace(-3e-10, 3e-10, 41)
    # tau -> 0: a Gaussian (the difference is tau phi(x / sigma) / sigma, here 4e-7)
    np.testing.assert_allclose(emg_cdf(x, 1e-10, 1e-16), stats.norm.cdf(np.asarray(x) / 1e-10), atol=1e-6)
    # sigma -> 0: a one-sided exponential
    np.testing.assert_allclose(emg_cdf(x, 1e-18, 1e-10), np.where(x > 0, 1 - np.exp(-np.asarray(x) / 1e-10), 0), atol=1e-6)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("sigma,tau", [(1e-15, 1e-15), (1e-15, 1e-8), (1e-8, 1e-15), (1e-8, 1e-8), (6e-11, 1.5e-10)])
def test_no_nan_at_extremes(dtype, sigma, tau):
    x = jnp.linspace(-2e-8, 2e-8, 801, dtype=dtype)

    def total(s, t):
        return jnp.sum(emg_cdf(x, s, t, floor=1e-13) ** 2) + jnp.sum(emg_pdf(x, s, t, floor=1e-13) * 1e-12)

    s, t = jnp.asarray(sigma, dtype), jnp.asarray(tau, dtype)
    v, g = jax.value_and_grad(total, argnums=(0, 1))(s, t)
    assert np.isfinite(v) and all(np.isfinite(gi) for gi in g)
    c = np.asarray(emg_cdf(x, s, t, floor=1e-13))
    assert (np.diff(c) >= -1e-6).all() and c.min() >= 0 and c.max() <= 1


@pytest.mark.parametrize("q,tol", [(1, 2e-2), (2, 2e-3), (4, 2e-4), (8, 2e-5)])
def test_point_event_binned_like_the_exact_pulse(q, tol):
    """An event deposited on nodes and passed through the bin kernels lands in each bin with the
    probability the exact pulse puts between the bin's edges; the error falls fast with q."""
    from tofjax.model.components import Nodes, deposit

    n_bins, width = 64, 1e-10
    h = width / q
    sigma, tau = 7e-11, 1.2e-10
    kernels = bin_kernels(h, n_bins, q, sigma, tau, jnp.float64)
    assert kernels.shape == (q, 2 * n_bins - 1)
    t = (jnp.arange(n_bins * q) + 0.5) * h
    nodes = Nodes(t=t, h=jnp.asarray(h), r=t, dr=jnp.asarray(h), c1=jnp.asarray(1.0))
    for t_event in (1.0137e-9, 2.5e-9, 3.0333e-9):
        masses = deposit(jnp.full((1, 1, 1), t_event), jnp.ones((1, 1, 1)), nodes)
        counts = np.asarray(apply_kernels(masses, kernels, n_bins, q))[0, 0]
        assert counts.sum() == pytest.approx(1.0, abs=1e-9)
        edges = np.arange(n_bins + 1) * width - t_event
        exact = np.diff(stats.exponnorm.cdf(edges, tau / sigma, scale=sigma))
        assert np.abs(counts - exact).max() < tol
