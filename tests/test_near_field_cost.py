"""The near field's shape correction on a node grid (components.node_shape_correction: a binomial
series far from and very near the sensor, Gauss-Legendre on a window of nodes between) against an
adaptive reference (scipy.integrate.quad of G_p - G_2, r (G_p - G_2), r^2 (G_p - G_2) on each node),
relative to the node's whole integral of G_p r^j; both dtypes, the window and its fallback."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import quad

from tofjax.model import components as C

DR = 5.35e-3  # a node's range, m (the OptoSkin scene: 100 ps bins, 2 nodes per bin)
_node = jax.jit(C.node_shape_correction)


def _edges(K=48, first=-0.0391):
    """Node edges after emission as node_falloff_after_emission makes them (the smooth max)."""
    r = (np.arange(K) + 0.5) * DR + first
    eps = 0.02 * DR

    def after(x):
        sq = np.sqrt(x * x + eps * eps)
        return np.where(x > 0, 0.5 * (x + sq), 0.5 * eps * eps / np.where(x > 0, 1.0, sq - x))

    return after(r - DR / 2), after(r + DR / 2)


def _g(r, d, p):  # G_p without overflow (p up to 1000)
    m = max(r, d)
    return np.exp(-(2.0 / p) * np.log1p((min(r, d) / m) ** p)) / m**2


def _worst(lo, hi, d, p, got, nodes):
    """Largest |got - reference| / int G_p r^j over the nodes and j = 0, 1, 2."""
    worst = 0.0
    for i in nodes:
        pts = [d] if lo[i] < d < hi[i] else None
        for j in range(3):
            ref = quad(lambda r: (_g(r, d, p) - 1.0 / (r * r + d * d)) * r**j, lo[i], hi[i], points=pts, epsabs=0, epsrel=1e-13, limit=200)[0]
            tot = quad(lambda r: _g(r, d, p) * r**j, lo[i], hi[i], points=pts, epsabs=0, epsrel=1e-13, limit=200)[0]
            worst = max(worst, abs(float(got[j][i]) - ref) / tot)
    return worst


def _args(lo, hi, d, p, dtype=jnp.float64):
    return tuple(jnp.asarray(x, dtype) for x in (lo, hi, d, p))


@pytest.mark.filterwarnings("ignore::scipy.integrate.IntegrationWarning")
def test_node_correction_matches_adaptive_quadrature():
    """float64, near field 5 mm (the window): <= 5e-12 of the node's integral for p <= 8, 1e-10 at
    p = 65 (the fit's bound; 6e-8 at p = 1000, the Params' bound); p = 2 zero to rounding (exactly 0
    where XLA optimises the program fully, 6e-19 m of a node's r^2 moment at the tests' optimisation
    level, tests/conftest.py), on every node. Nodes before emission, the emission node, the band (d/4 to
    4 d) and far away."""
    lo, hi = _edges()
    nodes = [6, 8, 9, 10, 12, 47]
    for p, tol in ((1.0, 1e-10), (8.0, 1e-10), (65.0, 1e-9)):
        assert _worst(lo, hi, 0.005, p, _node(*_args(lo, hi, 0.005, p)), nodes) < tol, p
    assert _worst(lo, hi, 0.005, 2.0, _node(*_args(lo, hi, 0.005, 2.0)), range(len(lo))) < 1e-15


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::scipy.integrate.IntegrationWarning")
@pytest.mark.parametrize("dtype, tol", [(jnp.float64, 1e-10), (jnp.float32, 1e-5)])
def test_node_correction_both_dtypes_and_the_fallback(dtype, tol):
    """float64 as above; float32: <= 4e-6. Near field 5 mm (the window) and 30 mm (deeper than the
    window holds: the fallback), nodes from before emission to 43 d."""
    lo, hi = _edges()
    nodes = [*range(5, 20), 30, 47]
    for d in (0.005, 0.03):
        for p, t in ((1.0, tol), (1.37, tol), (8.0, tol), (65.0, 30 * tol)):
            assert _worst(lo, hi, d, p, _node(*_args(lo, hi, d, p, dtype)), nodes) < t, (d, p)


@pytest.mark.slow
def test_window_agrees_with_all_edges():
    lo, hi = _edges()
    full = jax.jit(C.shape_correction)
    for d in (0.001, 0.005, 0.012):
        win, ref = _node(*_args(lo, hi, d, 3.0)), full(*_args(lo, hi, d, 3.0))
        for w, f in zip(win, ref):
            np.testing.assert_allclose(np.asarray(w), np.asarray(f), rtol=1e-9, atol=1e-12 * float(jnp.abs(f).max()))
