"""Laplace covariance of a calibration, in NumPy (no eager JAX dispatch after the fit)."""

from __future__ import annotations

import numpy as np

from ._problem import JOINT, CalibrationProblem

__all__ = ["laplace_covariance", "normal_covariance"]


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
    u_sizes = {k: int(np.size(values[k])) for k in problem.free if k not in JOINT}
    if all(j in problem.free for j in JOINT):
        u_sizes |= {"extinction": 1, "albedo": 1}
    else:
        u_sizes |= {k: 1 for k in JOINT if k in problem.free}
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
