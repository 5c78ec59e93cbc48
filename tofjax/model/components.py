"""The physics of Eq. 2-5 (seed 000), one function per component.

``P_r(t) = Q_int + Q_vol + Q_touch + N_ms + N_a``, each backscatter term
``Q_i = K G(r) beta_i T(r)`` written in terms of the one-way range
``r = c1 (t - t_e) / 2`` inside the waveguide (``c1 = c / n1``, ``t_e`` the
emission time):

* ``G(r) = 1 / (r^2 + r0^2)``: the slab spreads light in two dimensions, so
  intensity falls as ``1/r`` each way, ``1/r^2`` round trip (Eq. 4). ``r0``
  (the near field, default the slab thickness) keeps it finite where the slab
  is not thin compared with the range.
* ``T(r) = exp(-2 mu_t r)``, ``mu_t = mu_s + mu_a`` (Eq. 5).

Each function returns *masses at time nodes* (counts deposited at node times,
before the pulse is applied), shape ``(S, Z, K)``; the forward model then
applies the instrument response and integrates over bins in one matrix
product. Distributed terms (interface, volume, multiple scattering) integrate
G over each node's range in closed form and sample the slowly varying rest at
the node; point-like terms (crosstalk, the far edge,
contacts) are deposited on the three nearest nodes with weights that conserve
their mass and mean time. See ``docs/physics.md`` for the derivations.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .geometry import Geometry
from .params import SPEED_OF_LIGHT_M_PER_S, Params

__all__ = ["SPEED_OF_LIGHT_M_PER_S", "Nodes", "NodeSpread", "make_nodes", "falloff", "transmittance", "edge_incidence_cos", "edge_law"]


class Nodes(NamedTuple):
    """The time grid shared by every component (``q`` nodes per bin)."""

    t: jax.Array  # (K,) node times, s
    h: jax.Array  # node spacing, s
    r: jax.Array  # (K,) one-way range at each node, m (negative before emission)
    dr: jax.Array  # range per node, m
    c1: jax.Array  # speed of light in the waveguide, m/s


def make_nodes(params: Params, bin_width_s: float, n_bins: int, q: int) -> Nodes:
    dtype = params.n1.dtype
    h = jnp.asarray(bin_width_s / q, dtype)
    t = (jnp.arange(n_bins * q, dtype=dtype) + 0.5) * h
    c1 = params.c1
    return Nodes(t=t, h=h, r=0.5 * c1 * (t - params.emission_time_s), dr=0.5 * c1 * h, c1=c1)


#: The near field's shape correction (:func:`shape_correction`): a binomial series where
#: ``s = min(r, d) / max(r, d) <= SHAPE_SERIES_SPLIT`` (``r <= d/4`` or ``r >= 4 d``), with
#: SHAPE_SERIES_TERMS terms (the worst case, p = 1, converges as ``k 4^-k``); between,
#: Gauss-Legendre with SHAPE_POINTS points; on a node grid (:func:`node_shape_correction`) the
#: quadrature only on a window of SHAPE_WINDOW edges
SHAPE_SERIES_SPLIT = 0.25
SHAPE_SERIES_TERMS = {"float64": 24, "float32": 13}
SHAPE_POINTS = 20
SHAPE_WINDOW = 16


def _pow_small(s, p):
    """``s^p`` for ``0 <= s <= 1``, with finite gradients at ``s = 0`` (where it is 0)."""
    pos = s > 0
    # the branch not taken reads the smallest normal number, not 1: if XLA evaluates the two
    # ``s > 0`` apart with different rounding of ``s`` (as it did in node_falloff_after_emission),
    # a disagreeing pair still gives ~0, the value beside the threshold (1 would give s^p = 1)
    tiny = jnp.finfo(jnp.result_type(s, float)).tiny
    return jnp.where(pos, jnp.exp(p * jnp.log(jnp.where(pos, s, tiny))), 0.0)


def falloff(r, near_field, shape=2.0):
    """Geometric factor G (Eq. 4) with the near field regularised: finite at r = 0.

    ``G = (r^p + d^p)^(-2/p)``, ``d = near_field``, ``p = shape`` (``Params.near_field_shape``):
    ``1 / (r^2 + d^2)`` at ``p = 2`` (seed 000's law), ``1 / max(r, d)^2`` as ``p`` grows,
    ``1 / (r + d)^2`` at ``p = 1``; ``1/r^2`` far from the sensor for every ``p``. Written as
    ``m^-2 (1 + s^p)^(-2/p)`` with ``m = max(r, d)``, ``s = min(r, d) / m``: no overflow for any
    ``p``, gradients finite everywhere (``r = 0`` included)."""
    r = jnp.abs(r)
    far = r >= near_field
    m = jnp.where(far, r, near_field)
    # the branch not taken divides by m (= d there), not by 1: should XLA evaluate the ``r >= d``
    # of the two wheres apart with different rounding at r = d, a disagreeing pair gives s = 1,
    # the value at the threshold, not d / 1
    s = jnp.where(far, near_field / m, r / near_field)
    return jnp.exp(-(2.0 / shape) * jnp.log1p(_pow_small(s, shape))) / m**2


def _exprel(a):
    """``expm1(a) / a``, 1 at ``a = 0`` (a double-where keeps the gradient finite)."""
    small = jnp.abs(a) < 1e-3
    # the placeholder sits at the threshold with a's sign: should XLA evaluate the two ``small``
    # apart with different rounding, the branch not taken gives the value beside it, not expm1(1)
    safe = jnp.where(small, jnp.copysign(jnp.asarray(1e-3, a.dtype), a), a)
    return jnp.where(small, 1.0 + a * (0.5 + a * (1.0 / 6.0 + a / 24.0)), jnp.expm1(safe) / safe)


def _shape_series(s, ls, inner, shape):
    """The antiderivatives of :func:`shape_correction` (in units of ``d``: multiply by ``1/d``, 1,
    ``d``) at ``s <= 1/4`` (``ls = ln s``), from the binomial series ``phi_p(s) = (1 + s^p)^(-2/p)
    = sum_k c_k s^(kp)`` integrated term by term, minus the same at ``p = 2`` (so ``p = 2`` gives
    exactly 0). ``r <= d`` (``r = d s``, ``inner``): ``int_0^r G r^j dr = d^(j-1) int_0^s s^j phi ds``;
    ``r >= d`` (``r = d / s``): ``-int_r^inf G r^j dr = -d^(j-1) int_0^s phi / s^j ds`` (j = 2: the
    integral diverges; its terms' antiderivatives instead, ``s^(kp-1) / (kp-1)``, the ``k = 1``
    one written ``ln s exprel((p-1) ln s)``: a log at ``p = 1``)."""
    n = SHAPE_SERIES_TERMS[jnp.dtype(s.dtype).name]
    pos = s > 0
    q = jnp.stack([jnp.asarray(shape, s.dtype), jnp.asarray(2.0, s.dtype)])  # p, and 2 (the same ops)
    qb = q.reshape((2,) + (1,) * s.ndim)
    # c_k = binom(-2/q, k) = (-1)^k prod_{j<k} (2/q + j) / (j + 1), k = 1..n, over (kq + a), all
    # vectorised; the powers x^k as exp(k q ln s) and one contraction (timed: value and gradient
    # 6x faster than products of powers of x summed elementwise; Horner's unrolled chain or a
    # cumprod compile slowly, their gradients more so)
    k = jnp.arange(1, n + 1, dtype=s.dtype)
    a = 2.0 / q[:, None]
    # |c_k| = prod_{j<k} (a + j) / (j + 1): a running sum of logs, as a product with a triangular
    # matrix, summed elementwise (a cumsum lowers to a scan that compiles slowly, lgamma to a long
    # expansion, a matrix product to a library call: all slower to compile than a fused reduction)
    tri = jnp.asarray(np.tril(np.ones((n, n))), s.dtype)
    c = jnp.where(k % 2 == 1, -1.0, 1.0) * jnp.exp(jnp.sum(jnp.log((a + k - 1.0) / k)[:, None, :] * tri, -1))
    kq = k * q[:, None]
    den = jnp.stack([kq + 1.0, kq + 2.0, kq, kq + 3.0, jnp.where(k > 1, kq - 1.0, 1.0)], -1)
    coef = jnp.where((k > 1)[:, None] | (jnp.arange(5) < 4), c[..., None] / den, 0.0)  # (2, n, 5)
    powers = jnp.where(pos[..., None], jnp.exp((qb * ls)[..., None] * k), 0.0)  # x^k = exp(k q ln s), (2, ..., n)
    t = jnp.einsum("q...n,qnc->q...c", powers, coef)  # (2, ..., 5)
    t = [t[..., i] for i in range(5)]
    c1 = -2.0 / qb  # binom(-2/q, 1)
    m = s * t[0]  # both sides
    f_in, f_out = s * s * t[1], t[2]
    s2_in = s * s * s * t[3]
    s2_out = c1 * ls * _exprel((qb - 1.0) * ls) + t[4] / jnp.where(pos, s, 1.0)
    out = (jnp.where(inner, m, -m), jnp.where(inner, f_in, -f_out), jnp.where(inner, s2_in, -s2_out))
    return [o[0] - o[1] for o in out]


def _shape_band(s, inner, shape):
    """What :func:`_shape_series` misses for ``1/4 <= s <= 1``: ``+-int_{1/4}^s (phi_p - phi_2)
    (s^j or s^-j) ds`` (``+`` for ``r <= d``), by Gauss-Legendre, :data:`SHAPE_POINTS` points graded
    towards ``s`` (where, at ``s`` near 1 and large ``p``, ``phi_p`` bends within ~1/p). The
    integrand is analytic on the interval (``s^p``'s branch point at 0 lies beyond it)."""
    x, w = np.polynomial.legendre.leggauss(SHAPE_POINTS)
    v = jnp.asarray(0.5 * (x + 1.0), s.dtype)
    w = jnp.asarray(w, s.dtype)
    a = SHAPE_SERIES_SPLIT
    top = jnp.maximum(s, a)
    width = (top - a)[..., None]
    t = top[..., None] - width * v * v  # (..., points) in [a, max(s, a)]: never near 0
    lt = jnp.log(t)
    y = jnp.exp(2.0 * lt)  # t^2, written as t^p is (at p = 2 the two cancel exactly)
    g = jnp.expm1(jnp.log1p(y) - (2.0 / shape) * jnp.log1p(jnp.exp(shape * lt))) / (1.0 + y)  # phi_p - phi_2
    g = g * (w * v) * width  # ds = 2 width v dv, dv = dx / 2
    it = 1.0 / t
    up = jnp.where(inner[..., None], t, it)
    sign = jnp.where(inner, 1.0, -1.0)
    return [sign * jnp.sum(g, -1), sign * jnp.sum(g * up, -1), sign * jnp.sum(g * up * up, -1)]


def _shape_points(e, near_field, shape, band=True):
    """The antiderivatives ``A_j(e)`` (j = 0, 1, 2) of ``(G_p - G_2) r^j`` at edges ``e >= 0``
    (1-D), in units of ``d^(j-1)``: ``int_0^e`` for ``e <= d``, ``-int_e^inf`` beyond (up to a
    constant, j = 2); the series plus (``band``) the band's quadrature; then the same at ``r = d``
    on either side, two more values (one call of each: compiled once). Returns ``(A (3 x (E,)),
    inner (E,), at_d (3 x (2,)))``."""
    d = near_field
    inner = jnp.concatenate([e <= d, jnp.asarray([True, False])])
    # the branch not taken divides by d, not 1 (see falloff): s = 1 should the two ``e <= d`` disagree
    s = jnp.concatenate([jnp.where(e <= d, e / d, d / jnp.where(e <= d, d, e)), jnp.ones((2,), e.dtype)])
    pos = s > 0
    sc = jnp.minimum(s, SHAPE_SERIES_SPLIT)
    out = _shape_series(jnp.where(pos, sc, 0.0), jnp.log(jnp.where(pos, sc, 1.0)), inner, shape)
    if band is True:
        out = [o + b for o, b in zip(out, _shape_band(s, inner, shape))]
    elif band is not False:  # (start, width, valid): the band on ``width`` points from ``start``
        start, width, valid = band  # (and at d) if ``valid``, else on all (only the band in the cond)

        def window(s, inner):
            idx = jnp.concatenate([start + jnp.arange(width), jnp.asarray([-2, -1]) + s.shape[0]])
            return [jnp.zeros_like(s).at[idx].add(x) for x in _shape_band(s[idx], inner[idx], shape)]

        b = jax.lax.cond(valid, window, lambda s, inner: _shape_band(s, inner, shape), s, inner)
        out = [o + x for o, x in zip(out, b)]
    return [o[:-2] for o in out], inner[:-2], [o[-2:] for o in out]


def _shape_nodes(a_lo, in_lo, a_hi, in_hi, at_d, near_field):
    """Node integrals from the edges' antiderivatives; a node across ``r = d`` adds the two sides'
    values at ``d``."""
    d = near_field
    across = in_lo & ~in_hi
    out = [jnp.where(across, hi - x[1] + x[0] - lo, hi - lo) for lo, hi, x in zip(a_lo, a_hi, at_d)]
    return out[0] / d, out[1], out[2] * d


def shape_correction(lo, hi, near_field, shape):
    """What the shape ``p`` adds to ``int G``, ``int r G`` and ``int r^2 G`` over ``[lo, hi]``
    (``0 <= lo <= hi``) relative to the closed forms at ``p = 2``: ``(dM, dF1, dF2)``, each 0 at
    ``p = 2``. In ``s = min(r, d) / max(r, d)`` (``G dr = phi_p(s) ds / d`` on either side of
    ``r = d``, ``phi_p = (1 + s^p)^(-2/p)``, bounded and smooth but at ``s = 0`` and, for large
    ``p``, near ``s = 1``): antiderivatives at the edges, a binomial series for ``s <= 1/4``
    (:func:`_shape_series`) and Gauss-Legendre from there (:func:`_shape_band`); a node across
    ``r = d`` is split there. See :func:`node_shape_correction` for a grid of nodes."""
    lo, hi = jnp.broadcast_arrays(jnp.asarray(lo), jnp.asarray(hi))
    shp, n = lo.shape, lo.size
    a, inner, at_d = _shape_points(jnp.concatenate([lo.ravel(), hi.ravel()]), near_field, shape)
    out = _shape_nodes([x[:n] for x in a], inner[:n], [x[n:] for x in a], inner[n:], at_d, near_field)
    return tuple(x.reshape(shp) for x in out)


def node_shape_correction(lo, hi, near_field, shape):
    """:func:`shape_correction` for a grid of contiguous nodes (``lo``, ``hi``: (K,), non-decreasing,
    ``hi[k]`` the edge ``lo[k + 1]``), at a fraction of its cost: the band's quadrature
    (:func:`_shape_band`, ``d / 4 < r < 4 d``) runs only on a window of :data:`SHAPE_WINDOW`
    edges from the first one beyond ``d / 4``; every other edge takes the series alone. Where
    the window does not hold every edge between ``d / 4`` and ``4 d`` (a
    near field deeper than about 3 nodes) the band runs on all edges (a ``lax.cond``; under
    ``vmap`` both branches run)."""
    K = lo.shape[-1]
    if lo.ndim != 1 or K + 1 <= SHAPE_WINDOW:
        return shape_correction(lo, hi, near_field, shape)
    d = near_field
    edges = jnp.concatenate([lo[:1], hi])
    a = SHAPE_SERIES_SPLIT
    start = jnp.clip(jnp.sum(edges <= a * d), 0, K + 1 - SHAPE_WINDOW)  # edges before: series only
    valid = jnp.sum(edges < d / a) <= start + SHAPE_WINDOW  # and the edges after the window
    out, inner, at_d = _shape_points(edges, d, shape, (start, SHAPE_WINDOW, valid))
    return _shape_nodes([o[:-1] for o in out], inner[:-1], [o[1:] for o in out], inner[1:], at_d, d)


def node_falloff(nodes: Nodes, near_field, shape=2.0):
    """G integrated over each node's range: (atan(r_hi/r0) - atan(r_lo/r0)) / r0 at ``p = 2``
    (exactly), plus :func:`shape_correction` for another shape.

    G changes by a large factor within one node near the sensor; integrating it
    in closed form instead of sampling it keeps the near field accurate at any
    quadrature order. Ranges before emission are mirrored (G is even); the
    emission step then takes the share of the node after emission.
    """
    lo = nodes.r - 0.5 * nodes.dr
    hi = nodes.r + 0.5 * nodes.dr
    exact = (jnp.arctan(hi / near_field) - jnp.arctan(lo / near_field)) / near_field
    if isinstance(shape, (int, float)) and shape == 2.0:  # a Python 2: nothing to add (nothing traced)
        return exact
    # the correction on |r| (G is even): the node split at 0 where it straddles emission
    a, b = jnp.abs(lo), jnp.abs(hi)
    straddle = (lo < 0) & (hi > 0)
    d1 = shape_correction(jnp.where(straddle, 0.0, jnp.minimum(a, b)), jnp.where(straddle, a, jnp.maximum(a, b)), near_field, shape)[0]
    d2 = shape_correction(jnp.zeros_like(b), jnp.where(straddle, b, 0.0), near_field, shape)[0]
    return exact + d1 + d2


class NodeSpread(NamedTuple):
    """Where in its node each node's distributed mass sits: ``offset``, its mean from the node's
    centre, and ``variance``, its spread about that mean (both in node spacings, (K,))."""

    offset: jax.Array
    variance: jax.Array


def smooth_like_deposit(masses, offset=None):
    """Blur node masses with the [1/8, 3/4, 1/8] filter: the h^2/4 variance :func:`deposit` gives
    point events, so distributed and point-like terms share the pulse correction.

    ``offset`` (broadcast against ``masses``, in node spacings, within [-1/2, 1/2]): where in
    its node each node's mass sits on average; it is then shared with :func:`deposit`'s
    quadratic B-spline weights about that time (mass and mean time kept, the same h^2/4
    variance). A :class:`NodeSpread` (what :func:`node_falloff_after_emission` returns) also
    gives the mass's own spread within its node, added to the h^2/4: a node's mass is spread
    over its node (about h^2/12 far from the sensor), not a point, and leaving that out
    biases a decaying return by about ``-(h^2/24) f''/f`` (a slow range-dependent error that a
    fit reads as attenuation). None (or 0): at the node's centre, the filter above."""
    pad = [(0, 0)] * (masses.ndim - 1) + [(1, 1)]
    if offset is None:
        p = jnp.pad(masses, pad)
        return 0.75 * masses + 0.125 * (p[..., :-2] + p[..., 2:])
    if isinstance(offset, NodeSpread):
        d = jnp.broadcast_to(offset.offset, masses.shape)
        var = jnp.clip(jnp.broadcast_to(offset.variance, masses.shape), 0.0, 0.25 - d**2)
    else:
        d = jnp.broadcast_to(offset, masses.shape)
        var = 0.0
    # three weights with mean d and variance 1/4 + var (second moment 1/4 + var + d^2 <= 1/2),
    # all non-negative for |d| <= 1/2 and var <= 1/4 - d^2: what stays, what goes to the node
    # before, what goes to the node after
    second = 0.25 + var + d**2
    shares = jnp.stack([masses * (1.0 - second), masses * 0.5 * (second - d), masses * 0.5 * (second + d)], axis=-2)
    # summed by a 3-tap convolution (out[k] = stay[k] + before[k + 1] + after[k - 1]), not by shifted
    # slices: XLA fuses slices into their consumer and recomputed the shares' operand (and, in a
    # Jacobian, its tangents) at all three places; a convolution's operand is computed once
    # (the calibration's step 4.8 against 6.0 ms; equal to 2e-16)
    K = masses.shape[-1]
    taps = jnp.asarray([[[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]], masses.dtype)  # (out 1, in 3, width 3)
    rows = math.prod(masses.shape[:-1])
    # HIGHEST: a float32 convolution on a GPU may round its inputs to TF32 (10 bits); the sum must stay exact
    out = jax.lax.conv_general_dilated(shares.reshape((rows, 3, K)), taps, (1,), [(1, 1)], dimension_numbers=("NCH", "OIH", "NCH"),
                                       precision=jax.lax.Precision.HIGHEST)
    return out.reshape(masses.shape)


def node_falloff_after_emission(nodes: Nodes, near_field, shape=2.0):
    """G integrated over the part of each node's range after emission, and where in the node
    that mass sits: ``(mass (K,), NodeSpread(offset (K,), variance (K,)))``, in node spacings:
    the mean range of ``G`` over the part from the node's centre, and its variance about that
    mean (closed forms: ``int r G dr = ln(r^2 + r0^2) / 2``, ``int r^2 G dr = r - r0 atan(r / r0)``).

    Near the sensor ``G`` falls by a large factor within one node, so its mass sits well off
    the node's centre (with 100 ps bins and two nodes per bin a node spans 5 mm of range, the
    near field 2-5 mm): put at the centre, the near-field return arrives up to a quarter of a
    node early or late depending on where the emission time falls, and a fit moves the
    emission time (and with it n1) to make up for it. Nodes before emission have no mass.
    """
    r0 = near_field
    # where a node edge crosses the emission the split between the two nodes would have a kink
    # in the emission time: a smooth max (1/50 of a node wide; the two nodes share the edge, so
    # the mass is kept) keeps the model continuously differentiable
    eps = 0.02 * nodes.dr

    def after_emission(x):
        # 0.5 (x + sqrt(x^2 + eps^2)), written without cancellation for x < 0 (float32: nodes
        # long before emission must get 0, not rounding noise of either sign). The branch not
        # taken divides by sq + x (no cancellation, never 0), not by a placeholder: where an edge
        # sits on the emission (x within rounding of 0, a round emission time on the node grid)
        # XLA may evaluate the two tests of x > 0 apart, each with its own rounding, and a
        # placeholder 1 then gave the edge 0.5 eps^2 instead of eps / 2 (the node's spread 11% off)
        sq = jnp.sqrt(x * x + eps * eps)
        pos = x > 0
        return jnp.where(pos, 0.5 * (x + sq), 0.5 * eps * eps / jnp.where(pos, sq + x, sq - x))

    lo = after_emission(nodes.r - 0.5 * nodes.dr)
    hi = after_emission(nodes.r + 0.5 * nodes.dr)
    # the closed forms of G at p = 2, plus what another shape p adds (0 at p = 2)
    dm, df1, df2 = node_shape_correction(lo, hi, r0, shape)
    mass = jnp.maximum(jnp.arctan(hi / r0) - jnp.arctan(lo / r0) + r0 * dm, 0.0) / r0
    first = 0.5 * (jnp.log1p((hi / r0) ** 2) - jnp.log1p((lo / r0) ** 2)) + df1  # int r G dr
    some = mass > 1e-9 * (0.5 * jnp.pi / r0)  # the double-where keeps the gradient finite
    safe = jnp.where(some, mass, 1.0)
    mean_r = jnp.where(some, first / safe, 0.5 * (lo + hi))
    rc, dr = nodes.r, nodes.dr
    # int (r - rc)^2 G dr = (hi - lo) - 2 rc int r G + (rc^2 - r0^2) int G: exact, but it cancels
    # as (dr / r)^2 far from the sensor, so there (R > 30 dr; 6 dr in float32, whose digits run
    # out sooner) the moments of G's Taylor series about the node's centre take over (a density
    # 1 + a x + b x^2 + c x^3 on a whole node, x in node spacings): the two agree there to ~1e-6
    # (float32: ~1e-5) node^2
    # (with another shape: the p = 2 identity applied to the p = 2 parts, plus the corrections'
    # own second moment about the centre)
    mass2, first2 = mass - dm, first - df1
    second = (hi - lo) - 2.0 * rc * first2 + (rc * rc - r0 * r0) * mass2 + (df2 - 2.0 * rc * df1 + rc * rc * dm)
    exact_off = (mean_r - rc) / dr
    exact_var = jnp.where(some, second / (safe * dr * dr), 0.0) - exact_off**2
    R2 = rc * rc + r0 * r0
    far = R2 > ((30.0 if dr.dtype == jnp.float64 else 6.0) * dr) ** 2
    R2 = jnp.where(far, R2, (30.0 * dr) ** 2)  # the double-where: the series only where it is used
    u = dr * dr / R2
    a = -2.0 * rc * dr / R2  # G' / G dr
    b = 0.5 * (6.0 * rc * rc - 2.0 * r0 * r0) / R2 * u  # G'' / (2 G) dr^2
    c = 4.0 * rc * (r0 * r0 - rc * rc) / (R2 * R2) * dr * u  # G^(3) / (6 G) dr^3
    m0 = 1.0 + b / 12.0
    series_off = (a / 12.0 + c / 80.0) / m0
    series_var = (1.0 / 12.0 + b / 80.0) / m0 - series_off**2
    offset = jnp.clip(jnp.where(far, series_off, exact_off), -0.5, 0.5)
    variance = jnp.clip(jnp.where(far, series_var, exact_var), 0.0, 0.25 - offset**2)
    return mass, NodeSpread(offset, variance)


def transmittance(r, mu_t):
    """Round-trip transmittance T (Eq. 5) to range ``r``; underflows to 0, never overflows."""
    return jnp.exp(-2.0 * mu_t * jnp.maximum(r, 0.0))


def deposit(times, masses, nodes: Nodes):
    """Put point masses at ``times`` (S, Z, E) onto the nodes: (S, Z, K).

    Quadratic B-spline weights on the three nearest nodes (the "triangular
    shaped cloud" of particle-mesh codes): mass and mean time are conserved,
    and the result is continuously differentiable in the times, so gradients
    agree with finite differences wherever an event sits. The cost is a
    scatter of 3E values. Events outside the histogram are dropped.
    """
    S, Z, E = times.shape
    K = nodes.t.shape[0]
    u = times / nodes.h - 0.5  # position in node units
    centre = jnp.round(u)
    d = u - centre  # in [-1/2, 1/2]
    i = centre.astype(jnp.int32)
    # the three nodes' weights in one scatter (three scatters cost three XLA operations, each a loop of its own)
    k = i[..., None] + jnp.arange(-1, 2, dtype=i.dtype)  # (S, Z, E, 3)
    w = jnp.stack([0.5 * (0.5 - d) ** 2, 0.75 - d**2, 0.5 * (0.5 + d) ** 2], -1)
    s_idx = jnp.broadcast_to(jnp.arange(S)[:, None, None, None], (S, Z, E, 3))
    z_idx = jnp.broadcast_to(jnp.arange(Z)[None, :, None, None], (S, Z, E, 3))
    out = jnp.zeros((S, Z, K), masses.dtype)
    # below the first node: dropped (a negative index would wrap on to the last node)
    return out.at[s_idx, z_idx, jnp.where(k >= 0, k, K)].add(masses[..., None] * w, mode="drop")


def step_on(times, nodes: Nodes):
    """Smooth step at each node: the share of events at ``times`` (S, Z, E) before the node's centre.

    The running sum of :func:`deposit` (unit mass shared by the events),
    counting half of the node's own share: a discretised step that is
    continuously differentiable in the event times.
    """
    w = deposit(times, jnp.full(times.shape, 1.0 / times.shape[-1], nodes.t.dtype), nodes)
    return jnp.cumsum(w, axis=-1) - 0.5 * w


# ---- contacts -------------------------------------------------------------------------


class ContactGeometry(NamedTuple):
    distance: jax.Array  # (S, N) sensor-to-centre distance, m
    fraction: jax.Array  # (S, Z, N) share of the contact (its area: chord-weighted angles) inside each zone
    zone_cover: jax.Array  # (S, Z, N) fraction of each zone's angular width the contact covers


def contact_geometry(geom: Geometry, params: Params) -> ContactGeometry:
    d = params.touch_xy_m[None, :, :] - geom.sensor_xy[:, None, :]  # (S, N, 2)
    c, s = jnp.cos(geom.sensor_dir)[:, None], jnp.sin(geom.sensor_dir)[:, None]
    u = d[..., 0] * c + d[..., 1] * s  # along the optical axis
    v = -d[..., 0] * s + d[..., 1] * c
    # A contact on top of the sensor has no direction: the double-where keeps atan2's gradient finite.
    at_sensor = u**2 + v**2 < 1e-18
    rel = jnp.arctan2(jnp.where(at_sensor, 0.0, v), jnp.where(at_sensor, 1.0, u))
    dist = jnp.sqrt(u**2 + v**2 + 1e-12)
    half = jnp.arctan(params.touch_radius_m[None, :] / dist)  # angular half-width, < pi/2
    lo = jnp.maximum(geom.zone_lo[None, :, None], (rel - half)[:, None, :])
    hi = jnp.minimum(geom.zone_hi[None, :, None], (rel + half)[:, None, :])
    overlap = jnp.maximum(hi - lo, 0.0)  # (S, Z, N)
    zone_width = (geom.zone_hi - geom.zone_lo)[None, :, None]
    # the contact's light per angle follows its chord there (a disk: the semicircle law), not its angular width
    x_lo = (lo - rel[:, None, :]) / half[:, None, :]
    x_hi = (hi - rel[:, None, :]) / half[:, None, :]
    fraction = jnp.where(overlap > 0, _semicircle_cdf(x_hi) - _semicircle_cdf(x_lo), 0.0)
    return ContactGeometry(dist, fraction, overlap / zone_width)


def _semicircle_cdf(x):
    """Share of a disk's area on the near side of a chord at ``x`` radii from its centre (``x`` in [-1, 1]):
    ``1/2 + (x sqrt(1 - x^2) + asin x) / pi``; kept a hair inside +-1, where asin's slope is infinite."""
    x = jnp.clip(x, -1.0 + 1e-6, 1.0 - 1e-6)
    return 0.5 + (x * jnp.sqrt(1.0 - x * x) + jnp.arcsin(x)) / math.pi


def shadow(r, cg: ContactGeometry, params: Params, exclude_self: bool = False):
    """Fraction of light that gets to range ``r`` and back past the contacts in the zone.

    ``r`` has shape (S, Z, ...). Contact ``i`` removes a fraction
    ``opacity * zone_cover_i`` of the zone's light beyond its range, switched
    on smoothly over its radius; squared for the round trip. With
    ``exclude_self`` the last axis of ``r`` indexes contacts (S, Z, N, M) and
    a contact does not shadow itself.
    """
    o = params.shadow_opacity * cg.zone_cover  # (S, Z, N)
    rad = params.touch_radius_m
    if exclude_self:
        # r: (S, Z, N_target, M); blockers on a new last axis.
        step = jax.nn.sigmoid((r[..., None] - cg.distance[:, None, None, None, :]) / rad)  # (S,Z,Nt,M,Nb)
        n = rad.shape[0]
        mask = 1.0 - jnp.eye(n, dtype=r.dtype)[None, None, :, None, :]
        block = o[:, :, None, None, :] * step * mask
    else:
        step = jax.nn.sigmoid((r[..., None] - cg.distance[:, None, None, :]) / rad)  # (S, Z, R, N)
        block = o[:, :, None, :] * step
    return jnp.prod((1.0 - block) ** 2, axis=-1)


def _chord_samples(m: int):
    """Range offsets (in radii) and weights of a disk seen from afar: semicircle density."""
    k = jnp.arange(1, m + 1)
    theta = k * math.pi / (m + 1)
    w = jnp.sin(theta) ** 2
    return jnp.cos(theta), w / jnp.sum(w)


def contact_ranges(ctx, floor=0.0):
    """Each contact disk's range samples ``r`` (S, N, M), never below ``floor``, and their weights (M,)."""
    p, cg = ctx.params, ctx.contacts
    u, w = _chord_samples(ctx.touch_samples)
    u, w = u.astype(p.n1.dtype), w.astype(p.n1.dtype)
    return jnp.maximum(cg.distance[..., None] + p.touch_radius_m[:, None] * u, floor), w


# ---- the components ---------------------------------------------------------------------


def crosstalk(ctx) -> jax.Array:
    """Light-entry peak: light reaching the detector at emission, before entering the guide."""
    p, nodes = ctx.params, ctx.nodes
    t = jnp.broadcast_to(p.emission_time_s, p.crosstalk_counts.shape)[..., None]
    return deposit(t, p.crosstalk_counts[..., None], nodes)


def interface(ctx) -> jax.Array:
    """Q_int density per unit range: roughness backscatter beta_int (per metre) times G T."""
    p = ctx.params
    return p.interface_backscatter_per_m * ctx.falloff * ctx.transmittance


def volume(ctx) -> jax.Array:
    """Q_vol density: single backscatter from the medium, beta_vol = f_back mu_s (proportional to mu_s)."""
    p = ctx.params
    return p.volume_backscatter_fraction * p.mu_s_per_m * ctx.falloff * ctx.transmittance


def multiple_scattering(ctx) -> jax.Array:
    """N_ms density: light scattered out of the beam and back again.

    Scattered light stays in the guide, so only absorption removes it
    (``exp(-2 mu_a r)``), and it builds up as ``1 - exp(-2 mu_s r)``: zero
    without scattering, saturating once most light has scattered.
    """
    p = ctx.params
    r = ctx.range
    build_up = -jnp.expm1(-2.0 * p.mu_s_per_m * r)
    return p.multiple_scattering * p.mu_s_per_m * build_up * ctx.falloff * transmittance(r, p.mu_a_per_m)


#: Smallest cosine of incidence the edge law sees: a ray grazing an edge (cos -> 0) keeps a
#: finite log, so cos^p and its derivative in p stay finite for every p the Params allow.
EDGE_COS_FLOOR = 1e-3


def edge_incidence_cos(size_m, xy, angle):
    """|cos| of the angle between rays from ``xy`` (..., 2) along ``angle`` (...) and the normal
    of the edge of the rectangular waveguide they hit (NumPy; the edge
    :func:`tofjax.model.geometry.edge_hits` finds, as :func:`~tofjax.model.geometry.boundary_distance` does)."""
    import numpy as np

    from .geometry import edge_hits

    tx, ty, c, s = edge_hits(size_m, xy, angle)
    return np.where(tx <= ty, np.abs(c), np.abs(s))


def edge_law(cos_incidence, power):
    """The edge's angle law relative to normal incidence, ``cos(theta)^p`` (1 for ``p = 0``);
    ``cos_incidence`` floored at :data:`EDGE_COS_FLOOR`."""
    return jnp.exp(power * jnp.log(jnp.maximum(cos_incidence, EDGE_COS_FLOOR)))


def end(ctx) -> jax.Array:
    """The far-edge reflection along each of a zone's rays, averaged over the zone.

    The edge returns ``R(theta) = end_reflectance * cos(theta)^end_incidence_power`` of the
    light that reaches it, ``theta`` the angle of incidence of each ray on the edge it hits
    (any of the guide's four edges: the "far" edge is wherever the ray leaves the guide)."""
    p, geom = ctx.params, ctx.geom
    length = geom.ray_length  # (S, Z, A)
    mu_t = p.mu_s_per_m + p.mu_a_per_m
    refl = p.end_reflectance
    if ctx.edge_cos is not None:
        refl = refl * edge_law(ctx.edge_cos, p.end_incidence_power)
    amp = refl * falloff(length, p.near_field_m, p.near_field_shape) * transmittance(length, mu_t)
    amp = jnp.where(length > 0, amp, 0.0) / length.shape[-1]  # rays pointing out see no edge
    if ctx.contacts is not None:
        amp = amp * shadow(length, ctx.contacts, p)
    return p.gain[:, None, None] * deposit(ctx.end_times, amp, ctx.nodes)


def touch(ctx) -> jax.Array:
    """Q_touch: each contact seen by every zone whose angular window overlaps it.

    ``beta_touch`` of contact ``j`` in a zone is its strength times the
    share of its area inside the zone's wedge, so over the zones that see
    all of it the decay-corrected signal sums to its strength, at any
    distance. Its range spread is that of a disk (a semicircle around ``D``).
    """
    p, nodes, cg = ctx.params, ctx.nodes, ctx.contacts
    r, w = contact_ranges(ctx)  # (S, N, M), (M,)
    mu_t = p.mu_s_per_m + p.mu_a_per_m
    beta = p.touch_strength * cg.fraction  # (S, Z, N)
    amp = beta[..., None] * (w * falloff(r, p.near_field_m, p.near_field_shape) * transmittance(r, mu_t))[:, None]  # (S,Z,N,M)
    if ctx.shadowing:
        amp = amp * shadow(jnp.broadcast_to(r[:, None], amp.shape), cg, p, exclude_self=True)
    t = p.emission_time_s + 2.0 * r / nodes.c1  # (S, N, M)
    S, Z = amp.shape[:2]
    t = jnp.broadcast_to(t[:, None], amp.shape).reshape(S, Z, -1)
    return p.gain[:, None, None] * deposit(t, amp.reshape(S, Z, -1), nodes)


#: Backscatter spread along the range: densities per metre of range, shape (K,).
DISTRIBUTED = {"interface": interface, "volume": volume, "multiple_scattering": multiple_scattering}
#: Point-like components: node masses, shape (S, Z, K).
POINT = {"crosstalk": crosstalk, "end": end, "touch": touch}
