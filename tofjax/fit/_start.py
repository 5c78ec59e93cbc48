"""Where a calibration starts: timing first, then the envelope, then the joint fit.

1. **Timing.** The emission time from the light-entry peak, ambient from the bins before
   it, and n1 from the time of each zone's far-edge return and the known distance to the
   edge (:func:`edge_estimates`). Times do not depend on gains, pulse amplitudes or
   crosstalk, so a model that gets amplitudes wrong still starts at the right n1.
2. **Envelope.** The extinction ``mu_s + mu_a`` (and n1 within a few per cent of the timing
   estimate) from a grid of profiled chi-squares: each grid point is the model's decay
   envelope with every linear parameter at its best, all points in one compiled call
   (:func:`envelope_grid`).
3. The joint fit starts from the best grid point; the next best are the restarts.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..model import SPEED_OF_LIGHT_M_PER_S, Geometry, Params
from ..scene import Scene
from ._problem import CalibrationProblem

__all__ = ["edge_estimates", "timing_start", "envelope_grid", "ENVELOPE_MU_T", "ENVELOPE_N1"]

#: Extinction grid of the envelope stage, 1/m (log-spaced, 0.01 to 30 /m).
ENVELOPE_MU_T = tuple(float(x) for x in np.geomspace(0.01, 30.0, 19))
#: Relative n1 offsets around the timing estimate tried by the envelope stage.
ENVELOPE_N1 = (-0.03, -0.015, 0.0, 0.015, 0.03)


def mean_ray_length(scene: Scene) -> np.ndarray:
    """Mean far-edge distance of each zone's rays (S, Z)."""
    geom = Geometry.from_scene(scene, 8, np.float64)
    return np.asarray(geom.ray_length).mean(-1)


def edge_estimates(d: np.ndarray, frames: int, scene: Scene, tau: float):
    """Emission time, ambient per zone and n1 read off mean histograms ``d`` (S, Z, B):
    the light-entry peak's centroid, the bins before it, and the time of the far-edge bump
    of each zone (weighted median over zones); ``n1`` is None when no zone shows the bump."""
    sm = scene.sensor
    S, Z, B = d.shape
    width = sm.bin_width_s
    total = d.sum(axis=(0, 1))
    early = max(4, B // 3)
    peak = int(np.argmax(total[:early]))
    lo, hi = max(peak - 2, 0), min(peak + 3, B)
    pre = max(peak - 4, 0)
    if pre >= 3:
        ambient = np.median(d[..., :pre], axis=-1)
    else:
        ambient = np.median(d[..., -max(B // 10, 3) :], axis=-1)
    w = np.clip(total[lo:hi] - ambient.sum(), 0, None)
    centre = (np.sum(w * (np.arange(lo, hi) + 0.5)) / max(w.sum(), 1e-12)) * width
    t_e = max(centre - tau, 0.0)
    # n1: the far-edge bump of each zone, where counts rise again after the decay
    length = mean_ray_length(scene)  # (S, Z)
    c = SPEED_OF_LIGHT_M_PER_S
    a = ((t_e + 2 * length * 1.0 / c) / width).astype(int) + 1
    b = np.minimum(((t_e + 2 * length * 3.5 / c) / width).astype(int) + 3, B - 1)
    x = d - ambient[..., None]
    pad = np.concatenate([np.full((S, Z, 4), np.inf), x], axis=-1)
    before = np.min(np.stack([pad[..., k : k + B] for k in range(4)]), axis=0)
    rise = x - before
    idx = np.arange(B)
    window = (idx >= a[..., None]) & (idx < b[..., None]) & (length[..., None] > 0) & ((b - a)[..., None] >= 3)
    rise = np.where(window & np.isfinite(rise), rise, -np.inf)
    i = np.argmax(rise, axis=-1)
    best = np.take_along_axis(rise, i[..., None], -1)[..., 0]
    noise = np.sqrt(np.maximum(np.take_along_axis(d, i[..., None], -1)[..., 0], 1.0) / frames)
    ok = np.isfinite(best) & (best >= 5 * noise)
    if not ok.any():
        return t_e, ambient, None
    base_level = np.take_along_axis(before, i[..., None], -1)[..., 0]
    j = np.clip(i[..., None] + np.arange(-1, 2), 0, B - 1)
    valid = (i[..., None] + np.arange(-1, 2) >= 0) & (i[..., None] + np.arange(-1, 2) < B)
    ww = np.where(valid, np.clip(np.take_along_axis(x, j, -1) - base_level[..., None], 0, None), 0.0)
    t_peak = np.sum(ww * (j + 0.5), -1) / np.maximum(ww.sum(-1), 1e-12) * width
    est = c * (t_peak - t_e - tau) / (2 * np.where(length > 0, length, 1.0))
    estimates, weights = est[ok], best[ok]
    order = np.argsort(estimates)
    cum = np.cumsum(weights[order])
    n1 = float(estimates[order][np.searchsorted(cum, cum[-1] / 2)])
    return t_e, ambient, n1


@eqx.filter_jit
def _model_at(model, params):
    return model(params)


def timing_start(problem: CalibrationProblem, data: np.ndarray, frames: int, scene: Scene, base: Params):
    """Step 1: emission time, ambient and n1 from the data's timing; returns the start and
    whether n1 came from the data (an edge return was seen).

    The same estimators run on the model at ``base`` first; their offsets from ``base``
    (the estimators' bias: a pulse's peak is not its mean) are taken out of the estimates."""
    tau = float(base.pulse_tail_s)
    ref = np.asarray(_model_at(problem.model, base), np.float64)
    ref_t_e, _, ref_n1 = edge_estimates(ref, frames, scene, tau)
    t_e, ambient, n1 = edge_estimates(np.asarray(data, np.float64), frames, scene, tau)
    t_e = max(t_e + float(base.emission_time_s) - ref_t_e, 0.0)
    if n1 is not None and ref_n1 is not None:
        n1 = n1 + float(base.n1) - ref_n1
    found = n1 is not None
    n1 = float(base.n1) if n1 is None else float(np.clip(n1, 1.05, 3.5))
    start = base.replace(
        emission_time_s=t_e,
        ambient_counts=np.maximum(ambient, 0.1),
        n1=n1,
        mu_s_per_m=max(float(base.mu_s_per_m), 1e-3),
        mu_a_per_m=max(float(base.mu_a_per_m), 1e-3),
    )
    return start, found


@eqx.filter_jit
def envelope_grid(problem: CalibrationProblem, start: Params, data, sigma, n1, mu_t):
    """Step 2: profiled chi-square at every (n1, mu_t) pair (flat arrays of equal length),
    the albedo and everything else held at ``start``; one compiled, vmapped call."""
    albedo = start.mu_s_per_m / (start.mu_s_per_m + start.mu_a_per_m)

    def chi2(n, mt):
        p = start.replace(n1=n, mu_s_per_m=mt * albedo, mu_a_per_m=mt * (1.0 - albedo))
        if problem.linear:
            _, m, _, _ = problem.profile(p, data, sigma)
        else:
            m = problem.model(p)
        c = jnp.sum(((m - data) / sigma) ** 2)
        return jnp.where(jnp.isfinite(c), c, jnp.inf)

    return jax.vmap(chi2)(n1, mu_t)


def envelope_candidates(problem: CalibrationProblem, start: Params, data, sigma, count: int) -> list[Params]:
    """The ``count`` best grid points of :func:`envelope_grid`, best first, as starts (with
    distinct extinctions, so a restart is a different basin, not a neighbour)."""
    n1_0 = float(start.n1)
    grid = [(n1_0 * (1 + dn), mt) for dn in ENVELOPE_N1 for mt in ENVELOPE_MU_T]
    n = np.asarray([g[0] for g in grid])
    m = np.asarray([g[1] for g in grid])
    dt = start.n1.dtype
    chi = np.asarray(envelope_grid(problem, start, data, sigma, jnp.asarray(n, dt), jnp.asarray(m, dt)))
    albedo = float(start.mu_s_per_m) / float(start.mu_s_per_m + start.mu_a_per_m)
    out, used = [], set()
    for i in np.argsort(chi):
        if not np.isfinite(chi[i]) or m[i] in used:
            continue
        used.add(m[i])
        out.append(start.replace(n1=n[i], mu_s_per_m=m[i] * albedo, mu_a_per_m=m[i] * (1 - albedo)))
        if len(out) == count:
            break
    return out or [start]
