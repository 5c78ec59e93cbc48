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



def test_deposit_drops_what_falls_before_the_first_node():
    """An event within half a node of time 0 puts its first spline weight before the first node: that share is dropped,
    as the share past the last node is, never wrapped on to the last node (JAX reads a negative index from the end)."""
    from tofjax.model.components import Nodes, deposit

    h, K = 1e-11, 16
    t = (jnp.arange(K) + 0.5) * h
    nodes = Nodes(t=t, h=jnp.asarray(h), r=t, dr=jnp.asarray(h), c1=jnp.asarray(1.0))
    m = np.asarray(deposit(jnp.full((1, 1, 1), 0.2 * h), jnp.ones((1, 1, 1)), nodes))[0, 0]
    # u = -0.3: weights 0.32 (node -1, dropped), 0.66 (node 0), 0.02 (node 1)
    np.testing.assert_allclose(m[:2], [0.66, 0.02], rtol=1e-12)
    assert m[2:].sum() == 0.0
    late = np.asarray(deposit(jnp.full((1, 1, 1), (K - 0.2) * h), jnp.ones((1, 1, 1)), nodes))[0, 0]
    np.testing.assert_allclose(late[-2:], [0.02, 0.66], rtol=1e-12)
    assert late[:-2].sum() == 0.0

@given(
    sigma=st.floats(5e-12, 500e-12),
    ratio=st.floats(0.05, 20.0),
    u=st.floats(-4.0, 12.0),
)
def test_written_derivatives_match_finite_differences(sigma, ratio, u):
    """The CDF's and density's derivatives in x, sigma and tau (written down, not traced through
    erfcx) against central differences, first and second order, across the w > 0 / w <= 0 split.
    (Beyond tau/sigma in 0.05-20 the higher derivatives grow like (sigma/tau)^k and central
    differences, not the rule, lose the digits; test_no_nan_at_extremes covers the extremes.)"""
    tau = ratio * sigma
    x = u * (sigma + tau)
    scale = jnp.asarray([sigma + tau, sigma, tau])
    v0 = jnp.asarray([x, sigma, tau]) / scale
    jac = np.asarray(_scaled_jac(v0, scale))
    hess = np.asarray(_scaled_hess(v0, scale))
    eps = 1e-5
    for k in range(3):
        e = np.zeros(3)
        e[k] = eps
        fd = (np.asarray(_scaled_f(v0 + e, scale)) - np.asarray(_scaled_f(v0 - e, scale))) / (2 * eps)
        np.testing.assert_allclose(jac[:, k], fd, atol=2e-7, rtol=1e-5)
        fd2 = (np.asarray(_scaled_jac(v0 + e, scale)) - np.asarray(_scaled_jac(v0 - e, scale))) / (2 * eps)
        np.testing.assert_allclose(hess[:, :, k], fd2, atol=2e-6, rtol=1e-4)


def _scaled(v, scale):
    """CDF and density (times sigma + tau) at ``v * scale`` = (x, sigma, tau): derivatives in units of the scales."""
    y = v * scale
    return jnp.stack([emg_cdf(y[0], y[1], y[2]), emg_pdf(y[0], y[1], y[2]) * (scale[1] + scale[2])])


# compiled once for every example (eagerly, each example dispatched thousands of small operations)
_scaled_f = jax.jit(_scaled)
_scaled_jac = jax.jit(jax.jacfwd(_scaled))
_scaled_hess = jax.jit(jax.jacfwd(jax.jacfwd(_scaled)))


def test_written_derivatives_equal_traced_ones():
    """Agreement between methods: the written rule against JAX's own derivative of the same closed
    form traced through erfc (``Phi(x/s) - exp(s^2/2t^2 - x/t) Phi(x/s - s/t)``, safe where
    its exponent stays small)."""
    from jax.scipy.special import erfc

    def traced(x, s, t):
        phi = 0.5 * erfc(-x / (s * np.sqrt(2)))
        return phi - jnp.exp(0.5 * (s / t) ** 2 - x / t) * 0.5 * erfc((s / t - x / s) / np.sqrt(2))

    x = jnp.linspace(-2.0, 8.0, 41)
    for s, t in ((0.7, 1.3), (1.0, 0.8), (0.5, 3.0)):
        for arg in range(3):
            ours = jax.vmap(jax.grad(lambda *a: emg_cdf(*a), argnums=arg), (0, None, None))(x, s, t)
            ref = jax.vmap(jax.grad(traced, argnums=arg), (0, None, None))(x, s, t)
            np.testing.assert_allclose(ours, ref, atol=1e-12, rtol=1e-10)
