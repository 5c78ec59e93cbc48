"""The instrument response: an exponentially modified Gaussian (EMG) pulse.

Real TMF882x pulses rise sharply and decay with a long tail. The EMG (a
Gaussian of width sigma convolved with a one-sided exponential of time
constant tau) has both, and its cumulative distribution has a closed form, so
bins are integrated exactly instead of sampled at their centres.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.scipy.special import erfcx

__all__ = [
    "emg_cdf",
    "emg_pdf",
    "emg_mixture_cdf",
    "pulse_cdf",
    "binned_response",
    "bin_kernels",
    "apply_kernels",
    "template_cdf",
    "template_bin_masses",
]

_SQRT2 = 1.4142135623730951


def _safe_widths(sigma, tau, floor):
    sigma = jnp.sqrt(sigma**2 + floor**2)
    return sigma, jnp.maximum(tau, 1e-6 * sigma)


@jax.custom_jvp
def _cdf_terms(x, sigma, tau):
    """``(Phi(x/s), T)`` with ``T = exp(s^2/(2 t^2) - x/t) Phi(x/s - s/t)``, broadcast to one
    shape, without overflow, underflow or cancellation: the EMG's CDF is ``Phi - T`` and its
    density ``T / t``.

    One call of ``erfcx`` (on ``|z|`` and ``|w|``, ``z = x/(s sqrt 2)``, ``w = (s/t - x/s)/sqrt 2``)
    serves both: ``erfc(u) = exp(-u^2) erfcx(u)`` for ``u >= 0`` and ``2 - exp(-u^2) erfcx(-u)``
    below. For ``w > 0``, ``T = exp(-z^2) erfcx(w) / 2`` (both factors bounded); for ``w <= 0``
    the exponent ``s^2/(2t^2) - x/t`` is <= -s^2/(2 t^2) <= 0 and ``erfc(w) <= 2``. Each branch
    is evaluated only on safe arguments (the double-where trick), so values are finite for any
    pulse widths.

    The derivatives are written down (:func:`_cdf_terms_jvp`) rather than traced through
    ``erfcx``'s rational approximation and its branches: a fit's Jacobian then compiles a few
    products per derivative. (Traced, with ``erfc`` beside ``erfcx``, the pulse was a third of
    the calibration fit's compiled program.)
    """
    x, sigma, tau = jnp.broadcast_arrays(x, sigma, tau)
    z = x / (sigma * _SQRT2)
    w = (sigma / tau - x / sigma) / _SQRT2
    ez, ew = erfcx(jnp.abs(jnp.stack([z, w])))
    gauss = jnp.exp(-(z**2))  # exp(-x^2 / (2 s^2))
    half = 0.5 * gauss * ez  # 0.5 erfc(|z|)
    phi = jnp.where(z <= 0, half, 1.0 - half)
    pos = w > 0
    w_neg = jnp.where(pos, 0.0, w)
    x_neg = jnp.where(pos, sigma**2 / tau, x)
    a = 0.5 * gauss * ew
    b = 0.5 * jnp.exp(0.5 * (sigma / tau) ** 2 - x_neg / tau) * (2.0 - jnp.exp(-(w_neg**2)) * ew)
    return phi, jnp.where(pos, a, b)


_INV_SQRT_2PI = 0.3989422804014327


@_cdf_terms.defjvp
def _cdf_terms_jvp(primals, tangents):
    """With ``g = phi(x/s)`` (the standard normal density; the identity
    ``exp(s^2/(2t^2) - x/t) phi(x/s - s/t) = phi(x/s)`` removes the shifted one):
    ``dPhi = g (dx/s - x ds/s^2)``; ``dT/dx = g/s - T/t``, ``dT/ds = T s/t^2 - g (x/s^2 + 1/t)``,
    ``dT/dt = T (x/t^2 - s^2/t^3) + g s/t^2``. Higher derivatives go through this rule again,
    so they stay as cheap."""
    x, s, t = primals
    dx, ds, dt = tangents
    phi, T = _cdf_terms(x, s, t)
    g = _INV_SQRT_2PI * jnp.exp(-0.5 * (x / s) ** 2)
    rs, rt = 1.0 / s, 1.0 / t
    d_phi = g * rs * (dx - x * rs * ds)
    d_t = dx * (g * rs - T * rt)
    d_t = d_t + ds * (T * s * rt**2 - g * (x * rs**2 + rt))
    d_t = d_t + dt * (T * (x - s**2 * rt) * rt**2 + g * s * rt**2)
    return (phi, T), (jnp.broadcast_to(d_phi, phi.shape), jnp.broadcast_to(d_t, T.shape))


def emg_cdf(x, sigma, tau, floor=0.0):
    """P(arrival <= x) for a pulse emitted at 0: ``Phi(x/s) - exp(s^2/(2t^2) - x/t) Phi(x/s - s/t)``.

    ``floor`` keeps sigma away from 0 (a pulse narrower than the quadrature
    cannot be resolved anyway).
    """
    sigma, tau = _safe_widths(sigma, tau, floor)
    phi, T = _cdf_terms(x, sigma, tau)
    return jnp.clip(phi - T, 0.0, 1.0)


def emg_pdf(x, sigma, tau, floor=0.0):
    """The pulse shape itself (per second), for plots and tests."""
    sigma, tau = _safe_widths(sigma, tau, floor)
    return _cdf_terms(x, sigma, tau)[1] / tau


def emg_mixture_cdf(x, weights, sigmas, taus, delays, floor=0.0):
    """CDF of a sum of ex-Gaussians (weights sum to one): real TMF882x returns have a second,
    slower tail that one EMG cannot follow. Each component ``i`` is delayed by ``delays[i]``."""
    x = jnp.asarray(x)[..., None]
    w = jnp.asarray(weights) / jnp.sum(jnp.asarray(weights))
    return jnp.sum(w * emg_cdf(x - jnp.asarray(delays), jnp.asarray(sigmas), jnp.asarray(taus), floor), axis=-1)


def pulse_cdf(x, sigma, tau, slow_weight=0.0, slow_tau=None, floor=0.0):
    """CDF of the model's pulse: one EMG, or with ``slow_weight > 0`` the two-tail pulse
    ``(1 - w) EMG(sigma, tau) + w EMG(sigma, slow_tau)`` (a Gaussian convolved with two
    exponential tails, the second slower: what a real SPAD's diffusion tail looks like)."""
    if slow_tau is None:
        return emg_cdf(x, sigma, tau, floor)
    both = emg_cdf(jnp.asarray(x)[..., None], sigma, jnp.stack([jnp.asarray(tau), jnp.asarray(slow_tau)]), floor)
    return (1.0 - slow_weight) * both[..., 0] + slow_weight * both[..., 1]


def binned_response(t, bin_width_s, sigma, tau, slow_weight=0.0, slow_tau=None):
    """The pulse integrated over a bin centred ``t`` after a point event (NumPy in, NumPy out;
    for the inversion's response delay and unit peak)."""
    import jax
    import numpy as np

    with jax.ensure_compile_time_eval():
        t = jnp.asarray(t)
        return np.asarray(
            pulse_cdf(t + 0.5 * bin_width_s, sigma, tau, slow_weight, slow_tau)
            - pulse_cdf(t - 0.5 * bin_width_s, sigma, tau, slow_weight, slow_tau)
        )


def template_cdf(u, pdf, start, step):
    """CDF of an empirical instrument response at ``u`` (any shape, same units as ``step``).

    The pulse is piecewise linear between knots ``start + k step`` with values
    ``pdf[k]`` (k = 0..K-1) and zero outside them, so its CDF is piecewise
    quadratic and continuous with a continuous first derivative in ``u``: a
    sub-bin time shift moves bin contents smoothly (a piecewise-constant pulse
    gives kinks that a ranging fit snaps to). Not normalised: the CDF ends at
    the pulse's area.
    """
    pdf = jnp.asarray(pdf)
    K = pdf.shape[0]
    cell = step * 0.5 * (pdf[:-1] + pdf[1:])
    cum = jnp.concatenate([jnp.zeros((1,), pdf.dtype), jnp.cumsum(cell)])  # (K,) CDF at the knots
    x = (u - start) / step
    k = jnp.clip(jnp.floor(x), 0, K - 2)
    r = jnp.clip(x - k, 0.0, 1.0)
    ki = k.astype(jnp.int32)
    p0, p1 = pdf[ki], pdf[ki + 1]
    inner = cum[ki] + step * (p0 * r + 0.5 * (p1 - p0) * r * r)
    return jnp.where(x <= 0.0, 0.0, jnp.where(x >= K - 1, cum[-1], inner))


def template_bin_masses(shift_bins, pdf, start_bins, step_bins, n_bins, edges=None):
    """Exact bin integrals of an empirical pulse placed at ``shift_bins`` (..., ) -> (..., n_bins).

    Times in units of bins: bin ``b`` spans ``[b, b + 1)``, or ``[edges[b], edges[b + 1])``
    for a time-to-digital converter with unequal bins (differential non-linearity); the
    pulse's knot 0 sits at ``shift_bins + start_bins``.
    """
    if edges is None:
        edges = jnp.arange(n_bins + 1, dtype=jnp.result_type(pdf, float))
    u = edges - jnp.asarray(shift_bins)[..., None]
    c = template_cdf(u, pdf, start_bins, step_bins)
    return c[..., 1:] - c[..., :-1]


def bin_kernels(node_h, n_bins, q, sigma, tau, dtype, slow_weight=None, slow_tau=None):
    """Bin-integrated pulse for unit mass at each node phase: (q, 2 n_bins - 1).

    Nodes sit at ``(k + 1/2) h`` (``h = bin_width / q``) and bin ``b`` spans
    ``[b q h, (b + 1) q h)``. A node ``k = b' q + j`` (phase ``j``) adds
    ``kernel[j, b - b' + n_bins - 1]`` counts per unit mass to bin ``b``: the
    difference of the pulse CDF at the bin's two edges, i.e. exact bin
    integration of the pulse. Only ``q (2 n_bins)`` CDF values are computed.

    With ``slow_weight`` and ``slow_tau`` the pulse has two tails (:func:`pulse_cdf`).
    """
    n = jnp.arange(-(n_bins - 1), n_bins + 1, dtype=dtype)  # bin offsets b - b', one extra edge
    j = jnp.arange(q, dtype=dtype)[:, None]
    # Work in node units: squares of seconds underflow float32.
    sig, tail = sigma / node_h, tau / node_h
    # Depositing on nodes (quadratic B-spline weights) blurs every event by a variance of
    # exactly h^2/4; take it out of the Gaussian rise where the pulse is wide enough
    # (a smooth max keeps this differentiable), so errors fall faster with q.
    s2 = sig**2 - 0.25
    sig_k = jnp.sqrt(0.5 * (s2 + jnp.sqrt(s2**2 + 0.0625**2)))
    x = n * q - j - 0.5
    if slow_weight is None:
        edges = emg_cdf(x, sig_k, tail, floor=1e-3)  # (q, 2 n_bins)
    else:  # both tails in one evaluation (one program site: half the compiled pulse)
        both = emg_cdf(x[..., None], sig_k, jnp.stack([tail, slow_tau / node_h]), floor=1e-3)
        edges = (1.0 - slow_weight) * both[..., 0] + slow_weight * both[..., 1]
    return edges[:, 1:] - edges[:, :-1]


def _toeplitz(kernels, n_bins):
    """``M[j, b, b'] = kernels[j, b - b' + n_bins - 1]`` as (q, n_bins, n_bins).

    Built from tile, reshape and slice only: each row is the reversed kernel
    shifted by one more place, which a tiled copy of period ``2 n_bins`` read
    with stride ``2 n_bins - 1`` gives. (A gather here was measured 10-20x
    slower on CPU: XLA re-evaluated the pulse CDF inside it.)
    """
    B = n_bins
    u = kernels[:, ::-1]
    x = jnp.concatenate([u, jnp.zeros_like(u[:, :1])], axis=1)  # (q, 2B)
    y = jnp.concatenate([x[:, B - 1 :], x[:, : B - 1]], axis=1)  # start row 0 at u[B - 1]
    tiled = jnp.tile(y, (1, B))[:, : B * (2 * B - 1)]
    return tiled.reshape(-1, B, 2 * B - 1)[:, :, :B]


def apply_kernels(masses, kernels, n_bins, q):
    """Counts per bin from node masses (..., n_bins q): a product with the Toeplitz matrix of
    each node phase (measured faster than ``lax.conv`` and FFT at these sizes on CPU)."""
    m = masses.reshape(*masses.shape[:-1], n_bins, q)
    return jnp.einsum("...cj,jbc->...b", m, _toeplitz(kernels, n_bins))
