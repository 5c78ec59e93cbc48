"""Calibration: fit n1, mu_s, mu_a and the nuisance parameters to a baseline capture.

Residuals are Poisson-weighted, ``(model - mean) / sqrt(max(mean, 1) / frames)``,
so they are O(1) and ``sum(r^2) / dof`` is a reduced chi-square. Parameters
are fitted in an unconstrained space (:mod:`tofjax.fit.transforms`). The start
comes from the data: the emission time from the light-entry peak, ambient from
the bins before it, n1 from the far-edge peak's time, amplitudes from a fit of
the linear parameters alone; then a fit with a widened pulse, then the real
one (coarse to fine), so the narrow far-edge peak cannot trap the fit.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..capture import Capture
from ..config import ConfigError, from_dict, load_toml
from ..errors import UserError
from ..model import SPEED_OF_LIGHT_M_PER_S, ModelOptions, Params, build_model
from ..scene import Scene
from .solve import SolveResult, dense_jvp, solve_with_history
from .transforms import FITTABLE, default_transforms

__all__ = ["CalibrationError", "CalibrationResult", "Calibrator", "FitConfig", "calibrate", "load_fit_config"]

SOLVERS = ("levenberg-marquardt", "gauss-newton", "dogleg", "poisson-deviance")
DEFAULT_FREE = (
    "n1",
    "mu_s_per_m",
    "mu_a_per_m",
    "gain",
    "ambient_counts",
    "crosstalk_counts",
    "pulse_sigma_s",
    "pulse_tail_s",
    "emission_time_s",
    "interface_backscatter_per_m",
    "end_reflectance",
)
#: Parameters that scale the histogram linearly: fitted first, alone, for a robust start.
LINEAR = ("gain", "ambient_counts", "crosstalk_counts")


class CalibrationError(UserError):
    """The data cannot be calibrated as given (wrong scene, not a baseline, bad counts)."""


@dataclass(frozen=True)
class FitConfig:
    """Options of a calibration fit (TOML: ``[fit]`` keys at the top level of the file).

    - ``solver``: ``levenberg-marquardt`` (default), ``gauss-newton``, ``dogleg``,
      or ``poisson-deviance`` (BFGS on the Poisson deviance instead of least squares).
    - ``rtol``, ``atol``: optimistix tolerances in the unconstrained space.
    - ``loss_tol``: also stop when an accepted step lowers chi-square / 2 by less than
      this (default 1e-3: the fit is then within a few hundredths of a standard error of
      the optimum, see ``experiments/study_fit_speed.py``; the parameter tolerances
      alone take two to five times more steps in the flat mu_s / mu_a valley). 0 turns it off.
    - ``gauss_newton_first``: up to this many undamped Gauss-Newton steps first (for the
      ``levenberg-marquardt`` and ``dogleg`` solvers): from the data-driven start they reach
      the optimum in 3-6 steps where the damped solvers crawl along the curved valleys
      (gain against interface backscatter, end reflectance and albedo) for 20-100. Where
      they fail, or do not lower the loss, the configured solver takes over. 0 = off.
    - ``max_steps``: per stage.
    - ``free``: which parameters to fit; the rest stay at the scene's values.
    - ``multistart``: extra starts with n1 jittered by +-10%; the best fit wins.
    - ``coarse_to_fine``: first fit with a pulse three times wider (off by default: the start
      from the data already puts n1 within a few per cent, and a widened pulse lets the
      near-field terms wander on the default scene).
    - ``quadrature``: model fidelity (time nodes per bin).
    - ``dtype``: ``float64`` (default) or ``float32`` for the model (the solver's own
      variables stay in the default float precision). float32 is faster per step, but
      its rounding (~1e-7 relative) limits how far the tolerances can be met.
    - ``max_reduced_chi2``: above this the capture is not taken for a baseline.
    - ``prior_width``: width of a weak Gaussian prior on each nonlinear parameter in the
      unconstrained space (3 = a factor e^3 ~ 20 for log-scaled ones), centred on the
      scene's values; it keeps weakly determined parameters finite. 0 turns it off.
    """

    solver: str = "levenberg-marquardt"
    rtol: float = 1e-7
    atol: float = 1e-7
    loss_tol: float = 1e-3
    max_steps: int = 200
    gauss_newton_first: int = 10
    free: tuple[str, ...] = DEFAULT_FREE
    multistart: int = 0
    multistart_seed: int = 0
    coarse_to_fine: bool = False
    prior_width: float = 3.0
    quadrature: int = 2
    dtype: str = "float64"
    max_reduced_chi2: float = 4.0

    def __post_init__(self):
        if self.solver not in SOLVERS:
            raise ConfigError(f"solver: must be one of {', '.join(SOLVERS)}, got {self.solver!r}")
        if self.loss_tol < 0:
            raise ConfigError(f"loss_tol: must be >= 0, got {self.loss_tol!r}")
        if self.prior_width < 0:
            raise ConfigError(f"prior_width: must be >= 0, got {self.prior_width!r}")
        for k in ("rtol", "atol", "max_reduced_chi2"):
            if getattr(self, k) <= 0:
                raise ConfigError(f"{k}: must be > 0, got {getattr(self, k)!r}")
        if self.max_steps < 1:
            raise ConfigError(f"max_steps: must be >= 1, got {self.max_steps!r}")
        if self.gauss_newton_first < 0:
            raise ConfigError(f"gauss_newton_first: must be >= 0, got {self.gauss_newton_first!r}")
        if self.multistart < 0:
            raise ConfigError(f"multistart: must be >= 0, got {self.multistart!r}")
        if self.dtype not in ("float32", "float64"):
            raise ConfigError(f"dtype: must be float32 or float64, got {self.dtype!r}")
        if self.quadrature < 1:
            raise ConfigError(f"quadrature: must be >= 1, got {self.quadrature!r}")
        for name in self.free:
            if name not in FITTABLE:
                raise ConfigError(f"free: {name!r} cannot be fitted; fittable: {', '.join(FITTABLE)}")
        if not self.free:
            raise ConfigError("free: at least one parameter must be free")
        if all(name in LINEAR for name in self.free):
            raise ConfigError(
                "free: at least one of n1, mu_s_per_m, mu_a_per_m, the pulse, the emission time or the "
                "reflectances must be free (gain, ambient and crosstalk alone are a linear solve, not a fit)"
            )

    def make_solver(self):
        if self.solver == "levenberg-marquardt":
            return optx.LevenbergMarquardt(rtol=self.rtol, atol=self.atol)
        if self.solver == "gauss-newton":
            return optx.GaussNewton(rtol=self.rtol, atol=self.atol)
        if self.solver == "dogleg":
            return optx.Dogleg(rtol=self.rtol, atol=self.atol)
        return optx.BFGS(rtol=self.rtol, atol=self.atol)


def load_fit_config(path) -> FitConfig:
    """Read a fit config TOML; errors name the file and the key."""
    try:
        return from_dict(FitConfig, load_toml(path))
    except ConfigError as e:
        msg = str(e)
        raise ConfigError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None


@dataclass
class CalibrationResult:
    """A finished fit, in physical units."""

    params: Params  # every model parameter, fitted ones replaced
    free: tuple[str, ...]
    values: dict[str, np.ndarray]
    stderr: dict[str, np.ndarray]
    interval95: dict[str, tuple[np.ndarray, np.ndarray]]  # Laplace, symmetric in the unconstrained space
    covariance: np.ndarray  # physical units, over the flattened free parameters
    labels: list[str]  # one per row of ``covariance``
    converged: bool
    result: str
    steps: int
    reduced_chi2: float
    loss_history: list[float]
    solver: str
    frames: int
    stages: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    #: Laplace standard errors in the fit's unconstrained coordinates (posterior walkers start from them)
    unconstrained_stderr: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        def pack(k):
            lo, hi = self.interval95[k]
            return {
                "value": np.asarray(self.values[k]).tolist(),
                "stderr": np.asarray(self.stderr[k]).tolist(),
                "interval95": [np.asarray(lo).tolist(), np.asarray(hi).tolist()],
            }

        return {
            "parameters": {k: pack(k) for k in self.free},
            "units": {k: FITTABLE[k] for k in self.free},
            "covariance": {"labels": self.labels, "matrix": np.asarray(self.covariance).tolist()},
            "converged": self.converged,
            "result": self.result,
            "steps": self.steps,
            "reduced_chi2": self.reduced_chi2,
            "loss_history": self.loss_history,
            "solver": self.solver,
            "frames": self.frames,
            "stages": self.stages,
            "fixed": {
                f.name: np.asarray(getattr(self.params, f.name)).tolist()
                for f in dataclasses.fields(self.params)
                if f.name not in self.free and not f.name.startswith("touch_")
            },
        }


def fit_report(result: CalibrationResult) -> str:
    """A short text table: each parameter with its standard error and Laplace 95% interval."""
    lines = [
        f"calibration: {'converged' if result.converged else 'NOT converged'} ({result.result}) after "
        f"{result.steps} steps, {result.solver}, {result.frames} frames, reduced chi-square {result.reduced_chi2:.3f}",
        f"{'parameter':30s} {'value':>12s} {'stderr':>10s}   95% interval (Laplace)",
    ]
    for k in result.free:
        v, e = np.ravel(result.values[k]), np.ravel(result.stderr[k])
        lo, hi = (np.ravel(x) for x in result.interval95[k])
        unit = FITTABLE[k]
        if v.size == 1:
            lines.append(f"{k:30s} {v[0]:12.6g} {e[0]:10.3g}   [{lo[0]:.6g}, {hi[0]:.6g}] {unit}")
        else:
            lines.append(
                f"{k + f' ({v.size})':30s} {np.mean(v):12.6g} {np.mean(e):10.3g}   values {v.min():.4g} .. {v.max():.4g} {unit}"
            )
    i = result.labels.index("mu_s_per_m") if "mu_s_per_m" in result.labels else None
    j = result.labels.index("mu_a_per_m") if "mu_a_per_m" in result.labels else None
    if i is not None and j is not None:
        c = result.covariance
        corr = c[i, j] / np.sqrt(c[i, i] * c[j, j]) if c[i, i] > 0 and c[j, j] > 0 else float("nan")
        lines.append(
            f"correlation(mu_s, mu_a) = {corr:+.2f}"
            + ("  (strong: a baseline alone barely separates scattering from absorption)" if abs(corr) > 0.8 else "")
        )
    return "\n".join(lines)


# ---- checks -------------------------------------------------------------------------------


def check_baseline(capture: Capture, scene: Scene) -> None:
    """Refuse data that cannot be a usable baseline, with the reason."""
    h = capture.histograms
    if scene.shape != capture.scene.shape:
        raise CalibrationError(
            f"the scene has (sensors, zones, bins) = {scene.shape} but the capture {capture.scene.shape}"
        )
    if capture.n_frames < 1:
        raise CalibrationError("the capture has no frames")
    if not np.isfinite(h).all():
        bad = np.argwhere(~np.isfinite(h))[0]
        raise CalibrationError(f"non-finite counts (NaN or inf), first at frame {bad[0]}, sensor {bad[1]}, zone {bad[2]}")
    if (h < 0).any():
        raise CalibrationError("negative counts: these are not raw histograms")
    per_zone = h.sum(axis=(0, 3))
    if (per_zone == 0).any():
        s, z = np.argwhere(per_zone == 0)[0]
        raise CalibrationError(f"all-zero histograms (sensor {s}, zone {z}): is the sensor connected?")
    sat = scene.sensor.saturation_counts
    n_sat = int((h >= sat).sum())
    if n_sat:
        raise CalibrationError(
            f"{n_sat} bins at the saturation limit ({sat:g} counts): lower the sensor's iterations or gain"
        )


# ---- the fit ------------------------------------------------------------------------------


class _Problem:
    """The residual function of a fit, with the linear parameters profiled out.

    The model is ``gain[s] R + crosstalk[s, z] P + ambient[s, z]`` with ``R`` and
    ``P`` nonlinear in the rest (:meth:`ForwardModel.linear_parts`). For given
    nonlinear parameters the best linear ones solve a small weighted least-squares
    problem per sensor (1 + 2 zones unknowns), so the solver only sees the few
    nonlinear parameters (variable projection); JAX differentiates through the
    solve, which gives the exact variable-projection Jacobian.
    """

    def __init__(self, scene: Scene, free: tuple[str, ...], data, frames: int, opts: ModelOptions, prior_width: float):
        self.transforms = default_transforms(scene)
        self.dtype = opts.jnp_dtype
        self.model = build_model(scene.without_touches(), opts)
        comps = self.model.components
        present = {"gain": True, "crosstalk_counts": "crosstalk" in comps, "ambient_counts": "ambient" in comps}
        self.linear = tuple(p for p in LINEAR if p in free and present[p])
        self.nonlinear = tuple(p for p in free if p not in LINEAR)
        self.free = tuple(free)
        self.set_data(data, frames)
        self._solvers: dict = {}
        self.prior_width = prior_width
        # the profile of a start point, jitted (run eagerly it dispatches the model op by op: seconds)
        self.profile_jit = jax.jit(lambda p, d, s: self.profile(p, d, s))
        self.model_jit = jax.jit(lambda p: self.model(p))

    def set_data(self, data, frames: int) -> None:
        """New data of the same shape: the compiled solves are reused."""
        self.data = jnp.asarray(data, self.dtype)
        self.frames = frames
        self.sigma = jnp.sqrt(jnp.maximum(self.data, 1.0) / frames)

    # mu_s and mu_a are fitted as extinction mu_t = mu_s + mu_a (log) and albedo
    # mu_s / mu_t (logit): a baseline pins mu_t far better than the split, and in
    # (log mu_s, log mu_a) that makes a curved valley (log(e^a + e^b) = const) in which
    # Gauss-Newton steps overshoot and Levenberg-Marquardt crawls (~100 steps); in
    # (mu_t, albedo) the valley is straight. Results are reported as mu_s and mu_a.
    JOINT = ("mu_s_per_m", "mu_a_per_m")

    def pack(self, params: Params, names=None) -> dict[str, jax.Array]:
        """Unconstrained coordinates of the physical parameters ``names`` (default: the nonlinear ones)."""
        names = self.nonlinear if names is None else names
        joint = all(j in names for j in self.JOINT)
        u = {
            k: jnp.asarray(self.transforms[k].to_unconstrained(np.asarray(getattr(params, k))))
            for k in names
            if not (joint and k in self.JOINT)
        }
        if joint:
            mu_s = max(float(params.mu_s_per_m), 1e-12)
            mu_a = max(float(params.mu_a_per_m), 1e-12)
            u["extinction"] = jnp.asarray(math.log(mu_s + mu_a))
            u["albedo"] = jnp.asarray(math.log(mu_s) - math.log(mu_a))
        return u

    def physical(self, u) -> dict[str, jax.Array]:
        """Physical values of the parameters whose coordinates ``u`` holds (jit- and grad-safe)."""
        out = {k: self.transforms[k].to_physical(v) for k, v in u.items() if k not in ("extinction", "albedo")}
        if "extinction" in u:
            mu_t = jnp.exp(u["extinction"])
            albedo = jax.nn.sigmoid(u["albedo"])
            out["mu_s_per_m"] = mu_t * albedo
            out["mu_a_per_m"] = mu_t * (1.0 - albedo)
        return out

    def unpack(self, u, base: Params) -> Params:
        return base.replace(**self.physical(u))

    def pack_jax(self, params: Params, names) -> dict[str, jax.Array]:
        """:meth:`pack` in JAX (jit-safe), in the default float precision."""
        ft = jnp.result_type(float)
        joint = all(j in names for j in self.JOINT)
        u = {
            k: self.transforms[k].unconstrain(jnp.asarray(getattr(params, k), ft))
            for k in names
            if not (joint and k in self.JOINT)
        }
        if joint:
            mu_s = jnp.maximum(jnp.asarray(params.mu_s_per_m, ft), 1e-12)
            mu_a = jnp.maximum(jnp.asarray(params.mu_a_per_m, ft), 1e-12)
            u["extinction"] = jnp.log(mu_s + mu_a)
            u["albedo"] = jnp.log(mu_s) - jnp.log(mu_a)
        return u

    def profile_parts(self, params: Params, data, sigma):
        """Closed-form variable projection: ``(params with the best linear parameters, the
        model at them, sum_s log det(A_s^T W A_s))``.

        Per sensor the model is ``K R + x_z P_z + a_z`` (gain shared by the zones, light
        entry and ambient per zone). The zone unknowns are eliminated with an explicit 2 x 2
        solve per zone, then the gain from its Schur complement (a scalar per sensor): only
        weighted sums over bins, no batched LU (whose forward-mode derivative cost many
        times the model on CPU). One evaluation of ``linear_parts`` gives the residuals too.
        """
        R, P = self.model.linear_parts(params)
        comps = self.model.components
        w = 1.0 / sigma**2
        fixed = jnp.zeros_like(R)
        if "gain" not in self.linear:
            fixed = fixed + params.gain[:, None, None] * R
        if "crosstalk" in comps and "crosstalk_counts" not in self.linear:
            fixed = fixed + params.crosstalk_counts[..., None] * P
        if "ambient" in comps and "ambient_counts" not in self.linear:
            fixed = fixed + params.ambient_counts[..., None]
        y = data - fixed
        basis = []
        if "crosstalk_counts" in self.linear:
            basis.append(P)
        if "ambient_counts" in self.linear:
            basis.append(jnp.ones_like(R))

        def ip(a, b):  # weighted inner product over bins: (S, Z)
            return jnp.sum(w * a * b, axis=-1)

        logdet = jnp.zeros((), R.dtype)
        m = len(basis)
        if m == 1:
            g = ip(basis[0], basis[0])
            g = g + 1e-12 * g + jnp.finfo(R.dtype).tiny
            ginv = [[1.0 / g]]
            logdet = logdet + jnp.sum(jnp.log(g))
        elif m == 2:
            a, b, c = ip(basis[0], basis[0]), ip(basis[0], basis[1]), ip(basis[1], basis[1])
            ridge = 1e-12 * (a + c) + jnp.finfo(R.dtype).tiny
            a, c = a + ridge, c + ridge
            det = a * c - b * b
            ginv = [[c / det, -b / det], [-b / det, a / det]]
            logdet = logdet + jnp.sum(jnp.log(det))

        def zone_coefs(v):
            proj = [ip(bi, v) for bi in basis]
            return [sum(ginv[i][j] * proj[j] for j in range(m)) for i in range(m)]

        def q_ip(u, v):  # <u, (I - projection onto the zone basis) v>
            out = ip(u, v)
            if m:
                cv = zone_coefs(v)
                out = out - sum(ip(u, basis[i]) * cv[i] for i in range(m))
            return out

        out, fitted = {}, fixed
        if "gain" in self.linear:
            rr = jnp.sum(q_ip(R, R), axis=1)  # (S,)
            rr = rr + jnp.finfo(R.dtype).tiny
            gain = jnp.sum(q_ip(R, y), axis=1) / rr
            out["gain"] = gain
            fitted = fitted + gain[:, None, None] * R
            logdet = logdet + jnp.sum(jnp.log(rr))
            y = y - gain[:, None, None] * R
        if m:
            coefs = zone_coefs(y)
            names = [k for k in ("crosstalk_counts", "ambient_counts") if k in self.linear]
            for k, coef, bi in zip(names, coefs, basis):
                out[k] = coef
                fitted = fitted + coef[..., None] * bi
        return params.replace(**out), fitted, logdet

    def profile(self, params: Params, data=None, sigma=None, with_logdet: bool = False):
        """``params`` with the free linear parameters at their weighted least-squares values.

        With ``with_logdet`` also returns ``sum_s log det(A_s^T W A_s)``: integrating the
        linear parameters out of the Gaussian likelihood (flat priors) multiplies the
        profile likelihood by ``det^-1/2``, which the posterior uses."""
        data = self.data if data is None else data
        sigma = self.sigma if sigma is None else sigma
        if not self.linear:
            return (params, jnp.zeros((), params.n1.dtype)) if with_logdet else params
        p, _, logdet = self.profile_parts(params, data, sigma)
        return (p, logdet) if with_logdet else p

    def prior_residuals(self, u, prior):
        """A weak Gaussian prior in the unconstrained space, ``(u - prior) / width``, on the
        nonlinear parameters: it keeps a parameter the data cannot pin (mu_a -> 0 in log
        space) from running off to infinity, and barely moves well-determined ones."""
        if self.prior_width <= 0:
            return jnp.zeros((0,), jnp.result_type(float))
        parts = [jnp.ravel((u[k] - prior[k]) / self.prior_width) for k in sorted(u) if k not in self.linear]
        return jnp.concatenate(parts) if parts else jnp.zeros((0,), jnp.result_type(float))

    def _profiled_model(self, u, base, data, sigma):
        params = self.unpack(u, base)
        if not self.linear:
            return params, self.model(params)
        p, m, _ = self.profile_parts(params, data, sigma)
        return p, m

    def residuals(self, u, args):
        """Profiled residuals; ``args = (base params, mean data, sigma, prior centre)``."""
        base, data, sigma, prior = args
        _, m = self._profiled_model(u, base, data, sigma)
        data_part = ((m - data) / sigma).ravel()
        return jnp.concatenate([data_part.astype(jnp.result_type(float)), self.prior_residuals(u, prior)])

    def full_residuals(self, u, base, prior, data=None, sigma=None):
        """Residuals with every free parameter explicit (for the covariance), prior included.
        Jitted callers pass ``data`` and ``sigma``: read from ``self`` inside a trace they
        would be frozen into the compiled function and go stale after :meth:`set_data`."""
        data = self.data if data is None else data
        sigma = self.sigma if sigma is None else sigma
        data_part = ((self.model(self.unpack(u, base)) - data) / sigma).ravel()
        return jnp.concatenate([data_part.astype(jnp.result_type(float)), self.prior_residuals(u, prior)])

    def _covariance_jacobian(self, params: Params, prior_params: Params, data, sigma):
        """Jacobian of :meth:`full_residuals` over every free coordinate (columns in
        ``ravel_pytree`` order), in JAX. The nonlinear columns come from forward-mode AD;
        the linear ones (gain, crosstalk, ambient: one per sensor or zone, most of the
        columns) are written down from ``linear_parts``, which is much cheaper."""
        u = self.pack_jax(params, self.free)
        prior = self.pack_jax(prior_params, self.free)
        lin = {k: u[k] for k in u if k in LINEAR}
        nl = {k: u[k] for k in u if k not in LINEAR}
        f_nl, unravel_nl = jax.flatten_util.ravel_pytree(nl)
        j_nl = jax.jacfwd(lambda g: self.full_residuals({**unravel_nl(g), **lin}, params, prior, data, sigma))(f_nl)
        n_rows = j_nl.shape[0]
        R, P = self.model.linear_parts(params)
        S, Z, B = R.shape
        ft = j_nl.dtype
        R, P, sig = R.astype(ft), P.astype(ft), jnp.asarray(sigma, ft)
        cols, pos = {}, 0
        for k in sorted(nl):
            n = int(np.size(nl[k]))
            cols[k] = j_nl[:, pos : pos + n]
            pos += n
        eye_s, eye_z = jnp.eye(S, dtype=ft), jnp.eye(Z, dtype=ft)
        comps = self.model.components
        for k, uk in lin.items():
            dxdu = self.transforms[k].derivative(uk)
            if k == "gain":
                block = jnp.einsum("szb,st->szbt", R / sig, eye_s * dxdu[None, :]).reshape(S * Z * B, S)
            elif (k == "crosstalk_counts" and "crosstalk" in comps) or (k == "ambient_counts" and "ambient" in comps):
                part = P if k == "crosstalk_counts" else jnp.ones_like(R)
                block = jnp.einsum("szb,st,zy->szbty", part / sig, eye_s, eye_z) * dxdu[None, None, None]
                block = block.reshape(S * Z * B, S * Z)
            else:
                block = jnp.zeros((S * Z * B, int(np.size(uk))), ft)
            cols[k] = jnp.concatenate([block, jnp.zeros((n_rows - S * Z * B, block.shape[1]), ft)])
        return jnp.concatenate([cols[k] for k in sorted(u)], axis=1)

    def covariance_jacobian(self, params: Params, prior_params: Params) -> np.ndarray:
        """:meth:`_covariance_jacobian` at ``params`` on the current data (jitted, for tests)."""
        key = ("covariance", self.free)
        if key not in self._solvers:
            self._solvers[key] = jax.jit(self._covariance_jacobian)
        return np.asarray(self._solvers[key](params, prior_params, self.data, self.sigma))

    def _laplace(self, params: Params, prior_params: Params, data, sigma):
        """``J^T J`` of the full residuals over every free coordinate, and the Jacobian of the
        physical values (in ``sorted(free)`` order) over those coordinates."""
        jac = self._covariance_jacobian(params, prior_params, data, sigma)
        u = self.pack_jax(params, self.free)
        flat, unravel = jax.flatten_util.ravel_pytree(u)
        names = sorted(self.free)

        def phys_flat(f):
            x = self.physical(unravel(f))
            return jnp.concatenate([jnp.ravel(x[k]) for k in names])

        return jac.T @ jac, jax.jacfwd(phys_flat)(flat), flat

    def deviance(self, u, args):
        """Poisson deviance per bin of the profiled model (for the minimiser option), plus the prior."""
        base, d, sigma, prior = args
        _, m = self._profiled_model(u, base, d, sigma)
        mu = jnp.maximum(m, 1e-9)
        term = mu - d + jnp.where(d > 0, d * jnp.log(jnp.where(d > 0, d, 1.0) / mu), 0.0)
        # the frame count from the traced arguments (sigma^2 = max(d, 1) / frames, see
        # set_data), not from self: read from self it would be frozen into the compiled fit
        # and go stale for a capture with another number of frames
        frames = jnp.mean(jnp.maximum(d, 1.0) / sigma**2)
        return (2.0 * frames * jnp.sum(term) + jnp.sum(self.prior_residuals(u, prior) ** 2)) / d.size

    def core_for(
        self, names: tuple[str, ...], solver, max_steps: int, minimise: bool, loss_tol: float, with_cov: bool, gn_first: int = 0
    ):
        """The whole fit from a start as one compiled function (compiled once per setting, reused
        for every capture of the same shape): profile the start, solve (``gn_first``: a
        Gauss-Newton fast path first), profile the end point, chi-square, and (``with_cov``)
        what the Laplace covariance needs."""
        key = ("core", names, repr(solver), max_steps, minimise, loss_tol, with_cov, gn_first)
        if key in self._solvers:
            return self._solvers[key]
        target = self.deviance if minimise else self.residuals
        # the deviance loss is chi-square per bin: the same tolerance in its units
        tol = 2.0 * loss_tol / self.data.size if minimise else loss_tol

        def core(start: Params, data, sigma, prior_params: Params):
            p0 = self.profile(start, data, sigma)
            u0 = self.pack_jax(p0, names)
            prior = self.pack_jax(prior_params, names)
            f0, unravel = jax.flatten_util.ravel_pytree(u0)
            args = (p0, data, sigma, prior)
            # the solver works on the flat vector of unconstrained coordinates
            def flat_target(f, a):
                return target(unravel(f), a)

            fn = flat_target if minimise else dense_jvp(flat_target)
            v0 = f0

            def main(v_start):
                return solve_with_history(fn, solver, v_start, args, max_steps=max_steps, minimise=minimise, loss_tol=tol)

            if gn_first:
                # the fast path: undamped Gauss-Newton steps from the data-driven start (the first
                # one may overshoot along the curved valleys; the next one lands near the optimum);
                # the configured solver runs only where they fail or do not lower the loss
                gn = solve_with_history(
                    fn, optx.GaussNewton(rtol=solver.rtol, atol=solver.atol), v0, args, max_steps=gn_first, loss_tol=tol
                )
                hist = gn.history
                last = hist[jnp.clip(gn.steps, 0, gn_first)]
                ok = (gn.result == optx.RESULTS.successful) & jnp.isfinite(last) & (last <= hist[0])
                ok = ok & jnp.all(jnp.isfinite(gn.value))
                better = jnp.isfinite(last) & (last < hist[0]) & jnp.all(jnp.isfinite(gn.value))
                pad = jnp.full((max_steps + 1,), jnp.nan, hist.dtype)

                def done(_):
                    return gn.value, gn.result, gn.steps, jnp.concatenate([hist[: gn_first + 1], pad])

                def fallback(_):
                    o = main(jnp.where(better, gn.value, v0))
                    return o.value, o.result, gn.steps + o.steps, jnp.concatenate([hist[: gn_first + 1], o.history])

                value, result, steps, history = jax.lax.cond(ok, done, fallback, None)
                out = SolveResult(value, result, steps, history)
            else:
                out = main(v0)
            u = unravel(out.value)
            params, m = self._profiled_model(u, p0, data, sigma)
            res = {
                "params": params,
                "result": out.result,
                "steps": out.steps,
                "history": out.history,
                "chi2": jnp.sum(((m - data) / sigma) ** 2),
            }
            if with_cov:
                res["hessian"], res["dphys"], res["u_flat"] = self._laplace(params, prior_params, data, sigma)
            return res

        self._solvers[key] = jax.jit(core)
        return self._solvers[key]

    def reference_estimates(self, scene: Scene, base: Params, frames: int):
        """What the start's estimators read from the model at the scene's own values (cached):
        their bias, taken out of the estimates from data."""
        key = ("reference", frames)
        if key not in self._solvers:
            ref = np.asarray(self.model_jit(base), np.float64)
            self._solvers[key] = _edge_estimates(ref, frames, scene, float(base.pulse_tail_s))
        return self._solvers[key]


def _edge_estimates(d: np.ndarray, frames: int, scene: Scene, tau: float):
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
    # ambient: bins well before the light-entry peak, else the last tenth of the histogram
    pre = max(peak - 4, 0)
    if pre >= 3:
        ambient = np.median(d[..., :pre], axis=-1)
    else:
        ambient = np.median(d[..., -max(B // 10, 3) :], axis=-1)
    w = np.clip(total[lo:hi] - ambient.sum(), 0, None)
    centre = (np.sum(w * (np.arange(lo, hi) + 0.5)) / max(w.sum(), 1e-12)) * width
    t_e = max(centre - tau, 0.0)
    # n1: the far-edge bump of each zone, where counts rise again after the decay
    length = _mean_ray_length(scene)  # (S, Z)
    c = SPEED_OF_LIGHT_M_PER_S
    a = ((t_e + 2 * length * 1.0 / c) / width).astype(int) + 1
    b = np.minimum(((t_e + 2 * length * 3.5 / c) / width).astype(int) + 3, B - 1)
    x = d - ambient[..., None]
    # rise over the minimum of the four bins before (inf where there are none)
    pad = np.concatenate([np.full((S, Z, 4), np.inf), x], axis=-1)
    before = np.min(np.stack([pad[..., k : k + B] for k in range(4)]), axis=0)
    rise = x - before
    idx = np.arange(B)
    window = (idx >= a[..., None]) & (idx < b[..., None]) & (length[..., None] > 0) & ((b - a)[..., None] >= 3)
    rise = np.where(window & np.isfinite(rise), rise, -np.inf)
    i = np.argmax(rise, axis=-1)  # (S, Z)
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


_RAY_LENGTHS: dict = {}


def _mean_ray_length(scene: Scene) -> np.ndarray:
    """Mean far-edge distance of each zone's rays (S, Z), cached per scene."""
    from ..model.geometry import Geometry

    key = id(scene)
    if key not in _RAY_LENGTHS or _RAY_LENGTHS[key][0] is not scene:
        geom = Geometry.from_scene(scene, 8, np.float64)
        _RAY_LENGTHS[key] = (scene, np.asarray(geom.ray_length).mean(-1))
    return _RAY_LENGTHS[key][1]


def _initial_params(capture: Capture, scene: Scene, base: Params, reference=None) -> Params:
    """A start from the data: emission time, ambient, n1 from the far-edge peak.

    ``reference``: the same estimates read from the model at ``base`` (see
    :meth:`_Problem.reference_estimates`); their offsets from ``base`` (the estimators'
    bias: the pulse's peak is not its mean) are taken out of the estimates from data."""
    tau = float(base.pulse_tail_s)
    t_e, ambient, n1 = _edge_estimates(capture.mean(), capture.n_frames, scene, tau)
    if reference is not None:
        ref_t_e, _, ref_n1 = reference
        t_e = max(t_e + float(base.emission_time_s) - ref_t_e, 0.0)
        if n1 is not None and ref_n1 is not None:
            n1 = n1 + float(base.n1) - ref_n1
    n1 = float(base.n1) if n1 is None else float(np.clip(n1, 1.01, 3.9))
    return base.replace(
        emission_time_s=t_e,
        ambient_counts=np.maximum(ambient, 0.1),
        n1=n1,
        mu_s_per_m=max(float(base.mu_s_per_m), 1e-3),
        mu_a_per_m=max(float(base.mu_a_per_m), 1e-3),
    )


def _covariance(problem: _Problem, params: Params, hessian, dphys, u_flat) -> tuple[np.ndarray, list[str], dict, dict, dict]:
    """Laplace covariance of every free parameter (linear ones included) from ``J^T J`` of the
    full residuals at the optimum, carried to physical units with ``dphys``."""
    u_sizes = {k: int(np.size(getattr(params, k))) for k in problem.free if k not in problem.JOINT}
    if all(j in problem.free for j in problem.JOINT):
        u_sizes |= {"extinction": 1, "albedo": 1}
    else:
        u_sizes |= {k: 1 for k in problem.JOINT if k in problem.free}
    cov_u = np.linalg.pinv(np.asarray(hessian, np.float64), hermitian=True)
    d = np.asarray(dphys, np.float64)  # d physical / d unconstrained
    cov = d @ cov_u @ d.T
    names = sorted(problem.free)
    x_flat = np.concatenate([np.ravel(np.asarray(getattr(params, k), np.float64)) for k in names])
    stderr_flat = np.sqrt(np.clip(np.diag(cov), 0, None))
    stderr, interval, u_stderr, labels, pos = {}, {}, {}, [], 0
    for k in names:
        shape = np.shape(getattr(params, k))
        n = int(np.prod(shape))
        x = x_flat[pos : pos + n].reshape(shape)
        stderr[k] = stderr_flat[pos : pos + n].reshape(shape)
        # the 95% interval is symmetric in the parameter's own unconstrained space
        # (log, logit), so it respects bounds; its width there is the delta method's.
        t = problem.transforms[k]
        w = t.to_unconstrained(x)
        sw = stderr[k] / np.maximum(t.derivative_np(w), 1e-300)
        interval[k] = (t.to_physical_np(w - 1.96 * sw), t.to_physical_np(w + 1.96 * sw))
        labels += [k] if shape == () else [f"{k}[{i}]" for i in range(n)]
        pos += n
    pos = 0
    su_flat = np.sqrt(np.clip(np.diag(cov_u), 0, None))
    for k in sorted(u_sizes):  # ravel_pytree orders dict keys sorted
        n = u_sizes[k]
        shape = () if k in ("extinction", "albedo") else np.shape(getattr(params, k))
        u_stderr[k] = su_flat[pos : pos + n].reshape(shape)
        pos += n
    return cov, labels, stderr, interval, u_stderr


def _result_name(result) -> str:
    for name in ("successful", "nonlinear_max_steps_reached", "nonlinear_divergence", "nonfinite", "singular"):
        if hasattr(optx.RESULTS, name) and bool(result == getattr(optx.RESULTS, name)):
            return name
    return "failed"


class Calibrator:
    """Calibration of one scene with one config; compiled once, reused for every capture.

    ``Calibrator(scene, config).fit(capture)``; :func:`calibrate` is the one-shot form.
    """

    def __init__(self, scene: Scene, config: FitConfig = FitConfig()):
        self.scene = scene.without_touches()
        self.config = config
        self.options = ModelOptions(quadrature=config.quadrature, dtype=config.dtype)
        self._problem: _Problem | None = None
        if self.scene.noise.pile_up:
            raise CalibrationError("calibration of scenes with pile-up is not supported yet: set [noise] pile_up = false")

    def base_params(self) -> Params:
        """The scene's own parameters: the prior centre and the values of fixed parameters."""
        return Params.from_scene(self.scene, self.options.jnp_dtype)

    def fit(self, capture: Capture) -> CalibrationResult:
        """Fit to a baseline capture (see :func:`calibrate`)."""
        scene, config = self.scene, self.config
        check_baseline(capture, scene)
        base = self.base_params()
        if self._problem is None:
            self._problem = _Problem(scene, config.free, capture.mean(), capture.n_frames, self.options, config.prior_width)
        else:
            self._problem.set_data(capture.mean(), capture.n_frames)
        problem = self._problem
        start = _initial_params(capture, scene, base, problem.reference_estimates(scene, base, capture.n_frames))
        solver = config.make_solver()
        minimise = config.solver == "poisson-deviance"
        stages: list[dict[str, Any]] = []

        def stage(name, params, names, with_cov):
            """One compiled fit over the nonlinear parameters ``names`` (the rest held at ``params``)."""
            gn = config.gauss_newton_first if config.solver in ("levenberg-marquardt", "dogleg") else 0
            gn = min(gn, config.max_steps)
            run = problem.core_for(names, solver, config.max_steps, minimise, config.loss_tol, with_cov, gn)
            out = jax.device_get(run(params, problem.data, problem.sigma, base))
            h = np.asarray(out["history"])
            h = h[np.isfinite(h)]
            ok = bool(out["result"] == optx.RESULTS.successful)
            stages.append(
                {"stage": name, "free": list(names), "steps": int(out["steps"]), "converged": ok, "final_loss": float(h[-1])}
            )
            return out, ok, h.tolist()

        candidates = [start]
        if config.multistart:
            rng = np.random.default_rng(config.multistart_seed)
            candidates += [start.replace(n1=float(start.n1) * rng.uniform(0.9, 1.1)) for _ in range(config.multistart)]

        best = None
        for k, params in enumerate(candidates):
            history: list[float] = []
            if config.coarse_to_fine and "pulse_sigma_s" in problem.nonlinear:
                wide = params.replace(pulse_sigma_s=3.0 * float(params.pulse_sigma_s))
                coarse = tuple(p for p in problem.nonlinear if p != "pulse_sigma_s")
                out, _, h = stage(f"start {k}: widened pulse", wide, coarse, False)
                history += h
                params = out["params"].replace(pulse_sigma_s=float(start.pulse_sigma_s))
            out, ok, h = stage(f"start {k}: full", params, problem.nonlinear, True)
            history += h
            loss = stages[-1]["final_loss"]
            if best is None or loss < best[0]:
                best = (loss, out, ok, history)

        _, out, ok, best_history = best
        params = out["params"]
        n_free = int(sum(np.size(getattr(params, k)) for k in problem.free))
        dof = max(int(np.size(problem.data)) - n_free, 1)
        reduced = float(out["chi2"]) / dof
        cov, labels, stderr, interval, u_stderr = _covariance(problem, params, out["hessian"], out["dphys"], out["u_flat"])
        values = {k: np.asarray(getattr(params, k)) for k in config.free}
        return CalibrationResult(
            params=params,
            free=tuple(config.free),
            values=values,
            stderr={k: stderr[k] for k in config.free},
            interval95={k: interval[k] for k in config.free},
            covariance=cov,
            labels=labels,
            converged=ok,
            result=_result_name(out["result"]),
            steps=int(out["steps"]),
            reduced_chi2=reduced,
            loss_history=best_history,
            solver=config.solver,
            frames=capture.n_frames,
            stages=stages,
            unconstrained_stderr=u_stderr,
        )


def calibrate(
    capture: Capture,
    config: FitConfig = FitConfig(),
    *,
    scene: Scene | None = None,
) -> CalibrationResult:
    """Fit the scene's optical and nuisance parameters to a baseline capture.

    **Arguments:**

    - ``capture``: a baseline (no touch), any number of frames; they are averaged.
    - ``config``: solver, tolerances, free parameters (:class:`FitConfig`).
    - ``scene``: the scene to start from (default: the capture's own).

    **Returns:** a :class:`CalibrationResult`. A fit that did not converge has
    ``converged = False``; it is never reported as if it had. ``reduced_chi2``
    far above 1 means the model does not describe the data (a touch in the
    baseline, a wrong scene).

    Raises :class:`CalibrationError` for data that cannot be a baseline.
    """
    return Calibrator(scene or capture.scene, config).fit(capture)
