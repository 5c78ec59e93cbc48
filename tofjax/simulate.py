"""Simulated captures: the forward model plus photon noise, written like recorded ones."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from .capture import Capture
from .model import ModelOptions, Params, build_model, sample_frames
from .scene import Scene

__all__ = ["capture_from_expected", "expected_counts", "simulate", "true_parameters"]


def true_parameters(params: Params) -> dict:
    """The parameters a simulation used, as JSON-able lists (stored in ``truth``)."""
    return {f.name: np.asarray(getattr(params, f.name)).tolist() for f in dataclasses.fields(params)}


def capture_from_expected(
    scene: Scene,
    expected,
    n_frames: int,
    seed: int,
    params: Params,
    *,
    source: str,
    frame_period_s: float,
    **extra,
) -> Capture:
    """``n_frames`` frames drawn from the expected counts ``expected`` (S, Z, B) (photon noise and
    saturation from the scene's ``[noise]`` and sensor tables, keys from ``seed``), with ground truth:
    ``truth_touches`` the scene's contact elements in every frame, ``truth`` the parameters
    (:func:`true_parameters` of ``params``), ``seed`` and ``extra``. What :func:`simulate` and the
    Monte Carlo's :func:`tofjax.mc.capture.mc_capture` both write."""
    keys = jax.random.split(jax.random.key(seed), n_frames)
    hist = np.array(sample_frames(keys, jnp.asarray(expected), poisson=bool(scene.noise.poisson),
                                  saturation=scene.sensor.saturation_counts), np.float64)  # a writable copy
    el = scene.contact_elements()
    touches = np.broadcast_to(el[:, [0, 1, 3]], (n_frames, len(el), 3)).copy() if len(el) else None
    truth = true_parameters(params)
    truth["seed"] = seed
    truth.update(extra)
    return Capture(histograms=hist, timestamps=np.arange(n_frames) * frame_period_s, scene=scene, source=source,
                   truth_touches=touches, truth=truth)


def expected_counts(scene: Scene, options: ModelOptions = ModelOptions(), params: Params | None = None) -> np.ndarray:
    """Noise-free expected counts of one frame: (sensors, zones, bins)."""
    model = build_model(scene, options)
    params = Params.from_scene(scene, options.jnp_dtype) if params is None else params
    return np.asarray(model(params))  # compiled by the model (one program per model structure, reused across calls)


def simulate(
    scene: Scene,
    n_frames: int = 1,
    seed: int = 0,
    *,
    options: ModelOptions = ModelOptions(),
    params: Params | None = None,
    frame_period_s: float = 1.0 / 9.0,
) -> Capture:
    """Simulate ``n_frames`` frames of a static scene.

    **Arguments:**

    - ``scene``: what is there; its ``[noise]`` table says whether photon noise
      and pile-up apply.
    - ``n_frames``: frames to draw (independent noise, same expected counts).
    - ``seed``: the same seed gives the same capture.
    - ``options``: model fidelity.
    - ``params``: override the scene's parameters (e.g. a calibrated set).
    - ``frame_period_s``: time between frames (the TMF8828 7x1 mode runs at 9 Hz).

    **Returns:** a :class:`~tofjax.capture.Capture` with ground truth
    (``truth_touches`` and ``truth``), ``source = "simulated"``.
    """
    if n_frames < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    params = Params.from_scene(scene, options.jnp_dtype) if params is None else params
    return capture_from_expected(scene, expected_counts(scene, options, params), n_frames, seed, params,
                                 source="simulated", frame_period_s=frame_period_s,
                                 model_options=dataclasses.asdict(options))
