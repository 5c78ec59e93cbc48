"""Posterior of the calibration parameters with emcee.

The sampled parameters are the nonlinear ones (n1, mu_s, mu_a, pulse, emission
time, reflectances) in the fit's unconstrained space. The linear ones (gain,
light-entry and ambient counts) are integrated out analytically: for the
Gaussian (Poisson-weighted) likelihood with flat priors on them, that adds
``-1/2 log det(A^T W A)`` to the profiled log-likelihood. The prior is the fit
config's weak Gaussian in the unconstrained space. One jitted, vmapped
log-probability serves all walkers (``vectorize=True``).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import emcee
import jax
import jax.numpy as jnp
import numpy as np

from ..capture import Capture
from .calibrate import CalibrationError, CalibrationResult, Calibrator, scene_fingerprint

__all__ = ["PosteriorOptions", "PosteriorResult", "sample_posterior"]


@dataclass(frozen=True)
class PosteriorOptions:
    """``walkers`` (default: max(32, 4 x parameters)), ``max_steps``, ``check_every`` steps
    between autocorrelation checks, ``tau_factor`` (stop once the chain is longer than this
    many autocorrelation times and tau changed by less than ``tau_rtol``), ``seed``,
    ``chain`` (an HDF5 file: the run resumes from it), ``progress`` (a progress bar)."""

    walkers: int | None = None
    max_steps: int = 5000
    check_every: int = 100
    tau_factor: float = 50.0
    tau_rtol: float = 0.01
    seed: int = 0
    chain: str | None = None
    progress: bool = True


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
        out = {}
        for i, k in enumerate(self.names):
            x = self.samples[:, i]
            q = np.percentile(x, [2.5, 16, 50, 84, 97.5])
            out[k] = {
                "mean": float(x.mean()),
                "median": float(q[2]),
                "interval68": [float(q[1]), float(q[3])],
                "interval95": [float(q[0]), float(q[4])],
            }
        corr = np.corrcoef(self.samples.T) if len(self.names) > 1 else np.ones((1, 1))
        return {
            "parameters": out,
            "correlation": {"labels": self.names, "matrix": np.asarray(corr).tolist()},
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
    problem = calibrator.problem
    if fit.scene_fingerprint and fit.scene_fingerprint != scene_fingerprint(calibrator.scene):
        raise CalibrationError("the point fit was made for another scene than this calibrator's")
    names = tuple(sorted(problem.nonlinear))
    base = fit.params
    u_fit = problem.pack(base, names)
    prior = problem.pack(calibrator.base_params(), names)
    flat0, unravel = jax.flatten_util.ravel_pytree(u_fit)
    P = flat0.size
    W = options.walkers or max(32, 4 * P)
    if W < 2 * P:
        raise CalibrationError(f"walkers: emcee needs at least 2 x {P} = {2 * P} walkers, got {W}")
    dtype = problem.model.geometry.ray_length.dtype
    mean = capture.mean()
    data = jnp.asarray(mean, dtype)
    sigma = jnp.asarray(np.sqrt(np.maximum(mean, 1.0) / capture.n_frames), dtype)

    def log_prob(flat):
        u = unravel(flat)
        params = problem.unpack(u, base)
        if problem.linear:
            _, m, logdet, _ = problem.profile(params, data, sigma)
        else:
            m, logdet = problem.model(params), 0.0
        r = (m - data) / sigma
        lp = -0.5 * jnp.sum(r**2) - 0.5 * logdet - 0.5 * jnp.sum(problem.prior_residuals(u, prior) ** 2)
        return jnp.where(jnp.isfinite(lp), lp, -jnp.inf)

    batched = jax.jit(jax.vmap(log_prob))

    def vectorised(x):
        return np.asarray(batched(jnp.asarray(x)), np.float64)

    # initial scatter from the Laplace errors in the unconstrained space
    scale = np.concatenate([np.ravel(fit.unconstrained_stderr[k]) for k in sorted(u_fit)])
    scale = np.maximum(scale, 1e-6)
    rng = np.random.default_rng(options.seed)

    backend = None
    start = np.asarray(flat0)[None, :] + 0.1 * scale[None, :] * rng.normal(size=(W, P))
    fingerprint = _fingerprint(capture, (*names, *sorted(u_fit)), W)  # coordinates too
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
    # back to physical units
    to_phys = jax.jit(jax.vmap(lambda f: jnp.concatenate([jnp.ravel(v) for _, v in sorted(problem.physical(unravel(f)).items())])))
    samples = np.asarray(to_phys(jnp.asarray(flat)))
    labels = []
    for k in names:  # sorted, as the columns of ``samples``
        n = int(np.size(getattr(base, k)))
        labels += [k] if np.ndim(getattr(base, k)) == 0 else [f"{k}[{i}]" for i in range(n)]
    n_samples_total = (sampler.iteration - min(burn, sampler.iteration - 1)) * W
    return PosteriorResult(
        names=labels,
        samples=samples,
        tau=np.asarray(tau),
        acceptance=float(np.mean(sampler.acceptance_fraction)),
        steps=int(sampler.iteration),
        converged=converged,
        n_effective=float(n_samples_total / np.nanmax(tau)) if np.all(np.isfinite(tau)) else 0.0,
        chain=sampler.get_chain(),
        chain_physical=np.asarray(to_phys(jnp.asarray(sampler.get_chain().reshape(-1, P)))).reshape(sampler.iteration, W, -1),
    )
