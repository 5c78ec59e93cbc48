"""The near field's shape family G = (r^p + d^p)^(-2/p) (Params.near_field_shape): today's law at
p = 2, the node integrals against fine quadrature, finite gradients at the extremes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tofjax.model import components as C

D = 0.003  # near field, m
_correction = jax.jit(C.shape_correction)


def _fine(f, lo, hi, n=20001):
    """int f over [lo, hi] by the trapezoid rule on a fine grid, split at D (the bend)."""
    out = 0.0
    cuts = [lo] + ([D] if lo < D < hi else []) + [hi]
    for a, b in zip(cuts[:-1], cuts[1:]):
        r = np.linspace(a, b, n)
        out += np.trapezoid(f(r), r)
    return out


def test_family_contains_todays_law_and_its_limits():
    r = jnp.linspace(0.0, 0.2, 2001)
    g2 = C.falloff(r, D, 2.0)
    np.testing.assert_allclose(np.asarray(g2), 1.0 / (np.asarray(r) ** 2 + D**2), rtol=1e-14)
    np.testing.assert_allclose(np.asarray(C.falloff(r, D, 1.0)), 1.0 / (np.asarray(r) + D) ** 2, rtol=1e-13)
    big = np.asarray(C.falloff(r, D, 400.0))
    np.testing.assert_allclose(big, 1.0 / np.maximum(np.asarray(r), D) ** 2, rtol=4e-3)  # 2^(-2/400) at r = D
    # far from the sensor every shape is 1/r^2
    for p in (1.0, 2.0, 65.0):
        assert float(C.falloff(0.2, D, p)) * 0.2**2 == pytest.approx(1.0, abs=0.04)


def test_p2_adds_nothing_to_the_closed_forms():
    lo = jnp.asarray([0.0, 0.001, 0.004, 0.05])
    hi = lo + 0.005
    mass = (np.arctan(np.asarray(hi) / D) - np.arctan(np.asarray(lo) / D)) / D
    dm, df1, df2 = (np.asarray(x) for x in _correction(lo, hi, D, 2.0))
    assert np.abs(dm / mass).max() < 1e-15 and np.abs(df1 / (mass * hi)).max() < 1e-15
    assert np.abs(df2 / (mass * hi**2)).max() < 1e-15



@pytest.mark.parametrize("p", [1.0, 4.0, 65.0])
def test_node_integrals_match_fine_quadrature(p):
    """Mass, first and second moment of G over node ranges (closed form at p = 2 plus the
    Gauss-Legendre correction) against the trapezoid rule on 2e4 points per piece: within
    1e-4 (the sharpest bend, p = 65 on a node ending at r = d: 2e-5)."""
    edges = np.array([0.0, 0.0012, D, 0.0055, 0.008, 0.02, 0.1])
    lo, hi = jnp.asarray(edges[:-1]), jnp.asarray(edges[1:])
    dm, df1, df2 = (np.asarray(x) for x in _correction(lo, hi, D, p))

    def g(r):  # G in NumPy, written as the physics states it
        return (r**p + D**p) ** (-2.0 / p)

    for i, (a, b) in enumerate(zip(edges[:-1], edges[1:])):
        mass = np.arctan(b / D) / D - np.arctan(a / D) / D + dm[i]
        first = 0.5 * (np.log1p((b / D) ** 2) - np.log1p((a / D) ** 2)) + df1[i]
        second = (b - a) - D * D * (np.arctan(b / D) - np.arctan(a / D)) / D + df2[i]
        ref = [_fine(lambda r: g(r) * r**k, a, b) for k in (0, 1, 2)]
        for got, want in zip((mass, first, second), ref):
            assert got == pytest.approx(want, rel=1e-4), (i, got, want)


def test_gradients_finite_at_the_extremes():
    """In p and d, at r = 0, r = d and far away, p from 1 to 1000; and the node masses' too."""
    ps, rs = (jnp.asarray(x).ravel() for x in np.meshgrid([1.0, 2.0, 65.0, 1000.0], [0.0, D, 0.3]))
    grad = jax.jit(jax.vmap(jax.grad(lambda p, d, r: C.falloff(r, d, p), argnums=(0, 1, 2)), (0, None, 0)))
    assert all(np.isfinite(np.asarray(x)).all() for x in grad(ps, D, rs))
    nodes = C.Nodes(t=None, h=None, r=jnp.arange(-3, 40) * 0.005 + 0.0013, dr=jnp.asarray(0.005), c1=None)

    def total(q):
        mass, spread = C.node_falloff_after_emission(nodes, q[1], q[0])
        return jnp.sum(mass) + jnp.sum(spread.offset) + jnp.sum(spread.variance)

    g = jax.jit(jax.vmap(jax.grad(total)))(jnp.asarray([[1.0, D], [2.0, D], [65.0, D], [1000.0, D]]))
    assert np.isfinite(np.asarray(g)).all()


def test_config_and_params_know_the_shape(optoskin):
    from tofjax.config import ConfigError
    from tofjax.fit import FitConfig
    from tofjax.fit.transforms import default_transforms
    from tofjax.model import Params
    from tofjax.model.params import ParamsError

    assert "near_field_shape" in FitConfig().free
    assert "near_field_shape" not in FitConfig(optics="guided").free  # the guided optics have no shape
    with pytest.raises(ConfigError, match="near_field_shape"):
        FitConfig(optics="guided", free=("n1", "near_field_shape"))
    p = Params.from_scene(optoskin)
    assert float(p.near_field_shape) == 2.0
    with pytest.raises(ParamsError, match="near_field_shape"):
        p.replace(near_field_shape=0.5)
    t = default_transforms(optoskin)["near_field_shape"]
    for v in (1.5, 2.0, 45.0):
        assert float(t.to_physical(t.to_unconstrained(v))) == pytest.approx(v, rel=1e-9)


class _Disagreeing:
    """``jnp`` as ``components`` sees it, except that the ``where`` calls made from function ``fn``
    whose order (0, 1, ...) is in ``flip`` see their condition negated (at elements ``at``, all if
    None): what XLA does when it
    evaluates one comparison in two fusions with different rounding of a value on its threshold
    (it did so in ``node_falloff_after_emission``: test_model.py,
    test_continuous_where_the_emission_sits_on_a_node_edge). A knife-edge-safe double where gives
    the value beside the threshold whichever calls disagree."""

    def __init__(self, fn, flip, at=None):
        self.fn, self.flip, self.at, self.calls = fn, set(flip), at, 0

    def __getattr__(self, name):
        return getattr(jnp, name)

    def where(self, cond, a, b):
        import sys

        if sys._getframe(1).f_code.co_name == self.fn:
            if self.calls in self.flip:
                cond = jnp.asarray(cond)
                cond = ~cond if self.at is None else cond.at[self.at].set(~cond[self.at])
            self.calls += 1
        return jnp.where(cond, a, b)


@pytest.mark.parametrize("case", ["falloff", "pow_small", "exprel", "shape_points"])
def test_double_wheres_hold_when_their_conditions_disagree(case, monkeypatch):
    """At each helper's threshold (r = d; s within rounding of 0; |a| = 1e-3; a node edge at d),
    any subset of its threshold wheres negated gives the value beside the threshold (within 1e-12
    relative), not the placeholder's (s = d / 1, 1^p, expm1(1) / 1)."""
    r = jnp.asarray([D])
    calls = {
        # fn whose wheres are flipped, the call, its wheres on the threshold (by order), the
        # elements on it (None: all), the value
        "falloff": ("falloff", lambda: C.falloff(r, D, 3.0), (0, 1), None, 2.0 ** (-2.0 / 3.0) / D**2),
        "pow_small": ("_pow_small", lambda: C._pow_small(jnp.asarray([1e-300]), 2.0), (0, 1), None, 0.0),
        "exprel": ("_exprel", lambda: C._exprel(jnp.asarray([1e-3, -1e-3])), (0, 1), None,
                   np.expm1([1e-3, -1e-3]) / np.asarray([1e-3, -1e-3])),
        # edges (lo, hi) = (1 mm, d): the edge at d (element 1) has s = e / d (inner) or d / e, 1 either
        # way; the wheres of ``pos`` (calls 2, 3) are not on a threshold
        "shape_points": ("_shape_points", lambda: C.shape_correction(jnp.asarray([0.001]), r, D, 3.0), (0, 1), 1, None),
    }
    fn, call, wheres, at, want = calls[case]
    if want is None:
        want = np.concatenate([np.asarray(x) for x in call()])
    for k in range(1, 2 ** len(wheres)):
        flip = [w for i, w in enumerate(wheres) if k >> i & 1]
        shim = _Disagreeing(fn, flip, at)
        monkeypatch.setattr(C, "jnp", shim)
        got = call()
        monkeypatch.setattr(C, "jnp", jnp)
        assert shim.calls >= len(wheres)
        got = np.concatenate([np.asarray(x).ravel() for x in (got if isinstance(got, (list, tuple)) else [got])])
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-300, err_msg=f"{case}: wheres {flip} negated")


def test_node_terms_derivative_as_a_matrix_product_equals_the_direct_one(optoskin):
    """``linear_masses(..., node_jvp=True)`` (the calibration's forward-mode Jacobian) gives the
    distributed terms' (K,) node densities a derivative ``J @ dx`` (so XLA does not recompute their
    tangents for every sensor and zone): the masses and their forward-mode, reverse-mode and
    second-order derivatives equal those of the direct computation to rounding, with the near
    field's shape free (p = 3)."""
    from tofjax.model import Params, build_model

    # every scalar parameter but the pulse's and the edge's (written out: a list the model forgot would pass)
    node_scalars = ("n1", "emission_time_s", "near_field_m", "near_field_shape", "mu_s_per_m", "mu_a_per_m",
                    "interface_backscatter_per_m", "volume_backscatter_fraction", "multiple_scattering")
    model = build_model(optoskin)
    p = Params.from_scene(optoskin, jnp.float64).replace(near_field_shape=jnp.asarray(3.0))
    x0 = jnp.stack([getattr(p, k) for k in node_scalars] + [p.end_reflectance])
    v = jnp.linspace(0.5, 1.5, x0.shape[0]) * jnp.abs(x0)

    def pieces(node_jvp):
        def masses(x):  # (at unit gain)
            q = p.replace(**{k: x[i] for i, k in enumerate(node_scalars)}, end_reflectance=x[-1])
            return model.linear_masses(q, node_jvp=node_jvp)[0]

        def all_four(x):  # one compiled program per variant (four cost four compiles of the OptoSkin model)
            return [masses(x), jax.jacfwd(masses)(x), jax.grad(lambda y: jnp.sum(masses(y) ** 2))(x),
                    jax.jvp(lambda y: jax.jvp(masses, (y,), (v,))[1], (x,), (v,))[1]]

        return jax.jit(all_four)(x0)

    got, want = pieces(True), pieces(False)
    # the same ops, fused apart (and, in one program with the derivatives, fused with them): to rounding of the
    # largest mass (the spline's far tails, 1e-18 against exact zeros, are not the same ops' rounding)
    np.testing.assert_allclose(np.asarray(got[0]), np.asarray(want[0]), rtol=1e-13, atol=1e-13 * float(np.max(np.abs(want[0]))))
    for i, (g, w) in enumerate(zip(got[1:], want[1:])):
        g, w = np.asarray(g), np.asarray(w)
        assert np.all(np.isfinite(g))
        # relative to each derivative's own scale: per column for the Jacobian (its columns span many decades)
        scale = np.max(np.abs(w), axis=tuple(range(w.ndim - 1)), keepdims=True) if i == 0 else np.max(np.abs(w))
        assert np.all(scale > 0)  # every scalar moves the masses
        assert np.max(np.abs(g - w) / scale) < 1e-9
