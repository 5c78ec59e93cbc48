"""Laplace covariance of a calibration, in NumPy (no eager JAX dispatch after the fit)."""

from __future__ import annotations

import numpy as np

from ._problem import JOINT, CalibrationProblem

__all__ = ["data_share", "data_shares", "laplace_covariance", "normal_covariance"]


def normal_covariance(hessian, extra_precision=None) -> np.ndarray:
    """The Laplace covariance ``(J^T J + diag(extra_precision))^+`` (pseudo-inverse, symmetric),
    in float64 NumPy: the point fit's (``hessian = J^T J`` of its residuals, the weak prior
    included) and the posterior's, whose nuisance prior adds ``extra_precision`` (1 / width^2
    per coordinate, 0 where it has none)."""
    h = np.asarray(hessian, np.float64)
    if extra_precision is not None:
        h = h + np.diag(np.asarray(extra_precision, np.float64))
    cov = np.linalg.pinv(h, hermitian=True)
    return 0.5 * (cov + cov.T)


def data_share(hessian, prior_precision) -> np.ndarray:
    """Per coordinate, the share of its Laplace variance that the data account for. With ``H =
    hessian`` (the prior's ``P = diag(prior_precision)`` included) and ``C = H^-1``, the variance
    splits as ``C = C (H - P) C + C P C``: the data's part and the prior's. The share is
    ``[C (H - P) C]_kk / C_kk``: 1 where the prior adds nothing; near 0 where the data leave the
    coordinate free along some direction (a scale the profiled gains absorb: there the weak prior
    alone holds it, and the value depends on the prior: not a measurement). Computed in ``H``'s
    scaled coordinates (unit diagonal)."""
    h = np.asarray(hessian, np.float64)
    p = np.broadcast_to(np.asarray(prior_precision, np.float64), h.shape[:1])
    d = np.sqrt(np.maximum(np.diag(h), np.finfo(np.float64).tiny))
    hs = h / d[:, None] / d[None, :]
    c = np.linalg.pinv(hs, hermitian=True)
    c = 0.5 * (c + c.T)
    prior_part = np.einsum("kj,j,jk->k", c, p / d**2, c)
    var = np.diag(c)
    return np.clip(1.0 - prior_part / np.where(var > 0, var, 1.0), 0.0, 1.0)


def _layout(problem: CalibrationProblem, values: dict) -> dict[str, int]:
    """The solver's coordinates and their sizes (mu_s and mu_a as extinction and albedo where both are free)."""
    sizes = {k: int(np.size(values[k])) for k in problem.free if k not in JOINT}
    if all(j in problem.free for j in JOINT):
        sizes |= {"extinction": 1, "albedo": 1}
    else:
        sizes |= {k: 1 for k in JOINT if k in problem.free}
    return sizes


def data_shares(problem: CalibrationProblem, values: dict, hessian) -> dict[str, float]:
    """:func:`data_share` of each coordinate of a calibration (the median over a per-zone parameter's
    values), by coordinate name (``extinction``: mu_s + mu_a; ``albedo``: mu_s / (mu_s + mu_a)). Empty
    without a prior (``prior_width = 0``: nothing to compare with) or a finite Gauss-Newton matrix."""
    if not problem.prior_width > 0 or not np.all(np.isfinite(hessian)):
        return {}
    sizes = _layout(problem, values)
    names = sorted(sizes)  # ravel_pytree orders dict keys sorted
    prior = np.concatenate([np.full(sizes[k], problem.prior_precision(k)) for k in names])
    share = data_share(hessian, prior)
    out, pos = {}, 0
    for k in names:
        out[k] = float(np.median(share[pos : pos + sizes[k]]))
        pos += sizes[k]
    return out


def laplace_covariance(problem: CalibrationProblem, values: dict, hessian, dphys):
    """Covariance of every free parameter from ``J^T J`` of the full residuals at the optimum
    (linear parameters included), carried to physical units with ``dphys``.

    **Arguments:** ``values``: the fitted physical value of every free parameter (with
    ``zone_gain`` the gain is (S, Z)); ``hessian`` and ``dphys`` from
    :meth:`CalibrationProblem.laplace`.

    **Returns:** ``(covariance, labels, stderr, interval95, unconstrained_stderr)``; the 95%
    interval is symmetric in each parameter's own unconstrained space (log, logit), so it
    respects bounds, with the delta method's width there.
    """
    u_sizes = _layout(problem, values)
    cov_u = normal_covariance(hessian)
    d = np.asarray(dphys, np.float64)
    cov = d @ cov_u @ d.T
    names = sorted(problem.free)
    stderr_flat = np.sqrt(np.clip(np.diag(cov), 0, None))
    stderr, interval, u_stderr, labels, pos = {}, {}, {}, [], 0
    for k in names:
        x = np.asarray(values[k], np.float64)
        n = x.size
        stderr[k] = stderr_flat[pos : pos + n].reshape(x.shape)
        t = problem.transform(k)
        w = t.to_unconstrained(x)
        sw = stderr[k] / np.maximum(t.derivative_np(w), 1e-300)
        interval[k] = (t.to_physical_np(w - 1.96 * sw), t.to_physical_np(w + 1.96 * sw))
        labels += [k] if x.shape == () else [f"{k}[{i}]" for i in range(n)]
        pos += n
    pos = 0
    su_flat = np.sqrt(np.clip(np.diag(cov_u), 0, None))
    for k in sorted(u_sizes):  # ravel_pytree orders dict keys sorted
        n = u_sizes[k]
        shape = () if k in ("extinction", "albedo") else np.shape(values[k])
        u_stderr[k] = su_flat[pos : pos + n].reshape(shape)
        pos += n
    return cov, labels, stderr, interval, u_stderr
