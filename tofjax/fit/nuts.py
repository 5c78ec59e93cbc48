"""Posterior of the calibration parameters with NUTS (blackjax), diagnosed with ArviZ.

The target is :func:`tofjax.fit.posterior.log_density`, the same log-density emcee samples:
the nonlinear parameters in the fit's unconstrained space, the linear ones integrated out
(log-uniform gain prior). NUTS starts at the log-density's mode, not at the point fit
(:func:`tofjax.fit.posterior.posterior_mode`: BFGS from the fit, then the Hessian there by
differences of the gradient): the nuisance prior, which the fit does not have, moves the
mode 1.5-2.5 of the fit's Laplace standard errors along the ridge (albedo, end reflectance
and interface backscatter), where the fit's ``J^T J`` is also the wrong curvature. NUTS works
in coordinates whitened by the Laplace covariance at the mode, ``u = u_mode + L z`` with
``L L^T = H^-1``: there the posterior is close to a unit normal, so the initial step size and
an identity mass matrix are already good, and the strong correlations (the ridge; n1, pulse
and emission time) no longer slow the sampler. Stan's window adaptation then tunes the step
size and a dense mass matrix on top. Chains start at independent draws from that Laplace
approximation, so R-hat compares chains that began apart. ``start="fit"`` and ``pilot``
(a first run whose draws whiten the kept one) remain as options.

Before the whitening the coordinates are sheared along the ridge (``shear``, on by default,
:func:`unshear`): the other coordinates are measured from the ridge's line in log albedo.
The ridge (log albedo, log end reflectance, log interface backscatter moving together
against the gains) ends where the albedo reaches its bound 1; in the samplers' coordinate
``w`` (log p, smoothly bounded at 0) the albedo then stops while a straight line in the
others runs on, off the ridge, into a wall where trajectories diverged (4 divergences in
4 x 700 draws on the default baseline). Sheared, past the bound the other coordinates stay
at the ridge's end and the density falls off smoothly (the change of variables' exponential
tail): no divergence in any of nine sheared runs against 1-11 per run unsheared (docs/results/posterior_variants.json).

Warm-up and sampling of one chain are one compiled program with one NUTS kernel (the window
adaptation is driven by hand, so the kernel is not compiled twice), compiled once per problem
shape (not per capture): the chains, a study's replicates and the pilot reuse it. The chains
run one after the other, or ``threads`` at a time (vmapped, each NUTS step would last as long
as the longest chain's, and XLA's CPU runtime does not spread a vmapped gradient over the
cores: 4.1 ms for four against 1.0 ms for one). The draws do not depend on ``threads``.
"""

from __future__ import annotations

import dataclasses
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
from .posterior import STEEP, GAIN_PRIOR, GAIN_PRIORS, HELD, NUISANCE_WIDTH, LogDensity, _value_and_grad, log_density, log_prob, posterior_mode, summarise

__all__ = ["NutsOptions", "NutsResult", "sample_nuts", "diagnostics"]


class NutsOptionsError(CalibrationError):
    """NUTS options that cannot run (no chains, no draws, ...)."""


@dataclass(frozen=True)
class NutsOptions:
    """``chains`` (run one after the other), ``warmup`` steps of window adaptation per chain,
    ``draws`` kept per chain, ``start`` ("mode": the chains start at draws from the Laplace
    approximation at the log-density's mode, found first by BFGS, and work in coordinates
    whitened by it; "fit": at the point fit and its Laplace covariance), ``seed``, ``target_accept`` (the adaptation's target acceptance; 0.95: on the default
    baseline the sampler is fragile along the albedo / end reflectance / interface ridge; idle, seed 0,
    0.9 gave min ESS 21-145 with 28 divergences, 0.95 1091 with none (docs/results/posterior_idle_second.json);
    on two other runs 0.9 gave 1.6-2.9x more min ESS per gradient; 0.85 collapsed),
    ``max_tree_depth`` (at most 2^depth leapfrog steps per draw), ``dense`` (a dense mass
    matrix; False: diagonal), ``pilot`` (run the same chains twice: the first run, from the
    Laplace approximation at the fit, only finds the posterior's bulk and its covariance; the
    second, the one reported, works in coordinates whitened by them and starts where the
    first ended; wall time and gradient evaluations count both), ``nuisance_width`` (the prior of
    :func:`~tofjax.fit.posterior.log_density`), ``hold`` (its coordinates held at the fit),
    ``gain_prior`` (its prior of the integrated-out gains), ``shear`` (the coordinates sheared
    along the albedo ridge, :func:`unshear`), ``ridge_tail`` (with ``shear``: the ridge's low
    end compressed too, :func:`fit_tail`; measured no better on the default baseline, off),
    ``adapt_mass`` (False: no mass matrix adaptation, the whitened coordinates' identity;
    measured worse: the ridge's width is not the Laplace one), ``threads`` (chains run at the
    same time, each in its own thread on the one compiled program; None (the default): one per
    CPU core, at most ``chains``; 1: one after the other. The draws are the same whatever it is: each
    chain's are fixed by its key; only the wall time changes), ``pilot_warmup``,
    ``pilot_draws`` (the pilot's lengths; None: ``warmup``, ``draws``) and ``pilot_adapt_mass``
    (the pilot's mass matrix adaptation; False: its step size only, in the Laplace-whitened
    coordinates): a short pilot whose chains' draws are pooled is a cross-chain mass matrix
    (every chain's draws, not one chain's last window), and the kept run then needs only its
    step size (``adapt_mass=False``) and a short ``warmup``."""

    chains: int = 4
    warmup: int = 250
    draws: int = 700
    start: str = "mode"
    seed: int = 0
    target_accept: float = 0.95
    max_tree_depth: int = 10
    dense: bool = True
    pilot: bool = False
    shear: bool = True
    ridge_tail: bool = False
    adapt_mass: bool = True
    nuisance_width: float | None = NUISANCE_WIDTH
    hold: tuple[str, ...] = HELD
    gain_prior: str = GAIN_PRIOR
    threads: int | None = None
    pilot_warmup: int | None = None
    pilot_draws: int | None = None
    pilot_adapt_mass: bool = True

    def __post_init__(self):
        if self.threads is not None and (isinstance(self.threads, bool) or not isinstance(self.threads, (int, np.integer))
                                         or self.threads < 1):
            raise NutsOptionsError(f"threads: must be an integer >= 1 or None (one per CPU core), got {self.threads!r}")
        for k, lo in (("chains", 1), ("warmup", 10), ("draws", 10), ("max_tree_depth", 1), ("pilot_warmup", 10), ("pilot_draws", 10)):
            v = getattr(self, k)
            if v is None and k.startswith("pilot_"):
                continue
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise NutsOptionsError(f"{k}: must be an integer >= {lo}, got {v!r}")
        if not 0.5 <= self.target_accept < 1:
            raise NutsOptionsError(f"target_accept: must be in [0.5, 1), got {self.target_accept!r}")
        if self.start not in ("mode", "fit"):
            raise NutsOptionsError(f"start: mode or fit, got {self.start!r}")
        if self.gain_prior not in GAIN_PRIORS:
            raise NutsOptionsError(f"gain_prior: one of {', '.join(GAIN_PRIORS)}, got {self.gain_prior!r}")


@dataclass
class NutsResult:
    names: list[str]  # physical parameters, the columns of ``samples``
    samples: np.ndarray  # (chains x draws, P) physical units
    chains_physical: np.ndarray  # (chains, draws, P) physical units, for traces and diagnostics
    chains_unconstrained: np.ndarray  # (chains, draws, coordinates) the fit's unconstrained space
    coords: tuple[str, ...]
    divergences: int
    step_size: np.ndarray  # (chains,) adapted
    mean_tree_depth: float
    mean_accept: float
    gradient_evaluations: int  # leapfrog steps, all chains, warm-up included
    wall_s: float  # finding the mode, warm-up and sampling (compilation excluded)
    compile_s: float  # tracing and compiling (or reading the compilation cache); ~0 when reused
    diagnostics: dict[str, Any]
    options: NutsOptions
    start_info: dict = dataclasses.field(default_factory=dict)  # posterior_mode's info (start "mode")
    warmup_gradient_evaluations: int = 0  # leapfrog steps of the warm-up (pilot included), all chains

    def summary(self) -> dict[str, Any]:
        d = self.diagnostics
        return {
            "sampler": "nuts",
            **summarise(self.names, self.samples),
            "chains": self.options.chains,
            "warmup": self.options.warmup,
            "draws": self.options.draws,
            "pilot": self.options.pilot,
            "shear": self.options.shear,
            "ridge_tail": self.options.ridge_tail,
            "adapt_mass": self.options.adapt_mass,
            "start": self.options.start,
            "start_info": self.start_info,
            "target_accept": self.options.target_accept,
            "nuisance_width": self.options.nuisance_width,
            "held_at_fit": list(self.options.hold),
            "gain_prior": self.options.gain_prior,
            "divergences": self.divergences,
            "step_size": self.step_size.tolist(),
            "mean_tree_depth": self.mean_tree_depth,
            "mean_accept": self.mean_accept,
            "gradient_evaluations": self.gradient_evaluations,
            "warmup_gradient_evaluations": self.warmup_gradient_evaluations,
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
def _run(problem, template, args, idx, flat0, chol, key, z_start, ridge, warmup: int, draws: int, dense: bool, target_accept: float, depth: int,
         adapt_mass: bool = True):
    """Warm-up and draws of one chain as one scan over one NUTS kernel: Stan's window
    adaptation (blackjax's ``window_adaptation.base`` and schedule) updates the step size and
    mass matrix during the first ``warmup`` steps and is frozen after, at its final values.
    One kernel in the program, not blackjax's two (adaptation and sampling), halves what XLA
    compiles. One chain per call, not the chains vmapped: a vmapped NUTS step runs every
    chain's trajectory as long as the longest one, the batched model's gradient compiles
    separately and costs as much per chain on a CPU (measured on the default baseline: 1.0 ms
    for one gradient, 4.1 ms for four vmapped)."""
    import blackjax
    from blackjax.adaptation.window_adaptation import base, build_schedule

    def logdensity(z):
        x, log_jac = unshear(flat0 + chol @ z, ridge)
        return log_prob(problem, template, args, x, idx) + log_jac

    with warnings.catch_warnings():  # blackjax 1.7 marks base() deprecated (staged_adaptation is its successor)
        warnings.simplefilter("ignore", DeprecationWarning)
        adapt_init, adapt_update, adapt_final = base(not dense, target_accept)
    kernel = blackjax.nuts.build_kernel()
    with jax.ensure_compile_time_eval():  # a constant of the program (blackjax builds it with jnp)
        schedule = np.asarray(build_schedule(warmup), np.int32).reshape(warmup, 2)
    n = warmup + draws
    stage = jnp.asarray(np.concatenate([schedule[:, 0], np.zeros(draws, np.int32)]))
    window_end = jnp.asarray(np.concatenate([schedule[:, 1], np.zeros(draws, np.int32)]).astype(bool))
    warming = jnp.arange(n) < warmup

    def step(carry, x):
        state, adapt = carry
        k, st, end, warm = x
        final_step, final_imm = adapt_final(adapt)
        step_size = jnp.where(warm, adapt.step_size, final_step)
        imm = jnp.where(warm, adapt.inverse_mass_matrix, final_imm)
        if not adapt_mass:  # the whitened coordinates' identity: only the step size adapts
            imm = jnp.ones_like(imm) if imm.ndim == 1 else jnp.eye(imm.shape[0], dtype=imm.dtype)
        state, info = kernel(k, state, logdensity, step_size, imm, depth)
        updated = adapt_update(adapt, (st, end), state.position, info.acceptance_rate)
        adapt = jax.tree_util.tree_map(lambda u, a: jnp.where(warm, u, a), updated, adapt)
        return (state, adapt), (state.position, info.is_divergent, info.num_integration_steps, info.acceptance_rate,
                                info.num_trajectory_expansions, step_size)

    carry = (blackjax.nuts.init(z_start, logdensity), adapt_init(z_start, 0.5))
    _, (zs, div, nsteps, acc, depth_used, steps) = jax.lax.scan(step, carry, (jax.random.split(key, n), stage, window_end, warming))
    return zs[warmup:], div[warmup:], nsteps[warmup:], acc[warmup:], depth_used[warmup:], steps[-1], jnp.sum(nsteps[:warmup])


_COMPILED: dict = {}


def unshear(y, ridge):
    """The samplers' coordinates ``x`` (:func:`~tofjax.fit.posterior.log_prob`'s) of NUTS's
    ridge coordinates ``y``, and ``log |det dx/dy|``. ``ridge = (b, e_i, a_ref, m, s, alpha)``
    (``e_i`` one-hot on the albedo's coordinate, ``b_i = 0``):

    1. the ridge's low end compressed: ``y_i = m + s T((y_i - m) / s)`` with ``T(v) = v`` for
       ``v >= 0`` and ``asinh(alpha v) / alpha`` below (C2 at 0; ``alpha = 0``: the identity);
    2. the shear ``x = y + b (a(y_i) - a_ref)``, ``a(w) = -softplus(-STEEP w) / STEEP`` the log
       albedo of its coordinate ``w``: triangular with unit diagonal (determinant 1). The other
       coordinates are measured from the ridge's line in log albedo, so where the albedo
       saturates at 1 (``w`` past 0) they stay at the ridge's end instead of running off it.

    Zeros for ``b``, ``e`` and ``alpha`` (``s = 1``): the identity."""
    b, e, a_ref, m, s, alpha = ridge
    yi = y @ e
    v = (yi - m) / s
    neg = jnp.minimum(v, 0.0)
    al = jnp.maximum(alpha, 1e-9)
    t = jnp.arcsinh(al * neg) / al + jnp.maximum(v, 0.0)
    log_jac = -0.5 * jnp.log1p((al * neg) ** 2)
    y = y + e * (m + s * t - yi)
    a = -jax.nn.softplus(-STEEP * (y @ e)) / STEEP
    return y + b * (a - a_ref), log_jac


def _identity(P):
    return (np.zeros(P), np.zeros(P), 0.0, 0.0, 1.0, 0.0)


def ridge_shear(coords, idx, centre, cov):
    """``(ridge, cov_y)``: the shear of :func:`unshear` about ``centre`` (on the albedo's
    coordinate: the one whose bound p = 1 ends the albedo / end reflectance / interface
    ridge; no compression yet, ``alpha = 0``) and the covariance ``cov`` carried to ``y``;
    the identity where the albedo is not sampled as log p. ``b``: each coordinate's
    regression on log albedo under ``cov``."""
    P = len(centre)
    if "albedo" not in coords or coords.index("albedo") not in idx:
        return _identity(P), cov
    i = coords.index("albedo")
    slope = 1.0 / (1.0 + np.exp(STEEP * centre[i]))  # da/dw at the centre
    b = cov[:, i] / (slope * cov[i, i])
    b[i] = 0.0
    e = np.zeros(P)
    e[i] = 1.0
    a_ref = -np.logaddexp(0.0, -STEEP * centre[i]) / STEEP
    jac = np.eye(P) - slope * np.outer(b, e)  # dy/dx at the centre
    cy = jac @ cov @ jac.T
    return (b, e, float(a_ref), float(centre[i]), float(np.sqrt(cy[i, i])), 0.0), 0.5 * (cy + cy.T)


def fit_tail(ridge, centre, logdensity, at: float = 2.0):
    """``ridge`` with ``alpha`` chosen so that the compressed coordinate sees the ridge's low
    end as a unit normal would at ``at`` standard deviations: where the log-density there
    (the albedo's coordinate ``at`` sd below ``centre``, the others on the ridge's line) has
    fallen by ``D`` more than the normal's ``at^2 / 2``, ``T(-sqrt(2 D)) = -at``. ``alpha = 0``
    where it has not (a tail as heavy as the normal's or heavier is left alone)."""
    b, e, a_ref, m, s, _ = ridge
    if not np.any(e):
        return ridge
    y = np.asarray(centre, np.float64) - at * s * e
    drop = float(logdensity(centre) - logdensity(_unshear_np(y, ridge)[0]))
    if not np.isfinite(drop):
        drop = 1e6
    if drop <= at * at / 2:
        return ridge
    v = np.sqrt(2.0 * drop)  # T(-v) = -at: asinh(alpha v) / alpha = at, decreasing in alpha
    lo, hi = 0.0, 1.0
    while np.arcsinh(hi * v) / hi > at:
        hi *= 2.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if np.arcsinh(mid * v) / mid > at else (lo, mid)
    return (b, e, a_ref, m, s, 0.5 * (lo + hi))


def _unshear_np(y, ridge):
    b, e, a_ref, m, s, alpha = ridge
    y = np.asarray(y, np.float64)
    yi = y @ e
    v = (yi - m) / s
    neg = np.minimum(v, 0.0)
    al = max(alpha, 1e-9)
    t = np.arcsinh(al * neg) / al + np.maximum(v, 0.0)
    y = y + e * (m + s * t - yi)[..., None]
    a = -np.logaddexp(0.0, -STEEP * (y @ e)) / STEEP
    return y + b * (a - a_ref)[..., None], -0.5 * np.log1p((al * neg) ** 2)


def _whitening(cov: np.ndarray) -> np.ndarray:
    """``L`` with ``L L^T = cov``, the Cholesky factor taken of the correlation matrix (each
    axis scaled first, so coordinates of very different scales stay well conditioned)."""
    scale = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    corr = cov / scale[:, None] / scale[None, :]
    return scale[:, None] * np.linalg.cholesky(corr + 1e-10 * np.eye(len(scale)))


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


def _threads(options: NutsOptions) -> int:
    import os

    n = options.threads if options.threads is not None else (os.cpu_count() or 1)
    return max(1, min(int(n), options.chains))


def _run_chains(compiled, chain_args, statics, threads: int) -> list:
    """Every chain's outputs (NumPy), in the chains' order, ``threads`` chains at a time. XLA's
    CPU runtime runs one chain's program (small, sequential: a NUTS trajectory) on about one
    core, and a call releases the GIL while it runs, so chains in threads use the other cores;
    vmapped instead, every chain's step would last as long as the longest chain's."""

    def one(a):
        return [np.asarray(x) for x in jax.block_until_ready(compiled(*a, *statics))]

    if threads <= 1 or len(chain_args) <= 1:
        return [one(a) for a in chain_args]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=threads) as pool:
        return list(pool.map(one, chain_args))


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
    ld = density if density is not None else log_density(calibrator, capture, fit, options.nuisance_width, options.hold, options.gain_prior)
    P = ld.flat0.size
    dtype = ld.args[1].dtype
    key = jax.random.PRNGKey(options.seed)
    k_start, k_chains, k_main = jax.random.split(key, 3)
    z0 = jax.random.normal(k_start, (options.chains, P), dtype)  # draws from the Laplace approximation
    statics = (options.warmup, options.draws, options.dense, float(options.target_accept), options.max_tree_depth, options.adapt_mass)
    pilot_statics = (options.pilot_warmup or options.warmup, options.pilot_draws or options.draws, options.dense,
                     float(options.target_accept), options.max_tree_depth, options.pilot_adapt_mass)
    compile_s = wall = 0.0
    warm_grads = 0
    if options.start == "mode":
        t = time.perf_counter()
        jax.block_until_ready(_value_and_grad(ld.problem, ld.template, ld.args, jnp.asarray(ld.flat0, dtype), ld.idx))
        compile_s += time.perf_counter() - t
        t = time.perf_counter()
        centre, cov, mode_info = posterior_mode(ld)
        wall += time.perf_counter() - t
        mode_info["seconds"] = time.perf_counter() - t
        grads = mode_info["gradient_evaluations"]
    else:
        centre, cov, mode_info, grads = ld.flat0, ld.laplace_cov, {"used": "fit"}, 0
    ridge, cov = ridge_shear(ld.coords, ld.idx, np.asarray(centre, np.float64), cov) if options.shear else (_identity(P), cov)
    if options.shear and options.ridge_tail:
        t = time.perf_counter()
        ridge = fit_tail(ridge, np.asarray(centre, np.float64), lambda f: float(_value_and_grad(
            ld.problem, ld.template, ld.args, jnp.asarray(f, dtype), ld.idx)[0]))
        grads += 2
        wall += time.perf_counter() - t
        mode_info["ridge_tail_alpha"] = ridge[5]
    chol = _whitening(cov)
    ridge_j = tuple(jnp.asarray(x, dtype) for x in ridge)
    runs = [k_chains, k_main] if options.pilot else [k_chains]
    for i, k in enumerate(runs):
        keys = jax.random.split(k, options.chains)
        chain_args = [(ld.problem, ld.template, ld.args, ld.idx, jnp.asarray(centre, dtype), jnp.asarray(chol, dtype),
                       keys[c], jnp.asarray(z0[c], dtype), ridge_j) for c in range(options.chains)]
        st = pilot_statics if i + 1 < len(runs) else statics
        t = time.perf_counter()
        compiled = _compiled(chain_args[0], st)  # one compiled program serves every chain (and the pilot, if its lengths are the run's)
        compile_s += time.perf_counter() - t
        t = time.perf_counter()
        outs = _run_chains(compiled, chain_args, st, _threads(options))
        wall += time.perf_counter() - t
        zs, div, nsteps, acc, depth_used, step_size, warm_steps = (np.stack(x) for x in zip(*outs))
        grads += int(nsteps.sum() + warm_steps.sum())
        warm_grads += int(warm_steps.sum()) + (int(nsteps.sum()) if i + 1 < len(runs) else 0)
        if i + 1 < len(runs):  # the pilot: whiten the run by its draws' mean and covariance
            flats = centre[None, None, :] + np.einsum("ij,cnj->cni", chol, zs)  # sheared (y)
            pooled = flats.reshape(-1, P)
            c = np.cov(pooled.T).reshape(P, P)
            if np.all(np.isfinite(c)) and np.linalg.eigvalsh(c).min() > 0:
                centre, chol = pooled.mean(0), _whitening(c)
                z0 = np.linalg.solve(chol, (flats[:, -1, :] - centre).T).T  # continue from the pilot's last draws
    C, N = zs.shape[:2]
    flats = _unshear_np(centre[None, None, :] + np.einsum("ij,cnj->cni", chol, zs), ridge)[0]
    phys = ld.to_physical(flats.reshape(C * N, P)).reshape(C, N, -1)
    diag = diagnostics(ld.names, phys)
    return NutsResult(
        names=ld.names,
        samples=phys.reshape(C * N, -1),
        chains_physical=phys,
        chains_unconstrained=ld.to_fit(flats),
        coords=ld.coords,
        divergences=int(div.sum()),
        step_size=np.asarray(step_size, np.float64),
        mean_tree_depth=float(depth_used.mean()),
        mean_accept=float(acc.mean()),
        gradient_evaluations=grads,
        wall_s=wall,
        compile_s=compile_s,
        diagnostics=diag,
        options=options,
        start_info=mode_info,
        warmup_gradient_evaluations=warm_grads,
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
