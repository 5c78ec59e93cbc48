"""``tofjax sensor fit``: the sensor model from captures of a flat target at known distances.

Per zone, one joint Poisson fit (deviance residuals, Levenberg-Marquardt on dense normal
equations in float64) of the zone's pulse (piecewise linear, ``knots_per_bin`` knots per
bin), its pile-up (effective laser pulses per histogram) and, per frame, the pulse
position, amplitude and ambient floor. The pulse shape and pile-up are shared by every
frame; position, amplitude and floor are what the target sets. The bin width and the time
offset of zero range then come from a straight line through the fitted positions against
the true distances (with standard errors), and, as an independent check, from a line
through the raw peak positions (parabolic interpolation of the highest three bins).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from .response import C_AIR, SensorModelError, SensorResponse, zone_counts

__all__ = ["SensorFitOptions", "fit_sensor", "peak_positions", "line_fit", "poisson_deviance_residuals", "lm_fit"]

SATURATION = float(2**24 - 1)


@dataclass(frozen=True)
class SensorFitOptions:
    """How ``tofjax sensor fit`` fits.

    - ``min_distance_m``, ``max_distance_m``: frames used for the pulse fit (the centre zone
      sees almost nothing below ~20 mm: emitter/detector parallax).
    - ``line_min_distance_m``: the straight line (bin width, zero-range offset) uses frames
      from here to ``max_distance_m``.
    - ``knots_per_bin``, ``pulse_bins``, ``pulse_before_bins``: the learned pulse's knots
      and support (bins after and before its nominal position).
    - ``pile_up``: fit the effective number of laser pulses per histogram (Coates pile-up).
    - ``smoothness``: weight of a curvature penalty on the pulse (0: none): lambda times the
      integral over bins of (pulse'' / max pulse)^2. Without it the learned pulse rings at
      the knot spacing and ranging fits find false minima.
    - ``walk_degree``: degree of the range-walk polynomial (position minus the straight line
      against distance, fitted over every fitted frame); -1: none.
    - ``echo``: model the double bounce (target -> sensor cover -> target) at twice the distance.
    - ``shape_drift``, ``drift_order``: let the pulse's shape change with its position, as a
      polynomial of order ``drift_order`` (one learned shape per order, each with zero area
      and the same curvature penalty; the real sweep's strongest returns need order 2).
    - ``dnl``: also fit each bin's edges (time-to-digital converter non-linearity).
    - ``max_iterations``: Levenberg-Marquardt steps per zone.
    """

    min_distance_m: float = 0.04
    max_distance_m: float = 0.40
    line_min_distance_m: float = 0.10
    knots_per_bin: int = 4
    pulse_bins: float = 36.0
    pulse_before_bins: float = 2.0
    pile_up: bool = True
    smoothness: float = 2000.0
    walk_degree: int = 4
    dnl: bool = False
    shape_drift: bool = True
    drift_order: int = 2
    echo: bool = True
    max_iterations: int = 60

    def __post_init__(self):
        if not 0 <= self.min_distance_m < self.max_distance_m:
            raise SensorModelError(f"min_distance_m, max_distance_m: need 0 <= min < max, got {self.min_distance_m}, {self.max_distance_m}")
        if self.knots_per_bin < 1 or self.pulse_bins <= 2:
            raise SensorModelError("knots_per_bin must be >= 1 and pulse_bins > 2")
        if not 1 <= self.drift_order <= 3:
            raise SensorModelError(f"drift_order must be 1, 2 or 3, got {self.drift_order}")

    @property
    def order(self) -> int:
        """The shape drift's order in effect (0: a fixed shape)."""
        return self.drift_order if self.shape_drift else 0


# ---- statistics ----------------------------------------------------------------------------
def poisson_deviance_residuals(counts, mu):
    """Signed square roots of the Poisson deviance per bin (sum of squares = deviance).

    The double where keeps ``log(0)`` out of the value and the gradient for empty bins.
    """
    mu = jnp.maximum(mu, 1e-12)
    pos = counts > 0
    safe = jnp.where(pos, counts, 1.0)
    dev = 2.0 * (mu - counts + jnp.where(pos, counts * jnp.log(safe / mu), 0.0))
    dev = jnp.maximum(dev, 0.0)
    # sqrt'(0) is infinite: route exact zeros through a safe branch.
    nz = dev > 0
    root = jnp.sqrt(jnp.where(nz, dev, 1.0))
    return jnp.sign(counts - mu) * jnp.where(nz, root, 0.0)


def pearson_chi2(counts, mu, axis=-1):
    """Sum of (counts - mu)^2 / mu (Poisson weights from the model)."""
    mu = np.maximum(np.asarray(mu), 1e-9)
    return np.sum((np.asarray(counts) - mu) ** 2 / mu, axis=axis)


def line_fit(x, y):
    """Least-squares line ``y = a + b x`` with standard errors from the scatter: (a, b, se_a, se_b, rms)."""
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    n = len(x)
    if n < 3 or np.ptp(x) <= 0:
        raise SensorModelError(
            "the bin width cannot be identified: the captures need targets at three or more different distances "
            f"(got {len(np.unique(x))} distinct)"
        )
    X = np.stack([np.ones(n), x], 1)
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    r = y - X @ coef
    s2 = r @ r / (n - 2)
    cov = s2 * np.linalg.inv(X.T @ X)
    return float(coef[0]), float(coef[1]), float(math.sqrt(cov[0, 0])), float(math.sqrt(cov[1, 1])), float(math.sqrt(s2))


def peak_positions(hist):
    """Peak position (bins, centre of bin b = b + 0.5) per histogram by a parabola through the
    log of the three highest bins around the maximum, after removing a floor."""
    h = np.asarray(hist, float)
    floor = np.median(h[..., :8], axis=-1, keepdims=True)
    x = np.maximum(h - floor, 1.0)
    k = np.clip(np.argmax(x, axis=-1), 1, h.shape[-1] - 2)
    take = lambda o: np.log(np.take_along_axis(x, (k + o)[..., None], -1)[..., 0])  # noqa: E731
    a, b, c = take(-1), take(0), take(1)
    den = a - 2 * b + c
    off = np.where(den < 0, 0.5 * (a - c) / np.where(den < 0, den, -1.0), 0.0)
    return k + 0.5 + np.clip(off, -1, 1)


# ---- Levenberg-Marquardt -------------------------------------------------------------------
@functools.partial(jax.jit, static_argnums=0)
def _residual(resid, x, *args):
    """``resid(x, *args)``, compiled once per residual function (and argument shapes)."""
    return resid(x, *args)


@functools.partial(jax.jit, static_argnums=0)
def _jacobian(resid, x, *args):
    """The Jacobian of ``resid`` in ``x`` (forward mode), compiled once per residual function."""
    return jax.jacfwd(resid)(x, *args)


def lm_fit(resid, x0, args, *, max_iterations=60, rtol=1e-10):
    """Minimise ``sum(resid(x, *args)^2)`` by Levenberg-Marquardt on dense normal equations.

    Returns ``(x, cost, J at x, iterations, converged)``. ``resid`` must be jittable; its
    Jacobian is taken in forward mode (the fits here have a few hundred parameters). Both are
    module-level compiled functions taking ``resid`` (static: the same function object, not a
    new closure per call) and the data ``args``: a second fit of new data of the same shapes
    compiles nothing.
    """
    r_fn, j_fn = functools.partial(_residual, resid), functools.partial(_jacobian, resid)
    x = np.asarray(x0, float)
    r = np.asarray(r_fn(x, *args))
    cost = float(r @ r)
    lam = 1e-3
    J = np.asarray(j_fn(x, *args))
    converged = False
    it = 0
    for it in range(1, max_iterations + 1):
        A = J.T @ J
        g = J.T @ r
        d = np.diag(A).copy()
        d[d <= 0] = 1.0
        improved = False
        for _ in range(40):  # up to lam * 4^40: far from the minimum a tiny (gradient) step may be all that helps
            try:
                step = -np.linalg.solve(A + lam * np.diag(d), g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            xn = x + step
            rn = np.asarray(r_fn(xn, *args))
            cn = float(rn @ rn)
            if np.isfinite(cn) and cn <= cost:
                improved = True
                break
            lam *= 4
        if not improved:
            converged = True  # no step lowers the cost: at a minimum (to rounding)
            break
        rel = (cost - cn) / max(cost, 1e-300)
        x, r, cost = xn, rn, cn
        lam = max(lam / 3, 1e-12)
        J = np.asarray(j_fn(x, *args))
        if rel < rtol:
            converged = True
            break
    return x, cost, J, it, converged


# ---- the per-zone joint fit ----------------------------------------------------------------
@functools.lru_cache(maxsize=8)
def _zone_problem(K, F, start, step, n_bins, pile, smooth, dnl, drift=0, echo=False):
    E = n_bins - 1 if dnl else 0
    P0 = K + 1 + 3 * F + E  # where the drift knots start (``drift`` blocks of K: its order)
    Q0 = P0 + K * drift  # where the per-frame echo amplitudes (log) start

    def drift_of(th):
        return th[P0:Q0].reshape(drift, K) if drift else None

    def unpack(th):
        pdf = th[:K]
        logn = th[K]
        shift = th[K + 1 : K + 1 + F]
        loga = th[K + 1 + F : K + 1 + 2 * F]
        amb = th[K + 1 + 2 * F : K + 1 + 3 * F]
        return pdf, logn, shift, loga, amb

    def edges(th):
        if not dnl:
            return None
        inner = jnp.arange(1, n_bins, dtype=th.dtype) + th[K + 1 + 3 * F : K + 1 + 3 * F + E]
        return jnp.concatenate([jnp.zeros((1,), th.dtype), inner, jnp.full((1,), float(n_bins), th.dtype)])

    def model(th, zero_shift):
        pdf, logn, shift, loga, amb = unpack(th)
        area = step * (jnp.sum(pdf) - 0.5 * (pdf[0] + pdf[-1]))
        dr = drift_of(th)
        return zone_counts(pdf / area, start, step, n_bins, shift, jnp.exp(loga), amb, jnp.exp(logn) if pile else None, edges(th),
                           None if dr is None else dr / area, jnp.exp(th[Q0 : Q0 + F]) if echo else None, zero_shift)

    def resid(th, h, w, shift0, zero_shift):
        pdf, logn, shift, *_ = unpack(th)
        r = poisson_deviance_residuals(h, model(th, zero_shift)) * w[:, None]
        area = step * (jnp.sum(pdf) - 0.5 * (pdf[0] + pdf[-1]))
        extra = [
            jnp.atleast_1d(100.0 * (area - 1.0)),  # the pulse's scale belongs to the amplitudes
            jnp.atleast_1d(10.0 * jnp.mean(shift - shift0)),  # its position belongs to the offsets
        ]
        if not pile:
            extra.append(jnp.atleast_1d(logn))
        if smooth > 0:
            # lambda * integral of (pulse'' / max pulse)^2 over bins, on knots ``step`` apart
            extra.append(math.sqrt(smooth / step**3) * jnp.diff(pdf, 2) / jnp.max(jnp.abs(pdf)))
        if drift:
            dr = drift_of(th)
            extra.append(100.0 * step * (jnp.sum(dr, -1) - 0.5 * (dr[:, 0] + dr[:, -1])))  # no area change
            if smooth > 0:
                extra.append((math.sqrt(smooth / step**3) * jnp.diff(dr, 2, axis=-1) / jnp.max(jnp.abs(pdf))).ravel())
        return jnp.concatenate([r.ravel(), *extra])

    return unpack, jax.jit(model), resid, edges


def fit_pulse(hist, shift0, options: SensorFitOptions, n_pulses0=4e6, zero_shift=None):
    """Fit one channel's pulse to many frames (F, B) whose rough positions are ``shift0`` (F,).

    Returns a dict with the pulse, pulses per histogram, per-frame shift/amplitude/ambient with
    standard errors, the model and each frame's reduced chi-square (Pearson).
    """
    h = np.asarray(hist, float)
    F, B = h.shape
    q = options.knots_per_bin
    step = 1.0 / q
    start = -options.pulse_before_bins
    K = int(round(options.pulse_bins * q)) + 1
    u = start + step * np.arange(K)
    amb0 = np.median(np.concatenate([h[:, :6], h[:, -6:]], 1), 1)
    prof = np.zeros(K)
    for f in range(F):
        x = np.maximum(h[f] - amb0[f], 0.0)
        x = x / max(x.sum(), 1.0)
        prof += np.interp(u + shift0[f], np.arange(B) + 0.5, x, left=0, right=0)
    prof = np.maximum(prof / F, 0.0)
    prof /= step * prof.sum()
    a0 = np.log(np.maximum(h.sum(1) - amb0 * B, 10.0))
    unpack, model, resid, edges = _zone_problem(K, F, start, step, B, options.pile_up, options.smoothness, options.dnl,
                                                          options.order, options.echo and zero_shift is not None)
    th0 = np.concatenate([prof, [math.log(n_pulses0)], shift0, a0, amb0, np.zeros(B - 1 if options.dnl else 0),
                          np.zeros(K * options.order), np.log(np.exp(a0) * 1e-3) if options.echo and zero_shift is not None else []])
    w = np.ones(F)
    zs = jnp.asarray(0.0 if zero_shift is None else float(zero_shift))
    th, cost, J, its, conv = lm_fit(resid, th0, (jnp.asarray(h), jnp.asarray(w), jnp.asarray(shift0), zs),
                                max_iterations=options.max_iterations)
    mu = np.asarray(model(jnp.asarray(th), zs))
    pdf, logn, shift, loga, amb = (np.asarray(v) for v in unpack(th))
    area = step * (pdf.sum() - 0.5 * (pdf[0] + pdf[-1]))
    chi2 = pearson_chi2(h, mu) / (B - 3)
    # Covariance of the deviance fit, inflated by the median reduced chi-square when the model
    # does not reach the Poisson floor (an honest error, not the nominal one).
    A = J.T @ J
    cov = np.linalg.pinv(A)
    infl = max(1.0, float(np.median(chi2)))
    se = np.sqrt(np.maximum(np.diag(cov), 0.0) * infl)
    P0 = K + 1 + 3 * F + (B - 1 if options.dnl else 0)
    Q0 = P0 + K * options.order
    return {
        "echo": np.exp(th[Q0 : Q0 + F]) if options.echo and zero_shift is not None else None,
        "drift": th[P0:Q0].reshape(options.order, K) / area if options.order else None,
        "pulse": pdf / area,
        "start": start,
        "step": step,
        "pulses": float(np.exp(logn)) if options.pile_up else None,
        "pulses_se": float(np.exp(logn) * se[K]) if options.pile_up else None,
        "shift": shift,
        "shift_se": se[K + 1 : K + 1 + F],
        "amplitude": np.exp(loga),
        "ambient": amb,
        "model": mu,
        "chi2": chi2,
        "edges": None if not options.dnl else np.asarray(edges(jnp.asarray(th))),
        "iterations": its,
        "converged": conv,
    }


def centroid_offset(pulse, drift, shift, start, step):
    """How far the centroid of the drifted pulse ``P0 + a P1 + a^2 P2 ...`` lies from that of
    ``P0`` (bins; ``a = (shift - 28) / 10``), per frame; zeros without a drift."""
    shift = np.asarray(shift, float)
    if drift is None:
        return np.zeros_like(shift)
    from .response import SHAPE_REF_BINS, SHAPE_SCALE_BINS

    u = start + step * np.arange(len(pulse))
    a = (shift - SHAPE_REF_BINS) / SHAPE_SCALE_BINS
    terms = np.atleast_2d(drift)
    p = pulse[None, :] + sum(a[:, None] ** (k + 1) * terms[k][None, :] for k in range(len(terms)))
    def trap(y):  # the integral over the knots (np.trapezoid is numpy >= 2 only)
        return np.sum(0.5 * (y[..., 1:] + y[..., :-1]), axis=-1) * step

    return trap(u * p) / trap(p) - trap(u * pulse) / trap(pulse)


def _parameter_count(options, F, Z, K, walk, echo):
    """How many numbers the model has: what every capture shares, and what each capture sets."""
    per_zone = {
        "pulse_knots": K,
        "shape_drift_knots": K * options.order,
        "pulses_per_histogram": 1 if options.pile_up else 0,
        "zero_range_and_path_scale": 2,
        "range_walk": options.walk_degree + 1 if walk else 0,
        "echo_law": 2 if echo else 0,
    }
    shared_zone = sum(per_zone.values())
    per_capture_zone = 3 + (1 if echo else 0)  # position, amplitude, floor (+ echo amplitude)
    return {
        "shared_per_zone": per_zone,
        "shared_per_zone_total": shared_zone,
        "shared_total": shared_zone * Z,
        "per_capture_per_zone": per_capture_zone,
        "per_capture_total": per_capture_zone * Z,
        "fitted_total": (shared_zone + per_capture_zone * F) * Z,
        "note": "the pulse knots are tied by a curvature penalty (fewer effective degrees of freedom); the reference "
                "channel's own pulse is not counted",
    }


def _drift_array(terms):
    """Per-zone drift terms (order, K) -> the model's ``pulse_drift``: (Z, K) for first order (the
    layout older files have), (Z, order, K) above."""
    a = np.stack(terms)
    return a[:, 0] if a.shape[1] == 1 else a


def fit_sensor(histograms, distances_m, options: SensorFitOptions = SensorFitOptions(), *, reference=None,
               grid: tuple[int, int] | None = None, progress=None) -> tuple[SensorResponse, dict]:
    """Fit the sensor model to captures of a flat target at known distances.

    **Arguments:**

    - ``histograms``: (frames, zones, bins) counts (one sensor).
    - ``distances_m``: (frames,) true target distance per frame.
    - ``reference``: (frames, bins) reference-channel histograms, optional.
    - ``grid``: the zone grid (rows, cols); default square.

    **Returns:** ``(model, details)``: the :class:`SensorResponse` (its ``report`` holds the
    values with standard errors and each frame's reduced chi-square) and per-frame arrays
    (model histograms, fitted positions) for plots.
    """
    h = np.asarray(histograms, float)
    d = np.asarray(distances_m, float)
    if h.ndim != 3 or d.shape != (h.shape[0],):
        raise SensorModelError(f"need histograms (frames, zones, bins) and one distance per frame, got {h.shape} and {d.shape}")
    if not np.all(np.isfinite(d)):
        raise SensorModelError("some frames have no ground-truth distance (truth/target_distance_m is NaN): a sensor fit needs it for every frame")
    F, Z, B = h.shape
    if grid is None:
        r = int(round(math.sqrt(Z)))
        grid = (r, Z // r) if r * (Z // r) == Z else (1, Z)
    sat = np.any(h >= SATURATION, axis=(1, 2))
    sel = (d >= options.min_distance_m - 1e-9) & (d <= options.max_distance_m + 1e-9) & ~sat
    if sat.any():
        import warnings

        from .importer import DroppedFramesWarning

        warnings.warn(f"frames {', '.join(map(str, np.flatnonzero(sat)))} have saturated bins (>= 2^24-1): left out of the fit",
                      DroppedFramesWarning, stacklevel=2)
    if len(np.unique(np.round(d[sel], 6))) < 3:
        raise SensorModelError(
            f"the bin width cannot be identified: {len(np.unique(np.round(d[sel], 6)))} distinct target distance(s) in "
            f"[{options.min_distance_m:g}, {options.max_distance_m:g}] m; a sensor fit needs a sweep over three or more"
        )
    idx = np.flatnonzero(sel)
    hs, ds = h[idx], d[idx]
    line_sel = ds >= options.line_min_distance_m - 1e-9
    if len(np.unique(np.round(ds[line_sel], 6))) < 3:
        line_sel = np.ones_like(ds, bool)
    peaks = peak_positions(hs)  # (F, Z)
    zones = []
    for z in range(Z):
        a, b, *_ = line_fit(ds, peaks[:, z])
        shift0 = a + b * ds
        res = fit_pulse(hs[:, z], shift0, options, zero_shift=a)
        # With a shape drift the pulse's origin is not a time (a drift term can move the pulse as
        # well as reshape it): the line goes through each frame's pulse centroid instead.
        pos = res["shift"] + centroid_offset(res["pulse"], res["drift"], res["shift"], res["start"], res["step"])
        t0, slope, t0_se, slope_se, rms = line_fit(ds[line_sel], pos[line_sel])
        if z == (grid[0] // 2) * grid[1] + grid[1] // 2:
            origin_slope = line_fit(ds[line_sel], res["shift"][line_sel])[1]
        pa, pb, pa_se, pb_se, prms = line_fit(ds[line_sel], peaks[line_sel, z])
        gain = res["amplitude"] * ds**2
        walk = None
        if options.walk_degree >= 0 and len(np.unique(ds)) > options.walk_degree + 2:
            walk = np.polyfit(ds, res["shift"] - (t0 + slope * ds), options.walk_degree)
        res["walk"] = walk
        echo_law = None
        if res["echo"] is not None:  # the echo's ratio to the first return as a power law of distance
            ratio = np.maximum(res["echo"] / res["amplitude"], 1e-9)
            pw, lc = np.polyfit(np.log(ds / 0.2), np.log(ratio), 1)
            echo_law = (float(np.exp(lc)), float(pw))
        zones.append((res, t0, slope, t0_se, slope_se, rms, pa, pb, pa_se, pb_se, prms, gain, None, echo_law))
        if progress:
            progress(f"zone {z}: pulse fit {res['iterations']} steps, median reduced chi2 {np.median(res['chi2']):.2f}")
    centre = (grid[0] // 2) * grid[1] + grid[1] // 2
    slope_c, slope_c_se = zones[centre][2], zones[centre][4]
    w = 2.0 / (C_AIR * slope_c)
    w_se = w * slope_c_se / slope_c
    peak_slope, peak_slope_se = zones[centre][7], zones[centre][9]
    w_peak = 2.0 / (C_AIR * peak_slope)
    mu = np.stack([zr[0]["model"] for zr in zones], 1)  # (F, Z, B)
    frame_chi2 = pearson_chi2(hs, mu).sum(-1) / (Z * (B - 3))
    ref = None
    if reference is not None:
        rh = np.asarray(reference, float)[idx]
        rp = peak_positions(rh)
        # The reference pulse's tail runs to the end of the histogram (light inside the package):
        # give it the whole range after its peak, on coarser knots.
        span = float(B - np.ceil(np.median(rp)) - 1 - options.pulse_before_bins)
        ropts = dataclasses.replace(options, dnl=False, pulse_bins=max(span, 8.0), knots_per_bin=min(options.knots_per_bin, 4))
        ref = fit_pulse(rh, np.full(len(rh), np.median(rp)), dataclasses.replace(ropts, shape_drift=False))
        if progress:
            progress(f"reference: median reduced chi2 {np.median(ref['chi2']):.2f}")
    Zs = range(Z)
    report = {
        "bin_width_s": w,
        "bin_width_se_s": w_se,
        "bin_width_from_peak_line_s": w_peak,
        "bin_width_from_peak_line_se_s": w_peak * peak_slope_se / peak_slope,
        "bin_width_relative_difference": w / w_peak - 1.0,
        # the same line through the pulse's origin instead of its centroid (they differ with a shape drift)
        "bin_width_from_pulse_origin_s": 2.0 / (C_AIR * origin_slope),
        "centre_zone": centre,
        "line_distances_m": [float(ds[line_sel].min()), float(ds[line_sel].max())],
        "zero_range_s": None,  # filled below from the model (the pulse peak at zero range)
        "zero_range_se_s": [zones[z][3] * w for z in Zs],
        "bins_per_m": [zones[z][2] for z in Zs],
        "bins_per_m_se": [zones[z][4] for z in Zs],
        "path_scale": [zones[z][2] / slope_c for z in Zs],
        "line_rms_m": [zones[z][5] / zones[z][2] for z in Zs],
        "pulses_per_histogram": [zones[z][0]["pulses"] for z in Zs],
        "pulses_per_histogram_se": [zones[z][0]["pulses_se"] for z in Zs],
        "gain_m2": [float(np.median(zones[z][11])) for z in Zs],
        "frames": [int(i) for i in idx],
        "distances_m": ds.tolist(),
        "frame_reduced_chi2": frame_chi2.tolist(),
        "median_reduced_chi2": float(np.median(frame_chi2)),
        "zone_median_reduced_chi2": [float(np.median(zones[z][0]["chi2"])) for z in Zs],
        "converged": all(zr[0]["converged"] for zr in zones),
        "reference_median_reduced_chi2": None if ref is None else float(np.median(ref["chi2"])),
        "options": {k: getattr(options, k) for k in options.__dataclass_fields__},
        "parameters": _parameter_count(options, len(idx), Z, zones[0][0]["pulse"].shape[0], zones[0][0]["walk"] is not None,
                                       zones[0][0]["echo"] is not None),
    }
    model = SensorResponse(
        bin_width_s=w,
        n_bins=B,
        grid=tuple(grid),
        zero_range_bins=np.array([zones[z][1] for z in Zs]),
        bins_per_m=np.array([zones[z][2] for z in Zs]),
        pulse=np.stack([zones[z][0]["pulse"] for z in Zs]),
        pulse_start_bins=zones[0][0]["start"],
        pulse_step_bins=zones[0][0]["step"],
        pulses_per_histogram=np.array([zones[z][0]["pulses"] for z in Zs]) if options.pile_up else None,
        echo_ratio=None if zones[0][0]["echo"] is None else np.array([zones[z][13][0] for z in Zs]),
        echo_power=None if zones[0][0]["echo"] is None else np.array([zones[z][13][1] for z in Zs]),
        pulse_drift=_drift_array([zones[z][0]["drift"] for z in Zs]) if options.order else None,
        walk_coeffs=None if zones[0][0]["walk"] is None else np.stack([zones[z][0]["walk"] for z in Zs]),
        gain_m2=np.array(report["gain_m2"]),
        ambient_counts=np.array([float(np.median(zones[z][0]["ambient"])) for z in Zs]),
        reference_pulse=None if ref is None else ref["pulse"],
        reference_shift_bins=None if ref is None else float(np.median(ref["shift"])),
        reference_counts=None if ref is None else float(np.median(ref["amplitude"])),
        reference_pulse_step_bins=None if ref is None else float(ref["step"]),
        report=report,
    )
    report["zero_range_s"] = model.zero_range_s().tolist()
    details = {
        "frames": idx,
        "distances_m": ds,
        "histograms": hs,
        "model": mu,
        "shift": np.stack([zr[0]["shift"] for zr in zones], 1),
        "peaks": peaks,
        "zone_chi2": np.stack([zr[0]["chi2"] for zr in zones], 1),
        "reference": ref,
    }
    return model, details
