"""Posterior of the calibration parameters with NUTS (blackjax), diagnosed with ArviZ.

The target is :func:`tofjax.fit.posterior.log_density`, the same log-density emcee samples:
the nonlinear parameters in the fit's unconstrained space, the linear ones integrated out.
NUTS starts at the point fit and works in coordinates whitened by its Laplace covariance,
``u = u_fit + L z`` with ``L L^T = (J^T J)^-1``: there the posterior is close to a unit
normal, so the initial step size and an identity mass matrix are already good, and the
strong correlations of the nuisance parameters (interface backscatter, end reflectance and
albedo move together) no longer slow the sampler. Stan's window adaptation then tunes the
step size and a dense mass matrix on top. Chains start at independent draws from the
Laplace approximation, so R-hat compares chains that began apart.

Warm-up and sampling of every chain are one compiled, vmapped program, compiled once per
problem shape (not per capture): a study's replicates reuse it.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..capture import Capture
from .calibrate import CalibrationError, CalibrationResult, Calibrator
from .posterior import NUISANCE_WIDTH, LogDensity, log_density, log_prob, summarise

__all__ = ["NutsOptions", "NutsResult", "sample_nuts", "diagnostics"]


class NutsOptionsError(CalibrationError):
    """NUTS options that cannot run (no chains, no draws, ...)."""


@dataclass(frozen=True)
class NutsOptions:
    """``chains`` (run in parallel, vmapped), ``warmup`` steps of window adaptation per chain,
    ``draws`` kept per chain, ``seed``, ``target_accept`` (the adaptation's target acceptance),
    ``max_tree_depth`` (at most 2^depth leapfrog steps per draw), ``dense`` (a dense mass
    matrix; False: diagonal), ``nuisance_width`` (the prior of
    :func:`~tofjax.fit.posterior.log_density`)."""

    chains: int = 4
    warmup: int = 500
    draws: int = 1000
    seed: int = 0
    target_accept: float = 0.8
    max_tree_depth: int = 10
    dense: bool = True
    nuisance_width: float | None = NUISANCE_WIDTH

    def __post_init__(self):
        for k, lo in (("chains", 1), ("warmup", 10), ("draws", 10), ("max_tree_depth", 1)):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise NutsOptionsError(f"{k}: must be an integer >= {lo}, got {v!r}")
        if not 0.5 <= self.target_accept < 1:
            raise NutsOptionsError(f"target_accept: must be in [0.5, 1), got {self.target_accept!r}")


@dataclass
class NutsResult:
    names: list[str]  # physical parameters, the columns of ``samples``
    samples: np.ndarray  # (chains x draws, P) physical units
    chains_physical: np.ndarray  # (chains, draws, P) physical units, for traces and diagnostics
    chains_unconstrained: np.ndarray  # (chains, draws, coordinates) the sampler's space
    coords: tuple[str, ...]
    divergences: int
    step_size: np.ndarray  # (chains,) adapted
    mean_tree_depth: float
    mean_accept: float
    gradient_evaluations: int  # leapfrog steps, all chains, warm-up included
    wall_s: float  # warm-up and sampling (compilation excluded)
    compile_s: float  # tracing and compiling (or reading the compilation cache); ~0 when reused
    diagnostics: dict[str, Any]
    options: NutsOptions

    def summary(self) -> dict[str, Any]:
        d = self.diagnostics
        return {
            "sampler": "nuts",
            **summarise(self.names, self.samples),
            "chains": self.options.chains,
            "warmup": self.options.warmup,
            "draws": self.options.draws,
            "nuisance_width": self.options.nuisance_width,
            "divergences": self.divergences,
            "step_size": self.step_size.tolist(),
            "mean_tree_depth": self.mean_tree_depth,
            "mean_accept": self.mean_accept,
            "gradient_evaluations": self.gradient_evaluations,
            "wall_s": self.wall_s,
            "compile_s": self.compile_s,
            "ess_bulk": d["ess_bulk"],
            "ess_tail": d["ess_tail"],
            "rhat": d["rhat"],
            "ess_min": d["ess_min"],
            "rhat_max": d["rhat_max"],
            "ess_min_per_s": d["ess_min"] / self.wall_s if self.wall_s > 0 else None,
            "ess_bulk_per_s": {k: v / self.wall_s for k, v in d["ess_bulk"].items()} if self.wall_s > 0 else None,
        }


def _arviz():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)  # ArviZ 0.2x announces its 1.0 refactor on import
        import arviz as az
    return az


def diagnostics(names: list[str], chains: np.ndarray) -> dict[str, Any]:
    """ArviZ's bulk and tail ESS and rank-normalised split R-hat of ``chains`` (C, N, P), per
    parameter, with the minimum ESS (bulk and tail together) and the largest R-hat."""
    az = _arviz()
    post = {f"p{i}": np.asarray(chains[..., i], np.float64) for i in range(len(names))}
    data = az.convert_to_dataset(post)
    bulk, tail, rhat = az.ess(data, method="bulk"), az.ess(data, method="tail"), az.rhat(data)

    def per(ds):
        return {k: float(ds[f"p{i}"].values) for i, k in enumerate(names)}

    b, t, r = per(bulk), per(tail), per(rhat)
    finite = [v for v in list(b.values()) + list(t.values()) if np.isfinite(v)]
    return {
        "ess_bulk": b,
        "ess_tail": t,
        "rhat": r,
        "ess_min": float(min(finite)) if finite else 0.0,
        "rhat_max": float(max(r.values())),
    }


@eqx.filter_jit
def _run(problem, template, args, flat0, chol, keys, z0, warmup: int, draws: int, dense: bool, target_accept: float, depth: int):
    import blackjax

    def logdensity(z):
        return log_prob(problem, template, args, flat0 + chol @ z)

    def one_chain(key, z_start):
        k_warm, k_draw = jax.random.split(key)
        adapt = blackjax.window_adaptation(
            blackjax.nuts, logdensity, is_mass_matrix_diagonal=not dense, initial_step_size=0.5,
            target_acceptance_rate=target_accept, max_num_doublings=depth,
        )
        (state, params), winfo = adapt.run(k_warm, z_start, num_steps=warmup)
        kernel = blackjax.nuts(logdensity, **params)  # params carry max_num_doublings too

        def step(s, k):
            s, info = kernel.step(k, s)
            return s, (s.position, info.is_divergent, info.num_integration_steps, info.acceptance_rate, info.num_trajectory_expansions)

        _, (zs, div, nsteps, acc, depth_used) = jax.lax.scan(step, state, jax.random.split(k_draw, draws))
        warm_steps = jnp.sum(winfo.info.num_integration_steps)
        return zs, div, nsteps, acc, depth_used, params["step_size"], warm_steps

    return jax.vmap(one_chain)(keys, z0)


_COMPILED: dict = {}


def _compiled(run_args, statics):
    """The compiled sampler for these shapes and settings, compiled ahead of time (so the
    sampling is timed without it) and kept for the next call of the same shapes."""
    dyn, stat = eqx.partition(run_args, eqx.is_array)
    leaves, tree = jax.tree_util.tree_flatten(dyn)
    try:
        key = (tree, tuple((x.shape, str(x.dtype)) for x in leaves), jax.tree_util.tree_flatten(stat), statics)
        hash(key)
    except TypeError:
        key = None
    if key is not None and key in _COMPILED:
        return _COMPILED[key]
    compiled = _run.lower(*run_args, *statics).compile()
    if key is not None:
        if len(_COMPILED) > 8:
            _COMPILED.clear()
        _COMPILED[key] = compiled
    return compiled


def sample_nuts(
    calibrator: Calibrator,
    capture: Capture,
    fit: CalibrationResult,
    options: NutsOptions = NutsOptions(),
    density: LogDensity | None = None,
) -> NutsResult:
    """Sample the posterior of ``capture`` around the point fit ``fit`` with NUTS.

    ``density``: a :func:`~tofjax.fit.posterior.log_density` already built for these
    (saves rebuilding it). Returns draws in physical units and ArviZ's diagnostics.
    """
    ld = density if density is not None else log_density(calibrator, capture, fit, options.nuisance_width)
    P = ld.flat0.size
    cov = ld.laplace_cov
    scale = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    corr = cov / scale[:, None] / scale[None, :]
    chol = scale[:, None] * np.linalg.cholesky(corr + 1e-10 * np.eye(P))  # L L^T = cov, conditioned per axis
    dtype = ld.args[1].dtype
    key = jax.random.PRNGKey(options.seed)
    k_start, k_chains = jax.random.split(key)
    z0 = jax.random.normal(k_start, (options.chains, P), dtype)  # draws from the Laplace approximation
    keys = jax.random.split(k_chains, options.chains)
    statics = (options.warmup, options.draws, options.dense, float(options.target_accept), options.max_tree_depth)
    run_args = (ld.problem, ld.template, ld.args, jnp.asarray(ld.flat0, dtype), jnp.asarray(chol, dtype), keys, z0)
    t = time.perf_counter()
    compiled = _compiled(run_args, statics)
    compile_s = time.perf_counter() - t
    t = time.perf_counter()
    out = jax.block_until_ready(compiled(*run_args, *statics))
    wall = time.perf_counter() - t
    zs, div, nsteps, acc, depth_used, step_size, warm_steps = (np.asarray(x) for x in out)
    C, N = zs.shape[:2]
    flats = ld.flat0[None, None, :] + np.einsum("ij,cnj->cni", chol, zs)
    phys = ld.to_physical(flats.reshape(C * N, P)).reshape(C, N, -1)
    diag = diagnostics(ld.names, phys)
    return NutsResult(
        names=ld.names,
        samples=phys.reshape(C * N, -1),
        chains_physical=phys,
        chains_unconstrained=flats,
        coords=ld.coords,
        divergences=int(div.sum()),
        step_size=np.asarray(step_size, np.float64),
        mean_tree_depth=float(depth_used.mean()),
        mean_accept=float(acc.mean()),
        gradient_evaluations=int(nsteps.sum() + warm_steps.sum()),
        wall_s=wall,
        compile_s=compile_s,
        diagnostics=diag,
        options=options,
    )


def plot_nuts(result: NutsResult, folder, truths=None) -> list:
    """``corner.png`` (the draws of every chain, physical units) and ``traces.png`` (one
    colour per chain, with each parameter's bulk ESS and R-hat) in ``folder``."""
    from pathlib import Path

    import matplotlib.pyplot as plt

    from ..outputs import save_figure
    from ..plot import plot_posterior

    folder = Path(folder)
    paths = [plot_posterior(result.samples, result.names, truths, folder / "corner.png")]
    ch = result.chains_physical
    P = ch.shape[-1]
    d = result.diagnostics
    fig, axes = plt.subplots(P, 1, figsize=(7, 1.3 * P + 0.6), sharex=True, squeeze=False)
    for i, k in enumerate(result.names):
        ax = axes[i, 0]
        for c in range(ch.shape[0]):
            ax.plot(ch[c, :, i], lw=0.4, alpha=0.7)
        ax.set_ylabel(k, fontsize=6)
        ax.set_title(f"ESS bulk {d['ess_bulk'][k]:.0f}, tail {d['ess_tail'][k]:.0f}, R-hat {d['rhat'][k]:.3f}",
                     fontsize=6, loc="right")
    axes[-1, 0].set_xlabel("draw (after warm-up)")
    fig.suptitle(f"NUTS traces: {ch.shape[0]} chains, {result.divergences} divergences (physical units)", fontsize=9)
    fig.tight_layout()
    paths.append(save_figure(fig, folder / "traces.png"))
    return paths
