"""Does a baseline support a second, slow pulse tail? A score test at the one-tail optimum.

The two-tail pulse ``(1 - w) EMG(sigma, tau) + w EMG(sigma, tau_slow)`` is the one-tail pulse at
``w = 0`` for every ``tau_slow``. Where the data have no slow tail the two-tail fit's optimum
lies on that singular set (or on ``tau_slow = tau``), where the Gauss-Newton model fails and
the fit crawls (docs/calibration.md, "Straggler fits"). So fit one tail first and ask whether
the data want ``w > 0``: the Lagrange-multiplier (score) test of ``w = 0`` needs nothing but
the one-tail fit's end point (Rao 1948; Silvey 1959).

With ``r`` the one-tail residuals (data and prior rows), ``J`` their Jacobian over every free
coordinate (the Laplace covariance's) and ``j = dr/dw`` at ``w = 0`` for one slow time
constant, the part of ``j`` the one-tail parameters cannot mimic is ``j_perp = (I - P_J) j``
and the one-sided statistic is

    z = -j_perp . r / |j_perp|,

asymptotically N(0, 1) where ``w = 0`` holds (the residuals are Poisson-weighted, so ``r`` has
unit variance); a slow tail makes it large and positive. ``tau_slow`` is not identified at
``w = 0`` (Davies 1977), so z is taken over a few ratios ``tau_slow / tau`` and the largest
counts; a Bonferroni bound gives the false-alarm rate, ``K (1 - Phi(threshold))``.
``-j_perp . r / |j_perp|^2`` is also the Gauss-Newton estimate of ``w``: where the test says
two tails, the two-tail fit starts there.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._problem import CalibrationProblem
from ._scores import end_point, score_statistics

__all__ = ["SLOW_RATIOS", "slow_tail_score", "tail_test", "tail_tests"]

#: Slow/fast time-constant ratios the score is taken at: a tail twice to eight times as slow
#: (at 1 the slow tail is the fast one and ``j`` lies in the span of the pulse's own columns).
SLOW_RATIOS = (2.0, 4.0, 8.0)


@eqx.filter_jit
def slow_tail_score(one: CalibrationProblem, two: CalibrationProblem, params, linear, prior_params, data, sigma, anchor, ratios):
    """``(z, w_hat)`` per ratio: the one-sided score statistic of the slow tail's share at 0 and
    the Gauss-Newton estimate of the share, at the one-tail end point ``params`` / ``linear``.

    ``one`` is the one-tail problem the fit ran; ``two`` the same free parameters with the
    two-tail model (its slow-tail parameters come from ``params``, not from coordinates)."""
    jac, u, prior, r = end_point(one, params, linear, prior_params, data, sigma, anchor)
    ft = jac.dtype

    def column(ratio):
        def res(w):
            p = params.replace(pulse_slow_weight=w, pulse_slow_tail_s=ratio * params.pulse_tail_s)
            return two.full_residuals(u, p, prior, data, sigma)

        return jax.jvp(res, (jnp.zeros((), params.n1.dtype),), (jnp.ones((), params.n1.dtype),))[1].astype(ft)

    js = jax.vmap(column)(jnp.asarray(ratios, params.n1.dtype))  # (K, rows)
    z, w_hat, _ = score_statistics(jac, js, r)  # what the one-tail parameters can do projected out
    return z, w_hat


def two_tail_problem(one: CalibrationProblem, free: tuple[str, ...]) -> CalibrationProblem:
    """``one``'s problem with the two-tail model and ``free`` (both built from ``one``: no model rebuild)."""
    model = dataclasses.replace(one.model, options=dataclasses.replace(one.model.options, pulse_tails=2))
    return CalibrationProblem.build(model, dict(one.transforms), free, zone_gain=one.zone_gain, prior_width=one.prior_width,
                                    zone_end=one.zone_end)


def one_tail_problem(two: CalibrationProblem, free: tuple[str, ...]) -> CalibrationProblem:
    """``two``'s problem with the one-tail model and ``free`` (the slow-tail parameters dropped)."""
    model = dataclasses.replace(two.model, options=dataclasses.replace(two.model.options, pulse_tails=1))
    return CalibrationProblem.build(model, dict(two.transforms), free, zone_gain=two.zone_gain, prior_width=two.prior_width,
                                    zone_end=two.zone_end)


def tail_test(one, two_same_free, params, linear, prior_params, data, sigma, anchor, threshold: float) -> dict:
    """The score test as a JSON-able record: ``z`` (the largest over :data:`SLOW_RATIOS`), each
    ratio's, the threshold, the decision (``two_tails``), the false-alarm bound, and where a
    two-tail fit starts (``slow_weight_start``, ``slow_tail_start_s``)."""
    z, w = jax.device_get(slow_tail_score(one, two_same_free, params, linear, prior_params, data, sigma, anchor,
                                          np.asarray(SLOW_RATIOS)))
    return _record(z, w, float(np.asarray(params.pulse_tail_s)), threshold)


def tail_tests(one, two_same_free, params, linear, prior_params, data, sigma, anchors, threshold: float) -> list[dict]:
    """:func:`tail_test` for a batch of end points (``params``, ``linear``, ``data``, ``sigma``,
    ``anchors`` with a leading batch axis) in one vmapped call: what a vmapped batch of fits uses,
    so that an accelerator does not run one small program per fit."""
    score = eqx.filter_vmap(slow_tail_score, in_axes=(None, None, 0, 0, None, 0, 0, 0, None))
    z, w = jax.device_get(score(one, two_same_free, params, linear, prior_params, data, sigma, anchors, np.asarray(SLOW_RATIOS)))
    taus = np.asarray(params.pulse_tail_s, np.float64)
    return [_record(z[i], w[i], float(taus[i]), threshold) for i in range(len(taus))]


def _record(z, w, tau: float, threshold: float) -> dict:
    z, w = np.asarray(z, np.float64), np.asarray(w, np.float64)
    z = np.where(np.isfinite(z), z, -np.inf)
    k = int(np.argmax(z))
    return {
        "statistic": "one-sided score z of pulse_slow_weight at 0 (max over slow/fast ratios)",
        "z": float(z[k]),
        "z_per_ratio": {f"{q:g}": float(v) for q, v in zip(SLOW_RATIOS, z)},
        "threshold": float(threshold),
        "false_alarm_bound": len(SLOW_RATIOS) * 0.5 * math.erfc(threshold / math.sqrt(2.0)),
        "two_tails": bool(z[k] > threshold),
        # the Gauss-Newton share, kept inside (0.02, 0.4): a start, not an estimate
        "slow_weight_start": float(np.clip(w[k], 0.02, 0.4)) if np.isfinite(w[k]) else 0.1,
        "slow_tail_start_s": SLOW_RATIOS[k] * tau,
    }
