"""Score (Lagrange-multiplier) tests at a fit's end point: does the data want a parameter the fit held fixed to move?

A calibration fits the parameters in ``FitConfig.free`` and holds the rest at the scene's values. Where the model
misfits a capture (reduced chi-square well above 1), a held parameter set wrongly is one candidate, and a wrong value
does not only add misfit: the free parameters move to make up for it, with standard errors that do not know (on the
Monte Carlo baseline the guided optics' multiple-scattering coupling, held at the scene's 0.5, put mu_a at 0.30 +- 0.01
against a truth of 0.14; docs/calibration.md, "Fixed parameters the data contradict").

For a held scalar ``theta`` with residual column ``j = dr/dtheta`` at the end point (``r`` the Poisson-weighted residuals
and prior rows, ``J`` their Jacobian over every free coordinate, the Laplace covariance's), the part of ``j`` the free
parameters cannot mimic is ``j_perp = (I - P_J) j``, and

    z = -j_perp . r / |j_perp|

is asymptotically N(0, 1) where the held value is right (Rao 1948; Silvey 1959); ``-j_perp . r / |j_perp|^2`` is the
Gauss-Newton step of ``theta`` with the free parameters refitted to first order. The same projection serves the slow
pulse tail's test (:mod:`tofjax.fit._tails`). Where the model misfits, ``r`` is wider than N(0, 1): the record also
gives ``z / sqrt(reduced chi-square)`` (a quasi-likelihood scaling), and that is what its threshold applies to.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..compile_cache import call_stored
from .transforms import FITTABLE

__all__ = ["end_point", "fixed_parameter_scores", "fixed_score_names", "fixed_score_record", "score_statistics"]

#: A held parameter whose column the free ones mimic to within this share of its norm is not tested (its z is 0 / 0).
MIMICKED = 1e-6


def score_statistics(jac, js, r):
    """``(z, step, |j_perp| / |j|)`` per row of ``js`` (K, rows): the score statistic of each column against residuals
    ``r`` (rows,) with the span of ``jac`` (rows, p) projected out, the Gauss-Newton step, and the share of each
    column the span cannot mimic (0 for a column of zeros). The normal equations are scaled to unit diagonal and solved by a pseudo-inverse
    (the fit's weak prior keeps them regular; the cut-off guards the rest)."""
    ft = jac.dtype
    tiny = jnp.finfo(ft).tiny
    scale = 1.0 / jnp.sqrt(jnp.maximum(jnp.sum(jac**2, axis=0), tiny))
    js_ = jac * scale
    vals, vecs = jnp.linalg.eigh(js_.T @ js_)
    keep = vals > vals[-1] * 1e-13
    inv = (vecs * jnp.where(keep, 1.0 / jnp.where(keep, vals, 1.0), 0.0)) @ vecs.T
    perp = js - (js_ @ (inv @ (js_.T @ js.T))).T
    norm2 = jnp.sum(perp**2, axis=1)
    proj = perp @ r
    z = -proj / jnp.sqrt(jnp.maximum(norm2, tiny))
    step = -proj / jnp.maximum(norm2, tiny)
    size = jnp.sum(js**2, axis=1)
    share = jnp.where(size > 0, jnp.sqrt(norm2 / jnp.maximum(size, tiny)), 0.0)
    return z, step, share


def end_point(problem, params, linear, prior_params, data, sigma, anchor):
    """``(jac, u, prior, r)`` at a fit's end point ``params`` / ``linear``: the Jacobian over every free coordinate
    (the Laplace covariance's), the coordinates, the prior (with the n1 anchor) and the residuals with prior rows."""
    jac = problem.covariance_jacobian(params, linear, prior_params, data, sigma, anchor)
    u = problem.pack_jax(params, problem.free, linear)
    prior = problem.pack_jax(prior_params, problem.free)
    prior["n1_anchor"] = anchor
    return jac, u, prior, problem.full_residuals(u, params, prior, data, sigma)


def fixed_score_names(problem) -> tuple[str, ...]:
    """The held scalar parameters a problem's model can be scored on: fittable, not free, one value (per-zone
    parameters and the profiled linear ones are left out), and the slow pulse tail only where the model has two
    tails (at a share of 0 its time constant is not identified; :mod:`tofjax.fit._tails` tests that case)."""
    from ..model import Params

    two_tails = int(getattr(problem.model.options, "pulse_tails", 2)) == 2
    fields = set(Params.__dataclass_fields__)
    out = []
    for k in FITTABLE:
        if k in problem.free or k not in fields or k in ("gain", "ambient_counts", "crosstalk_counts"):
            continue
        if k in ("pulse_slow_weight", "pulse_slow_tail_s") and not two_tails:
            continue
        out.append(k)
    return tuple(out)


@eqx.filter_jit
def fixed_parameter_scores(problem, params, linear, prior_params, data, sigma, anchor, names: tuple[str, ...]):
    """``(z, step, share)`` for each held parameter of ``names`` (:func:`score_statistics`) at the end point
    ``params`` / ``linear`` (the profiled values) of a fit of ``problem``."""
    jac, u, prior, r = end_point(problem, params, linear, prior_params, data, sigma, anchor)
    ft = jac.dtype

    def column(name):
        x0 = jnp.asarray(getattr(params, name))

        def res(d):
            return problem.full_residuals(u, params.replace(**{name: x0 + d}), prior, data, sigma)

        return jax.jvp(res, (jnp.zeros((), x0.dtype),), (jnp.ones((), x0.dtype),))[1].astype(ft)

    js = jnp.stack([column(k) for k in names])
    return score_statistics(jac, js, r)


def fixed_score_record(problem, params, linear, prior_params, data, sigma, anchor, reduced_chi2: float,
                       threshold: float) -> dict:
    """The score tests of every held scalar parameter as a JSON-able record, most contradicted first: each one's
    value, ``z``, ``z_scaled`` (``z / sqrt(max(reduced chi-square, 1))``), the value one Gauss-Newton step would move
    it to, and whether ``|z_scaled|`` exceeds ``threshold``; ``contradicted`` lists those that do."""
    names = fixed_score_names(problem)
    scale = float(np.sqrt(max(reduced_chi2, 1.0)))
    rows = []
    if names:
        # through the program store, as the fit: a new process reads the compiled program instead of compiling it
        # (about 17 s cold on OptoSkin with the guided optics on the 2-core VM, 0.09 s warm)
        args = (problem, params, linear, prior_params, data, sigma, anchor, names)
        z, step, share = jax.device_get(call_stored("fixed-parameter scores", fixed_parameter_scores, args,
                                                    to_plain=lambda x: x, from_plain=lambda plain, _: tuple(plain)))
        for k, zk, sk, hk in zip(names, np.asarray(z, float), np.asarray(step, float), np.asarray(share, float)):
            value = float(np.asarray(getattr(params, k)))
            if not (np.isfinite(zk) and np.isfinite(sk)) or hk < MIMICKED:
                note = ("not in this model (its term is left out, or the capture does not depend on it)" if hk == 0
                        else "the free parameters mimic its effect: the data cannot test it")
                rows.append({"name": k, "value": value, "z": None, "z_scaled": None, "gauss_newton_value": None,
                             "contradicted": False, "note": note})
                continue
            rows.append({"name": k, "value": value, "z": float(zk), "z_scaled": float(zk) / scale,
                         "gauss_newton_value": value + float(sk), "contradicted": bool(abs(zk) / scale > threshold)})
    rows.sort(key=lambda row: -abs(row["z_scaled"]) if row["z_scaled"] is not None else 0.0)
    return {
        "statistic": "two-sided score z of each held scalar parameter at its held value (the free parameters "
                     "refitted to first order); z_scaled = z / sqrt(max(reduced chi-square, 1))",
        "threshold": float(threshold),
        "reduced_chi2": float(reduced_chi2),
        "parameters": rows,
        "contradicted": [row["name"] for row in rows if row["contradicted"]],
    }
