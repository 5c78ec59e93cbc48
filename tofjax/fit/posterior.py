"""Posterior of the calibration parameters: one log-density, two samplers.

:func:`log_density` is the posterior both samplers draw from (emcee here,
:func:`tofjax.fit.nuts.sample_nuts` with NUTS). Its coordinates are the nonlinear
parameters (n1, mu_s, mu_a, pulse, emission time, reflectances) in the fit's
unconstrained space (:mod:`tofjax.fit.transforms`; mu_s and mu_a as log extinction and
logit albedo). The linear ones (gain, light-entry and ambient counts) never reach the
sampler: they are integrated out analytically. Their prior:

- **gain** (per zone with ``zone_gain``, else per sensor): log-uniform (``p(g) ~ 1/g`` on a
  wide range ``[g_lo, g_hi]``, proper), the scale-invariant prior of a scale. With a flat
  prior instead, the marginal carries ``-log ||R||`` per zone (``R`` the model per unit
  gain): an arbitrary prior on the nonlinear parameters (it depends on how ``R`` is
  normalised) that on the default baseline's 42 zones pulls by 3.9 nats per Laplace
  standard error along the ridge where albedo, end reflectance and interface backscatter
  trade against the gain (``GAIN_PRIOR``; README "Posterior speed").
- **crosstalk and ambient counts**: uniform on a wide range (they are locations).

For the Gaussian (Poisson-weighted) likelihood the integral over the linear parameters
``c`` is then ``exp(-chi2_min / 2) (2 pi)^(k/2) det(A^T W A)^(-1/2) p(c*)``: the log-density
adds ``-1/2 log det(A^T W A) - sum log g*`` to the profiled log-likelihood. Exact for the
flat parts (the range's edges, and the non-negativity of the counts, are many standard
errors away: the profiled values are used); for the ``1/g`` factor the error is of the
order of ``(sd(g) / g)^2``, about 1e-6 on the baselines (each zone's gain is pinned to
0.1%). The rest is the fit's own objective: the same noise (photon noise and
``model_error``), the fit config's weak Gaussian prior in the unconstrained space, and the
timing anchor on n1 where the fit had one.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import emcee
import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np

from ..capture import Capture
from ._start import timing_start
from ._laplace import normal_covariance
from .calibrate import CalibrationError, CalibrationResult, Calibrator, _anchor, _data, scene_fingerprint
from .transforms import FITTABLE

__all__ = ["GAIN_PRIOR", "GAIN_PRIORS", "HELD", "HELD_SLOW_TAIL", "LogDensity", "PosteriorOptions", "PosteriorResult", "log_density", "posterior_mode",
           "sample_posterior", "summarise"]


#: Nuisance parameters the default baseline barely identifies: with only the fit's weak prior
#: (width 3 in the unconstrained space, i.e. a factor of 20 either way) they and the albedo
#: slide together along a thin curved ridge that no sampler crosses in reasonable time.
NUISANCE = ("interface_backscatter_per_m", "end_reflectance", "multiple_scattering", "volume_backscatter_fraction", "near_field_m")
#: Default width of their prior in the unconstrained space (log or logit): 0.3, i.e. +-35%
#: (one sigma) for a positive one, 0.43-0.57 for a reflectance at 0.5. Wider (1.0) still
#: leaves R-hat at 1.4-1.8 after 4 x 200 NUTS draws on the 3-sensor scene (docs/calibration.md).
NUISANCE_WIDTH = 0.3
#: Coordinates held at the point fit by default (the posterior is conditional on them): the
#: slow tail of the two-tail pulse. Where the data have no slow tail (every simulated
#: baseline of tofjax's own simulator), its share and time constant are not identified
#: together: with the share near zero the time constant is free, and with a time constant of
#: 10^5 bins the slow tail is a constant the gain absorbs. NUTS draws then wander along that
#: plateau to the edge of the fit's weak prior (slow tail at e^12 bins, 16 Laplace standard
#: errors from the fit), the Laplace whitening is off by a factor of 8 in the fast tail, and
#: the adapted step size collapses. They correlate with n1 and mu_s + mu_a by less than 0.1.
#: And the light-entry width (``crosstalk_width_s``, a sigmoid coordinate capped at two bins):
#: where the light-entry peak is as narrow as the pulse (every baseline of tofjax's own
#: simulator states 0), the data bound it only from above. On the default baseline the
#: log-density is flat within 0.4 nats from 0.07 to 1.3 ps (the draws there are the fit's weak
#: prior, not the data) and falls as ``exp(4 u)`` beyond (2.6 nats at 3.6 ps, 122 at 9.5 ps): its
#: curvature grows 6-7 fold per 0.5 in the coordinate, and at the draws that reach that wall the
#: Hessian's largest eigenvalue in the draws' metric was up to 420 (median draw 4.4), where a
#: leapfrog step above 0.1 diverges: most of the NUTS divergences (70 in 4 x 1000 draws).
#: Its draws correlated with n1, extinction and albedo by less than 0.02 and with the pulse
#: width by -0.15 (experiments/posterior_geometry.py, docs/calibration.md). For a
#: capture whose light-entry peak is resolved, sample it: ``hold=HELD_SLOW_TAIL``.
#: And the near field's shape (``near_field_shape``, free in the point fit since the session of
#: 2026-11-26): its sigmoid coordinate on (1, 65) has walls of its own, and every sampler figure
#: (ESS, divergences, coverage) was measured without it; held until a run shows it samples cleanly.
HELD_SLOW_TAIL = ("pulse_slow_weight", "pulse_slow_tail_s")
HELD = (*HELD_SLOW_TAIL, "crosstalk_width_s", "near_field_shape")
#: Prior of the profiled gains: "log-uniform" (default, ``p(g) ~ 1/g``) or "flat" (before
#: issue 16's rework; its volume term ``-log ||R||`` per zone moved the posterior's bulk
#: away from the fit along the ridge).
GAIN_PRIORS = ("log-uniform", "flat")
GAIN_PRIOR = "log-uniform"
#: Fractions (in [0, 1], logit in the fit's space) that the samplers see as ``w`` with
#: ``log p = -softplus(-STEEP w) / STEEP``: ``w = log p`` away from p = 1, smoothly bounded
#: there. Along the ridge the posterior is straight in (log albedo, log end reflectance, log
#: interface backscatter), all three moving together against the gain (NUTS draws on the
#: default baseline: the quadratic part of one against another is -0.02 to 0.00 in log and
#: -0.14 to -0.07 in logit, where the ridge's width is ~0.23 of its length): the logit curves
#: it into a banana that needs a step size a tenth of the ridge's length.
LOG_FRACTIONS = ("albedo", "end_reflectance")
STEEP = 30.0


def _to_fit(flat, idx):
    """The fit's coordinates (logit) of the samplers' ``flat`` (``idx``: the flat indices of the
    :data:`LOG_FRACTIONS` there) and ``log |d fit / d sampler|``."""
    flat = jnp.asarray(flat)
    if not idx:
        return flat, jnp.zeros((), flat.dtype)
    ii = jnp.asarray(idx)
    w = flat[ii]
    v = -jax.nn.softplus(-STEEP * w) / STEEP  # log p < 0
    one_minus = -jnp.expm1(v)
    u = v - jnp.log(one_minus)
    log_jac = jnp.sum(-jnp.log(one_minus) + jax.nn.log_sigmoid(-STEEP * w))
    return flat.at[ii].set(u), log_jac


def _to_sampler_np(flat, idx):
    """Inverse of :func:`_to_fit` (NumPy): logit p -> w."""
    out = np.array(flat, np.float64, copy=True)
    if idx:
        u = out[..., list(idx)]
        v = -np.logaddexp(0.0, -u)  # log sigmoid(u) = log p
        out[..., list(idx)] = -np.log(np.expm1(-STEEP * v)) / STEEP
    return out


def log_prob(problem, template, args, flat, idx=()):
    """:func:`log_prob_fit` at the samplers' coordinates ``flat`` (``idx``: the
    :data:`LOG_FRACTIONS`' flat indices, sampled as ``w``), with the change of variables'
    log Jacobian: the same posterior, in coordinates where its ridge is straight."""
    u, log_jac = _to_fit(flat, idx)
    return log_prob_fit(problem, template, args, u) + log_jac


def log_prob_fit(problem, template, args, flat):
    """The log posterior at the flat coordinates ``flat`` (module-level, so one compiled
    program serves every capture of the same shape). ``template``: the coordinates' pytree
    (gives the flat order); ``args = (base, data, sigma, prior, widths, held, log_gain)``: the
    fit's residuals' arguments, the nuisance prior's widths, the coordinates held fixed and
    1.0 for the log-uniform gain prior (0.0: flat)."""
    base, data, sigma, prior, widths, held, log_gain = args
    _, unravel = jax.flatten_util.ravel_pytree(template)
    u = {**held, **unravel(flat)}
    params = problem.unpack(u, base)
    if problem.linear:
        _, m, logdet, lin = problem.profile(params, data, sigma)
        if "gain" in lin:  # the log-uniform prior's 1/g at the profiled gains
            g = lin["gain"]
            logdet = logdet + 2.0 * log_gain * jnp.sum(jnp.log(jnp.where(g > 0, g, jnp.nan)))
    else:
        m, logdet = problem.model(params), 0.0
    r = (m - data) / sigma
    lp = -0.5 * jnp.sum(r**2) - 0.5 * logdet - 0.5 * jnp.sum(problem.prior_residuals(u, prior) ** 2)
    for k, w in widths.items():  # the nuisance prior, on top of the fit's weak one
        lp = lp - 0.5 * jnp.sum(((u[k] - prior[k]) / w) ** 2)
    return jnp.where(jnp.isfinite(lp), lp, -jnp.inf)


_log_prob_batch = eqx.filter_jit(eqx.filter_vmap(log_prob, in_axes=(None, None, None, 0, None)))


@eqx.filter_jit
def _jtj_flat(problem, template, fit_args, held, flat):
    """``J^T J`` of the fit's residuals (``fit_args``: weak prior and timing anchor included) over
    the sampled coordinates, the ``held`` ones at their values; the nuisance prior is added by
    the caller (so one compiled program serves every nuisance width)."""
    _, unravel = jax.flatten_util.ravel_pytree(template)
    jac = jax.jacfwd(lambda f: problem.residuals({**held, **unravel(f)}, fit_args))(flat)
    return jac.T @ jac


@eqx.filter_jit
def _to_physical_batch(problem, template, flats, idx=()):
    _, unravel = jax.flatten_util.ravel_pytree(template)

    def one(f):
        x = problem.physical(unravel(_to_fit(f, idx)[0]))  # the sampled coordinates only
        return jnp.concatenate([jnp.ravel(x[k]) for k in sorted(x)])

    return jax.vmap(one)(flats)


@dataclass(frozen=True)
class LogDensity:
    """The calibration posterior in the samplers' flat coordinates.

    - ``problem``, ``template`` (the coordinates' pytree at the fit), ``args`` (data, noise,
      prior): :func:`log_prob`'s arguments; :meth:`fn` is it with them bound.
    - ``idx``: the flat indices of the :data:`LOG_FRACTIONS` (sampled as ``w``, see there;
      every other coordinate is the fit's own); :meth:`to_fit` maps back.
    - ``flat0``: the point fit in the samplers' coordinates; ``laplace_cov``: the Laplace
      covariance there, ``(J^T J)^-1`` of the profiled residuals and the prior (P, P),
      carried to the samplers' coordinates.
    - ``coords``: the coordinates' names (``ravel_pytree``'s order: sorted).
    - ``names``: the physical parameters the samples report (sorted; arrays as ``k[i]``),
      the columns of :meth:`to_physical`.
    """

    problem: Any
    template: dict
    args: tuple
    flat0: np.ndarray
    laplace_cov: np.ndarray
    coords: tuple[str, ...]
    names: list[str]
    idx: tuple[int, ...] = ()

    def fn(self, flat):
        return log_prob(self.problem, self.template, self.args, flat, self.idx)

    def batch(self, flats) -> np.ndarray:
        """:meth:`fn` of many points (N, P) in one compiled call, as float64 NumPy."""
        return np.asarray(_log_prob_batch(self.problem, self.template, self.args, jnp.asarray(flats), self.idx), np.float64)

    def to_fit(self, flats) -> np.ndarray:
        """The fit's unconstrained coordinates (logit for the fractions) of samplers' ones (..., P)."""
        return np.asarray(_to_fit(jnp.asarray(flats).T, self.idx)[0].T if self.idx else flats, np.float64)

    def to_physical(self, flats) -> np.ndarray:
        """Physical values (N, len(names)) of flat coordinates (N, P)."""
        return np.asarray(_to_physical_batch(self.problem, self.template, jnp.asarray(flats), self.idx), np.float64)


def log_density(
    calibrator: Calibrator,
    capture: Capture,
    fit: CalibrationResult,
    nuisance_width: float | None = NUISANCE_WIDTH,
    hold: tuple[str, ...] = HELD,
    gain_prior: str = GAIN_PRIOR,
) -> LogDensity:
    """The posterior of ``calibrator``'s nonlinear parameters given ``capture``, around the
    point fit ``fit`` (which must be of this scene).

    ``nuisance_width``: the width, in the unconstrained space, of a Gaussian prior centred on
    the scene's value of each weakly identified nuisance parameter (:data:`NUISANCE`), on top
    of the fit's weak one; None: none (the fit's own objective alone). ``hold``: coordinates
    (of those the fit has) held at the point fit, not sampled (default :data:`HELD`)."""
    calibrator = calibrator.for_result(fit)  # pulse_tails = "auto": the model the fit chose
    problem = calibrator.problem
    if fit.scene_fingerprint and fit.scene_fingerprint != scene_fingerprint(calibrator.scene):
        raise CalibrationError("the point fit was made for another scene than this calibrator's")
    if not problem.nonlinear:
        raise CalibrationError("the posterior needs at least one free nonlinear parameter")
    config = calibrator.config
    names = tuple(problem.nonlinear)
    base = fit.params
    dtype = problem.model.geometry.ray_length.dtype
    data, sigma = _data(capture, dtype, config.model_error)
    prior_params = calibrator.base_params()
    prior = problem.pack_jax(prior_params, names)
    if "n1" in names:
        start, found = timing_start(problem, np.asarray(data), capture.n_frames, calibrator.scene, prior_params)
        prior["n1_anchor"] = _anchor(start, found, config, dtype)
    packed = {k: jnp.asarray(v, dtype) for k, v in problem.pack(base, names).items()}
    unknown = set(hold) - set(FITTABLE) - {"extinction", "albedo"}
    if unknown:
        raise CalibrationError(f"hold: unknown parameter {sorted(unknown)[0]!r}")
    held = {k: v for k, v in packed.items() if k in hold}
    template = {k: v for k, v in packed.items() if k not in held}
    if not template:
        raise CalibrationError("hold: every free parameter is held; nothing is left to sample")
    flat0, _ = jax.flatten_util.ravel_pytree(template)
    if nuisance_width is not None and not (0 < nuisance_width < np.inf):
        raise CalibrationError(f"nuisance_width: must be a positive number, got {nuisance_width!r}")
    widths = {k: jnp.asarray(nuisance_width, dtype) for k in NUISANCE if k in template and nuisance_width is not None}
    if gain_prior not in GAIN_PRIORS:
        raise CalibrationError(f"gain_prior: one of {', '.join(GAIN_PRIORS)}, got {gain_prior!r}")
    args = (base, data, sigma, prior, widths, held, jnp.asarray(float(gain_prior == "log-uniform"), dtype))
    extra = {k: np.zeros(np.shape(v)) + (1.0 / float(widths[k]) ** 2 if k in widths else 0.0) for k, v in template.items()}
    # J^T J over every coordinate the fit has (the held ones at their values: the same point), then
    # the sampled coordinates' block: one compiled program whatever is held
    full, _ = jax.flatten_util.ravel_pytree(packed)
    pos = np.cumsum([0] + [int(np.size(packed[k])) for k in sorted(packed)])
    keep = np.concatenate([np.arange(pos[i], pos[i + 1]) for i, k in enumerate(sorted(packed)) if k in template])
    jtj = np.asarray(_jtj_flat(problem, packed, args[:4], {}, full))[np.ix_(keep, keep)]
    cov = normal_covariance(jtj, np.concatenate([np.ravel(extra[k]) for k in sorted(extra)]))
    # the fractions sampled as w (LOG_FRACTIONS); flat0 and the covariance carried there
    sizes = {k: int(np.size(v)) for k, v in template.items()}
    starts = np.cumsum([0] + [sizes[k] for k in sorted(template)])
    log_fractions = [k for k in LOG_FRACTIONS if k in template and (k == "albedo" or (
        problem.transform(k).kind == "sigmoid" and problem.transform(k).lo == 0.0 and problem.transform(k).hi == 1.0))]
    idx = tuple(int(i) for k in log_fractions for i in range(starts[sorted(template).index(k)], starts[sorted(template).index(k) + 1]))
    flat0 = np.asarray(flat0, np.float64)
    w0 = _to_sampler_np(flat0, idx)
    jac = np.asarray(jax.jacfwd(lambda f: _to_fit(f, idx)[0])(jnp.asarray(w0)), np.float64)  # d fit / d sampler (diagonal)
    d = np.diag(jac)
    cov = cov / d[:, None] / d[None, :]
    labels = []
    for k in sorted(problem.physical(template)):  # the columns of to_physical
        n = int(np.size(getattr(base, k)))
        labels += [k] if np.ndim(getattr(base, k)) == 0 else [f"{k}[{i}]" for i in range(n)]
    return LogDensity(
        problem=problem, template=template, args=args, flat0=w0,
        laplace_cov=0.5 * (cov + cov.T), coords=tuple(sorted(template)), names=labels, idx=idx,
    )


_value_and_grad = eqx.filter_jit(lambda problem, template, args, flat, idx=(): jax.value_and_grad(
    lambda f: log_prob(problem, template, args, f, idx))(flat))


def posterior_mode(ld: LogDensity, max_steps: int = 200) -> tuple[np.ndarray, np.ndarray, dict]:
    """The log-density's mode and the Laplace covariance there: ``(mode, cov, info)``.

    The point fit is not the posterior's mode: the nuisance prior (absent from the fit) and
    the integrated linear parameters' volume term move it, on the default baseline by 1.5-2.5
    of the fit's Laplace standard errors along the ridge (albedo, end reflectance, interface
    backscatter), where the fit's ``J^T J`` is also the wrong curvature (the draws' covariance
    in its whitened coordinates had eigenvalues 4e-4 to 4). BFGS (SciPy) on the compiled value
    and gradient, in coordinates scaled by the fit's Laplace errors, from the fit; the Hessian
    at the mode by central differences of the gradient (2 P gradients, no second program to
    compile), symmetrised. Falls back to the fit and its Laplace covariance where the
    optimisation fails or the Hessian is not negative definite (``info["used"]`` says which)."""
    from scipy.optimize import minimize

    scale = np.sqrt(np.clip(np.diag(ld.laplace_cov), 1e-300, None))
    x0 = ld.flat0

    def vg(y):
        v, g = _value_and_grad(ld.problem, ld.template, ld.args, jnp.asarray(x0 + scale * y), ld.idx)
        v, g = float(v), np.asarray(g, np.float64) * scale
        if not np.isfinite(v) or not np.all(np.isfinite(g)):
            return 1e300, np.zeros_like(g)
        return -v, -g

    f0 = -vg(np.zeros_like(x0))[0]
    res = minimize(vg, np.zeros_like(x0), jac=True, method="BFGS", options={"maxiter": max_steps, "gtol": 1e-6})
    y = res.x
    info = {"log_density_fit": f0, "log_density_mode": -float(res.fun), "bfgs_iterations": int(res.nit),
            "gradient_evaluations": int(res.njev), "mode_minus_fit_in_fit_sd": dict(zip(ld.coords, y.tolist()))}
    h = 1e-3
    H = np.empty((y.size, y.size))
    for i in range(y.size):
        e = np.zeros_like(y)
        e[i] = h
        H[i] = (vg(y + e)[1] - vg(y - e)[1]) / (2 * h)  # Hessian of -log p (scaled coordinates)
    H = 0.5 * (H + H.T)
    info["gradient_evaluations"] += 2 * y.size
    ok = np.isfinite(res.fun) and -res.fun >= f0 and np.all(np.isfinite(H)) and np.linalg.eigvalsh(H).min() > 0
    if not ok:
        info["used"] = "fit"
        return ld.flat0, ld.laplace_cov, info
    cov = np.linalg.inv(H) * scale[:, None] * scale[None, :]
    info["used"] = "mode"
    return x0 + scale * y, 0.5 * (cov + cov.T), info


def summarise(names: list[str], samples: np.ndarray) -> dict[str, Any]:
    """Mean, median and 68/95% intervals per parameter, and the correlation matrix."""
    out = {}
    for i, k in enumerate(names):
        x = samples[:, i]
        q = np.percentile(x, [2.5, 16, 50, 84, 97.5])
        out[k] = {
            "mean": float(x.mean()),
            "median": float(q[2]),
            "interval68": [float(q[1]), float(q[3])],
            "interval95": [float(q[0]), float(q[4])],
        }
    corr = np.corrcoef(samples.T) if len(names) > 1 else np.ones((1, 1))
    return {"parameters": out, "correlation": {"labels": names, "matrix": np.asarray(corr).tolist()}}


@dataclass(frozen=True)
class PosteriorOptions:
    """``walkers`` (default: max(32, 4 x parameters)), ``max_steps``, ``check_every`` steps
    between autocorrelation checks, ``tau_factor`` (stop once the chain is longer than this
    many autocorrelation times and tau changed by less than ``tau_rtol``), ``seed``,
    ``chain`` (an HDF5 file: the run resumes from it), ``progress`` (a progress bar),
    ``nuisance_width``, ``hold`` and ``gain_prior`` (:func:`log_density`'s)."""

    walkers: int | None = None
    max_steps: int = 5000
    check_every: int = 100
    tau_factor: float = 50.0
    tau_rtol: float = 0.01
    seed: int = 0
    chain: str | None = None
    progress: bool = True
    nuisance_width: float | None = NUISANCE_WIDTH
    hold: tuple[str, ...] = HELD
    gain_prior: str = GAIN_PRIOR


@dataclass
class PosteriorResult:
    names: list[str]  # sampled parameters (physical names)
    samples: np.ndarray  # (n, P) physical units, burn-in discarded and thinned
    tau: np.ndarray  # integrated autocorrelation time per parameter, steps
    acceptance: float
    steps: int
    converged: bool  # chain longer than tau_factor x tau and tau stable
    n_effective: float
    chain: np.ndarray  # (steps, walkers, parameters), unconstrained space, for trace plots
    chain_physical: np.ndarray | None = None  # the same chain in physical units (columns as ``names``)

    def summary(self) -> dict[str, Any]:
        return {
            "sampler": "emcee",
            **summarise(self.names, self.samples),
            "tau": self.tau.tolist(),
            "acceptance_fraction": self.acceptance,
            "steps": self.steps,
            "converged": self.converged,
            "n_effective": self.n_effective,
        }


def _fingerprint(capture: Capture, names, walkers) -> str:
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(capture.mean(), np.float64).tobytes())
    h.update(json.dumps([list(names), int(walkers)]).encode())
    return h.hexdigest()


def sample_posterior(
    calibrator: Calibrator, capture: Capture, fit: CalibrationResult, options: PosteriorOptions = PosteriorOptions()
) -> PosteriorResult:
    """Sample the posterior around a point fit ``fit`` of ``capture`` made by ``calibrator``.

    Walkers start jittered around the fit (scaled by its Laplace errors). The run stops when
    the chain is longer than ``tau_factor`` autocorrelation times and tau is stable, or at
    ``max_steps``; with ``chain`` set, an interrupted run resumes where it stopped (refused if
    the data or settings differ).
    """
    ld = log_density(calibrator, capture, fit, options.nuisance_width, options.hold, options.gain_prior)
    flat0, P = ld.flat0, ld.flat0.size
    W = options.walkers or max(32, 4 * P)
    if W < 2 * P:
        raise CalibrationError(f"walkers: emcee needs at least 2 x {P} = {2 * P} walkers, got {W}")
    vectorised = ld.batch

    # initial scatter from the Laplace errors in the unconstrained space
    scale = np.maximum(np.sqrt(np.diag(ld.laplace_cov)), 1e-6)
    rng = np.random.default_rng(options.seed)

    backend = None
    start = flat0[None, :] + 0.1 * scale[None, :] * rng.normal(size=(W, P))
    fingerprint = _fingerprint(capture, (*ld.names, *ld.coords, f"nuisance {options.nuisance_width}", f"hold {sorted(options.hold)}", f"gain {options.gain_prior}"), W)  # coordinates too
    if options.chain:
        import h5py

        path = Path(options.chain)
        resume = path.exists()
        if resume:
            with h5py.File(path, "r") as f:
                stored = f["tofjax"].attrs.get("fingerprint") if "tofjax" in f else None
            if stored != fingerprint:
                raise CalibrationError(
                    f"{path}: this chain was made from other data or settings; delete it or choose another --chain"
                )
        backend = emcee.backends.HDFBackend(str(path), name="tofjax")
        if not resume:
            backend.reset(W, P)
            with h5py.File(path, "a") as f:
                f["tofjax"].attrs["fingerprint"] = fingerprint
        elif backend.iteration > 0:
            start = backend.get_last_sample()  # continue from where it stopped
    sampler = emcee.EnsembleSampler(W, P, vectorised, vectorize=True, backend=backend)
    done = 0 if backend is None else backend.iteration
    # emcee's moves draw from its own generator, seeded from the OS unless set: the same seed now gives the same chain
    # (a resumed chain continues from a stream of its own, keyed by where it stopped)
    sampler.random_state = np.random.RandomState(np.random.SeedSequence([options.seed, done]).generate_state(1)[0]).get_state()
    old_tau = np.inf
    converged = False
    for _ in sampler.sample(start, iterations=max(options.max_steps - done, 0), progress=options.progress):
        it = sampler.iteration
        if it % options.check_every:
            continue
        tau = sampler.get_autocorr_time(tol=0)
        if np.all(np.isfinite(tau)) and np.all(tau * options.tau_factor < it) and np.all(
            np.abs(old_tau - tau) / tau < options.tau_rtol
        ):
            converged = True
            break
        old_tau = tau
    tau = sampler.get_autocorr_time(tol=0)
    burn = int(2 * np.nanmax(tau)) if np.all(np.isfinite(tau)) else sampler.iteration // 2
    thin = max(int(0.5 * np.nanmin(tau)), 1) if np.all(np.isfinite(tau)) else 1
    flat = sampler.get_chain(discard=min(burn, sampler.iteration - 1), thin=thin, flat=True)
    samples = ld.to_physical(flat)
    n_samples_total = (sampler.iteration - min(burn, sampler.iteration - 1)) * W
    return PosteriorResult(
        names=ld.names,
        samples=samples,
        tau=np.asarray(tau),
        acceptance=float(np.mean(sampler.acceptance_fraction)),
        steps=int(sampler.iteration),
        converged=converged,
        n_effective=float(n_samples_total / np.nanmax(tau)) if np.all(np.isfinite(tau)) else 0.0,
        chain=ld.to_fit(sampler.get_chain()),
        chain_physical=ld.to_physical(sampler.get_chain().reshape(-1, P)).reshape(sampler.iteration, W, -1),
    )
