"""``tofjax range``: the distance each zone sees in each frame, from a fitted sensor model.

Each (frame, zone) histogram gets its own Poisson fit of three numbers with the zone's
learned pulse and pile-up held fixed: the pulse position, its amplitude and the ambient
floor. Levenberg-Marquardt steps on the deviance, a fixed number of them, vmapped over
every histogram in one compiled call. The distance is the position through the zone's
straight line (``SensorResponse.distance_m``); its standard error is the position's, from
the Fisher information, inflated by the frame's reduced chi-square when that exceeds 1.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .fit import SATURATION, peak_positions, poisson_deviance_residuals
from .response import SensorModelError, SensorResponse, zone_counts

__all__ = ["range_histograms", "ranges_to_json"]


def _fit_one(h, x0, pulse, start, step, n_bins, pulses, iterations, drift=None, echo=None):
    def counts(x):
        e = None
        if echo is not None:  # its own amplitude (x[3], log), at twice the distance
            e = jnp.exp(x[3])
        return zone_counts(pulse, start, step, n_bins, x[0], jnp.exp(x[1]), x[2], pulses, drift=drift,
                           echo=e, zero_shift=0.0 if echo is None else echo[2])

    def resid(x):
        mu = counts(x)
        return poisson_deviance_residuals(h, mu)

    jac = jax.jacfwd(resid)

    def body(carry, _):
        x, lam = carry
        r = resid(x)
        J = jac(x)
        A = J.T @ J
        g = J.T @ r
        D = jnp.diag(jnp.maximum(jnp.diag(A), 1e-12))
        step_ = -jnp.linalg.solve(A + lam * D, g)
        xn = x + step_
        better = jnp.sum(resid(xn) ** 2) <= jnp.sum(r**2)
        better = better & jnp.all(jnp.isfinite(xn))
        x = jnp.where(better, xn, x)
        lam = jnp.where(better, lam / 3.0, lam * 4.0)
        return (x, lam), None

    (x, _), _ = jax.lax.scan(body, (x0, jnp.asarray(1e-3, x0.dtype)), None, length=iterations)
    J = jac(x)
    cov = jnp.linalg.pinv(J.T @ J)
    mu = counts(x)
    chi2 = jnp.sum((h - mu) ** 2 / jnp.maximum(mu, 1e-9)) / (n_bins - x.shape[0])
    return x, jnp.sqrt(jnp.maximum(cov[0, 0], 0.0)), chi2


def _grid_start(h, s0, pulse, start, step, span=2.0, n=41):
    """Best pulse position on a grid around ``s0`` (frames,), with amplitude and floor solved
    linearly at each point (weighted least squares): a start inside the right basin."""
    B = h.shape[-1]
    cand = s0[:, None] + np.linspace(-span, span, n)[None, :]  # (F, n)
    from ..model.pulse import template_bin_masses

    m = np.asarray(template_bin_masses(jnp.asarray(cand), jnp.asarray(pulse), start, step, B))  # (F, n, B)
    w = 1.0 / np.maximum(h, 1.0)[:, None, :]
    hh = h[:, None, :]
    # normal equations of (A, c) for A m + c
    smm, sm1, s11 = (w * m * m).sum(-1), (w * m).sum(-1), w.sum(-1)
    smh, s1h = (w * m * hh).sum(-1), (w * hh).sum(-1)
    det = smm * s11 - sm1**2
    A = (smh * s11 - sm1 * s1h) / np.where(det > 0, det, 1.0)
    c = (smm * s1h - sm1 * smh) / np.where(det > 0, det, 1.0)
    cost = (w * (hh - A[..., None] * m - c[..., None]) ** 2).sum(-1)
    return cand[np.arange(len(h)), np.argmin(cost, axis=1)]


@functools.lru_cache(maxsize=8)
def _ranger(start, step, n_bins, pile, iterations, with_drift, with_echo):
    def one(hh, xx, pulse, n, drift, echo):
        return _fit_one(hh, xx, pulse, start, step, n_bins, n if pile else None, iterations, drift if with_drift else None,
                        echo if with_echo else None)

    return jax.jit(jax.vmap(one, in_axes=(0, 0, None, None, None, None)))


def range_histograms(model: SensorResponse, histograms, *, iterations: int = 30):
    """Distances (frames, zones) with standard errors and reduced chi-squares from histograms (frames, zones, bins).

    **Returns:** dict of arrays ``distance_m``, ``stderr_m``, ``reduced_chi2``, ``shift_bins``, ``amplitude``, ``ambient``.
    """
    h = np.asarray(histograms, float)
    if h.ndim == 2:
        h = h[None]
    F, Z, B = h.shape
    if Z != model.n_zones or B != model.n_bins:
        raise SensorModelError(f"histograms have {Z} zones x {B} bins, the sensor model {model.n_zones} x {model.n_bins}")
    sat = np.flatnonzero(np.any(h >= SATURATION, axis=(1, 2)))
    if len(sat):
        shown = ", ".join(map(str, sat[:12])) + (f", ... ({len(sat)} in all)" if len(sat) > 12 else "")
        raise SensorModelError(f"frame{'s' if len(sat) > 1 else ''} {shown} {'have' if len(sat) > 1 else 'has'} saturated bins (a count of 2^24 - 1): "
                               "a saturated histogram has lost the shape a range needs; leave those frames out")
    out = {k: np.zeros((F, Z)) for k in ("distance_m", "stderr_m", "reduced_chi2", "shift_bins", "amplitude", "ambient")}
    peaks = peak_positions(h)  # start at the highest bin's parabola, less the pulse's own peak offset
    for z in range(Z):
        pulse = jnp.asarray(model.pulse[z])
        knots = model.pulse_start_bins + model.pulse_step_bins * np.arange(model.pulse.shape[1])
        peak_offset = float(knots[np.argmax(model.pulse[z])])
        amb0 = np.median(np.concatenate([h[:, z, :6], h[:, z, -6:]], 1), 1)
        a0 = np.log(np.maximum(h[:, z].sum(1) - amb0 * B, 10.0))
        s0 = _grid_start(h[:, z], peaks[:, z] - peak_offset, model.pulse[z], model.pulse_start_bins, model.pulse_step_bins)
        x0 = np.stack([s0, a0, amb0], 1)
        if model.echo_ratio is not None:  # start the echo at the fitted law's ratio
            d0 = np.maximum((s0 - model.zero_range_bins[z]) / model.bins_per_m[z], 1e-3)
            x0 = np.concatenate([x0, (a0 + np.log(model.echo_ratio[z] * (d0 / 0.2) ** model.echo_power[z]))[:, None]], 1)
        pile = model.pulses_per_histogram is not None
        N = float(model.pulses_per_histogram[z]) if pile else 1.0
        with_drift = model.pulse_drift is not None
        with_echo = model.echo_ratio is not None
        f = _ranger(float(model.pulse_start_bins), float(model.pulse_step_bins), B, pile, iterations, with_drift, with_echo)
        drift = jnp.asarray(model.drift_terms(z)) if with_drift else jnp.zeros_like(pulse)
        echo = jnp.asarray([model.echo_ratio[z], model.echo_power[z], model.zero_range_bins[z], model.bins_per_m[z]]
                           if with_echo else [0.0, 0.0, 0.0, 1.0])
        x, se, chi2 = (np.asarray(v) for v in f(jnp.asarray(h[:, z]), jnp.asarray(x0), pulse, jnp.asarray(N), drift, echo))
        out["shift_bins"][:, z] = x[:, 0]
        out["amplitude"][:, z] = np.exp(x[:, 1])
        out["ambient"][:, z] = x[:, 2]
        out["reduced_chi2"][:, z] = chi2
        out["distance_m"][:, z] = model.distance_m(x[:, 0], z)
        out["stderr_m"][:, z] = se * np.sqrt(np.maximum(chi2, 1.0)) / model.bins_per_m[z]
    return out


def ranges_to_json(result, frame_index=None) -> dict:
    """The ``tofjax range --json`` layout: ``{"frames": [{"index": i, "zones": [{"distance_m", "stderr_m"}, ...]}]}``."""
    d, s, c = result["distance_m"], result["stderr_m"], result["reduced_chi2"]
    idx = range(d.shape[0]) if frame_index is None else frame_index
    return {
        "frames": [
            {
                "index": int(i),
                "zones": [
                    {"distance_m": float(d[f, z]), "stderr_m": float(s[f, z]), "reduced_chi2": float(c[f, z])}
                    for z in range(d.shape[1])
                ],
            }
            for f, i in enumerate(idx)
        ]
    }
