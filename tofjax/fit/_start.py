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

from ..compile_cache import call_stored
from ..model import SPEED_OF_LIGHT_M_PER_S, Geometry, Params
from ..scene import Scene
from ._problem import CalibrationProblem

__all__ = ["edge_estimates", "timing_start", "envelope_grid", "envelope_candidates", "basin_order", "ENVELOPE_MU_T", "ENVELOPE_N1"]

#: Extinction grid of the envelope stage, 1/m (log-spaced, 0.01 to 30 /m).
ENVELOPE_MU_T = tuple(float(x) for x in np.geomspace(0.01, 30.0, 19))
#: Where a fit with a free light-entry width (``Params.crosstalk_width_s``) starts it, in bins,
#: when the scene states none (the prior stays centred on the scene's 0).
LIGHT_ENTRY_WIDTH_START = 0.2
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
def _model_at(problem, params):
    """The problem's model at ``params`` (the problem, not its model, is the argument: its switches key the program)."""
    return problem.model(params)


def _stored(name: str, fn, args):
    """``fn(*args)`` (one array out) through the program store, as the fit itself: a new process
    with the store on reads the traced start stages from disk instead of tracing them again."""
    return call_stored(name, fn, args, to_plain=lambda x: x, from_plain=lambda plain, _: plain)


def timing_start(problem: CalibrationProblem, data: np.ndarray, frames: int, scene: Scene, base: Params):
    """Step 1: emission time, ambient and n1 from the data's timing; returns the start and
    whether n1 came from the data (an edge return was seen).

    The same estimators run on the model at ``base`` first; their offsets from ``base``
    (the estimators' bias: a pulse's peak is not its mean) are taken out of the estimates."""
    tau = float(base.pulse_tail_s)
    ref = np.asarray(_stored("calibration timing reference", _model_at, (problem, base)), np.float64)
    ref_t_e, _, ref_n1 = edge_estimates(ref, frames, scene, tau)
    t_e, ambient, n1 = edge_estimates(np.asarray(data, np.float64), frames, scene, tau)
    t_e = max(t_e + float(base.emission_time_s) - ref_t_e, 0.0)
    if n1 is not None and ref_n1 is not None:
        n1 = n1 + float(base.n1) - ref_n1
    found = n1 is not None
    n1 = float(base.n1) if n1 is None else float(np.clip(n1, 1.05, 3.5))
    dt = base.n1.dtype
    # NumPy values of the pytree's dtype: replacing with Python floats compiles a small program in every new process
    start = base.replace(
        emission_time_s=np.asarray(t_e, dt),
        ambient_counts=np.maximum(ambient, 0.1),
        n1=np.asarray(n1, dt),
        mu_s_per_m=np.asarray(max(float(base.mu_s_per_m), 1e-3), dt),
        mu_a_per_m=np.asarray(max(float(base.mu_a_per_m), 1e-3), dt),
    )
    if "crosstalk_width_s" in problem.nonlinear and float(base.crosstalk_width_s) < LIGHT_ENTRY_WIDTH_START * scene.sensor.bin_width_s:
        # a width far below the pulse's barely changes the peak (it adds in quadrature): no
        # gradient to leave from; the fit starts at a fifth of a bin and may go back to ~0
        start = start.replace(crosstalk_width_s=np.asarray(LIGHT_ENTRY_WIDTH_START * scene.sensor.bin_width_s, dt))
    return start, found


@eqx.filter_jit
def envelope_grid(problem: CalibrationProblem, start: Params, data, sigma, n1, mu_t):
    """Step 2: profiled chi-square on the grid ``n1`` (N,) x ``mu_t`` (M,), returned (N, M), the
    albedo and everything else held at ``start``; one compiled call of two nested vmaps, so what
    depends on n1 alone (the node integrals of the near field, the rays past the far edge) is
    computed once per n1, not once per grid point."""
    albedo = start.mu_s_per_m / (start.mu_s_per_m + start.mu_a_per_m)

    def chi2(n, mt):
        p = start.replace(n1=n, mu_s_per_m=mt * albedo, mu_a_per_m=mt * (1.0 - albedo))
        if problem.linear:
            _, m, _, _ = problem.profile(p, data, sigma)
        else:
            m = problem.model(p)
        c = jnp.sum(((m - data) / sigma) ** 2)
        return jnp.where(jnp.isfinite(c), c, jnp.inf)

    return jax.vmap(lambda n: jax.vmap(lambda mt: chi2(n, mt))(mu_t))(n1)


def envelope_candidates(problem: CalibrationProblem, start: Params, data, sigma, count: int, with_basins: bool = False):
    """The ``count`` best starts of :func:`envelope_grid`, best first: the grid's best point,
    then the best point of every other basin along mu_t (the local minima of the chi-square
    profiled over n1, by chi-square), then the best remaining extinctions.

    A restart from a neighbour of the first start ends in the same basin; a strongly
    attenuating guide can have a second basin at low mu_t (the distributed backscatter's decay
    read as a weak attenuation with other pulse and edge parameters) that the best grid
    point falls into, so the restarts go to the other basins first. With ``with_basins``:
    ``(starts, b)``, the first ``b`` starts being the best point of a basin each.

    The two ends of the grid never count as a basin's minimum here (a profile still falling
    at 30 /m is the light-entry peak alone, not a guide)."""
    n1_0 = float(start.n1)
    n_axis = np.asarray([n1_0 * (1 + dn) for dn in ENVELOPE_N1])
    m_axis = np.asarray(ENVELOPE_MU_T)
    dt = start.n1.dtype
    chi = np.asarray(_stored("calibration envelope grid", envelope_grid,
                             (problem, start, data, sigma, jnp.asarray(n_axis, dt), jnp.asarray(m_axis, dt))))
    # the sum in NumPy (same dtype, same rounding): a JAX add would compile a small program in a new process
    albedo = float(start.mu_s_per_m) / float(np.asarray(start.mu_s_per_m) + np.asarray(start.mu_a_per_m))
    order, n_basins = basin_order(chi)
    out = []
    for j, i in order[:count]:
        out.append(start.replace(n1=np.asarray(n_axis[j], dt), mu_s_per_m=np.asarray(m_axis[i] * albedo, dt),
                                 mu_a_per_m=np.asarray(m_axis[i] * (1 - albedo), dt)))  # arrays: no small program to compile
    if with_basins:
        return (out or [start]), max(min(n_basins, len(out)), 1)
    return out or [start]


def basin_order(chi: np.ndarray) -> list[tuple[int, int]]:
    """``(n1 index, mu_t index)`` of the starts in the order :func:`envelope_candidates` tries
    them, from a chi-square grid (n1 offsets, mu_t), and how many of them are basins: one per
    extinction (its best n1); the best point, then the other interior local minima along mu_t
    (by chi-square), then the rest by chi-square; non-finite points are left out."""
    chi = np.where(np.isfinite(chi), chi, np.inf)
    j_best = np.argmin(chi, axis=0)  # best n1 offset per extinction
    prof = chi[j_best, np.arange(chi.shape[1])]
    M = len(prof)
    best = int(np.argmin(prof))
    minima = [i for i in range(1, M - 1) if np.isfinite(prof[i]) and prof[i] <= prof[i - 1] and prof[i] <= prof[i + 1]]
    minima = [best] + sorted((i for i in minima if i != best), key=lambda i: prof[i])
    rest = sorted((i for i in range(M) if np.isfinite(prof[i]) and i not in minima), key=lambda i: prof[i])
    if not np.isfinite(prof[best]):
        return [], 0
    return [(int(j_best[i]), int(i)) for i in minima + rest], len(minima)
