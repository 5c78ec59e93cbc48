"""Compiled once, not per call: the greedy fit detector's model change and Jacobian, and the sensor
fit's Levenberg-Marquardt (``lm_fit``). Each was a ``jax.jit`` of a closure made per call (a new
detector, a new fit), so every call traced and compiled again; now module-level compiled functions
take the model (or the residual function) and the data as arguments. Traces are counted with a
Python side effect inside the traced function (its body runs only when traced)."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from tofjax.invert.correction import OpticalParams
from tofjax.invert.greedy import FitDetectOptions, build_fit_detector
from tofjax.sensor.fit import lm_fit

from small_scenes import three_sensor_square as _small_scene


def test_second_fit_detector_traces_nothing(monkeypatch):
    """A second detector of the same scene and slots (another baseline, another contact coupling: new
    data of the same shapes) traces the model change and its Jacobian no more. Stand-ins for the
    guided model's change (a pytree with data in it) and for the unit-contact responses (cheap)."""
    import tofjax.invert.greedy as greedy
    import tofjax.invert.reconstruct as rec

    sc = _small_scene()
    K, n = 2, int(np.prod(sc.shape))
    W = np.random.default_rng(0).normal(size=(3 * K, n))
    traces = []

    class Change(eqx.Module):
        scale: jax.Array

        def __call__(self, theta):
            traces.append(1)
            return self.scale * jnp.tanh(theta @ W)

    scales = iter([1.0, 0.8])
    monkeypatch.setattr(greedy, "_contact_change", lambda scene, optical, K, r: (Change(jnp.asarray(next(scales))), jnp.float64))
    monkeypatch.setattr(rec, "response_matrix", lambda scene, optical, centres, r, **k: np.ones((len(centres), *scene.shape)))
    base = np.full(sc.shape, 100.0)
    optical = dataclasses.replace(OpticalParams.from_scene(sc), optics="guided")
    theta = np.array([0.06, 0.11, 0.10, 0.05, 0.9, 0.0])
    fits = []
    for b in (base, 1.1 * base):
        det = build_fit_detector(sc, b, optical, FitDetectOptions(cell_m=0.03, max_contacts=K), n_baseline=100)
        y = np.tanh(theta @ W) / det.sigma
        fits.append(det._refit(theta + 0.003, np.array([0]), y, iterations=2))  # the change and its Jacobian
        if len(fits) == 1:
            n_first = len(traces)
    assert n_first >= 2 and len(traces) == n_first, (n_first, len(traces))  # each traced once, by the first
    assert fits[0][1] != fits[1][1] and np.isfinite(fits[1][1])  # the second detector used its own data


def test_lm_fit_second_fit_traces_nothing():
    """``lm_fit`` of the same residual function on new data of the same shapes traces nothing."""
    traces = []

    def resid(x, t, y):
        traces.append(1)
        return x[0] * jnp.exp(-x[1] * t) - y

    t = jnp.linspace(0.0, 2.0, 20)
    fits = []
    for seed in (0, 1):
        y = 3.0 * jnp.exp(-1.5 * t) + 0.01 * jnp.asarray(np.random.default_rng(seed).normal(size=20))
        fits.append(lm_fit(resid, np.array([1.0, 1.0]), (t, y))[0])
        if seed == 0:
            n = len(traces)
    assert n == 2 and len(traces) == 2, (n, len(traces))  # the residual and its Jacobian, each once
    assert np.allclose(fits, [3.0, 1.5], rtol=0.05) and not np.array_equal(*fits)
