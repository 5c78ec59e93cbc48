"""Simulated captures and emulator signals of a free-space scene from a fitted sensor model,
so that simulated and emulated TMF882x histograms look like real ones (issue 12, item 6)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .response import SensorModelError, SensorResponse, expected_counts, expected_reference, load_sensor_model

__all__ = ["simulate_free_space", "emulator_signals", "scene_sensor_model"]


def scene_sensor_model(scene) -> SensorResponse:
    """The fitted sensor model a scene names in ``[sensor] model``."""
    if not scene.sensor.model:
        raise SensorModelError(
            "this free-space scene has no [sensor] model: fit one with `tofjax sensor fit` and set model = \"sensor.json\""
        )
    model = load_sensor_model(Path(scene.sensor.model))
    if model.n_zones != scene.sensor.zones or model.n_bins != scene.sensor.n_bins:
        raise SensorModelError(
            f"[sensor] model {scene.sensor.model}: {model.n_zones} zones x {model.n_bins} bins, the scene "
            f"{scene.sensor.zones} x {scene.sensor.n_bins}"
        )
    return model


def _expected(scene, model, distances):
    t = scene.target
    refl = 1.0 if t is None else t.reflectance
    lam = expected_counts(model, distances, amplitude=model.gain_m2[None, :] * refl / np.asarray(distances)[:, None] ** 2)
    return lam


def _check_expected(lam: np.ndarray, distances: np.ndarray) -> None:
    """Refuse expected counts no sensor can give (one line, the distance named): negative ones (a
    sensor model whose fit did not converge can dip below zero), non-finite ones and counts beyond a
    Poisson draw's range (a target at 1e-300 m)."""
    lam = np.asarray(lam, float)
    per_frame = lam.reshape(len(distances), -1)
    peak = np.max(np.abs(np.where(np.isfinite(per_frame), per_frame, 0.0)), axis=1)
    for i, d in enumerate(distances):
        row = per_frame[i]
        if not np.all(np.isfinite(row)):
            raise SensorModelError(f"target at {d:g} m: the sensor model's expected counts are not finite")
        if row.min() < -1e-9 * max(peak[i], 1.0):
            raise SensorModelError(f"target at {d:g} m: the sensor model gives negative expected counts "
                                   f"({row.min():.3g}); was its fit converged (report.converged in sensor.json)?")
        if row.max() > 1e15:
            raise SensorModelError(f"target at {d:g} m: {row.max():.3g} expected counts in a bin, beyond any sensor "
                                   "(a target this close is outside the model)")


def simulate_free_space(scene, n_frames: int = 1, seed: int = 0, *, distances_m=None, model: SensorResponse | None = None,
                        frame_period_s: float = 1.0 / 30.0):
    """Simulate a TMF882x looking at the scene's flat target (or at ``distances_m``, one per frame).

    Poisson counts from the fitted sensor model (learned pulse, pile-up, zone gains and offsets),
    with the reference channel from its own pulse and ground truth in ``truth/target_distance_m``.
    """
    from ..capture import Capture

    if not scene.free_space:
        raise SensorModelError("simulate_free_space needs a free-space scene (no [waveguide])")
    model = model or scene_sensor_model(scene)
    if distances_m is None:
        if scene.target is None:
            raise SensorModelError("the scene has no [target] table: give the target distance")
        distances_m = np.full(n_frames, scene.target.distance_m)
    d = np.asarray(distances_m, float)
    rng = np.random.default_rng(seed)
    lam = _expected(scene, model, d)
    _check_expected(lam, d)
    lam = np.maximum(lam, 0.0)  # rounding below zero only (checked)
    hist = rng.poisson(lam).astype(float) if scene.noise.poisson else lam
    hist = np.minimum(hist, scene.sensor.saturation_counts)
    ref = expected_reference(model, len(d))
    if ref is not None and scene.noise.poisson:
        ref = rng.poisson(ref).astype(float)
    return Capture(
        histograms=hist[:, None],
        timestamps=np.arange(len(d)) * frame_period_s,
        scene=scene,
        source="simulated",
        reference=None if ref is None else ref[:, None],
        target_distance_m=d,
        truth={"seed": seed, "sensor_model": str(scene.sensor.model)},
    )


def emulator_signals(model: SensorResponse, distance_m: float, n_sensors: int = 1, reflectance: float = 1.0):
    """``(expected (sensors, zones, 128), reference (sensors, 128))`` for the TMF8828 emulator
    (``tofjax.hw.rig.emulated_bus(..., signals=...)``) from a fitted sensor model."""
    lam = expected_counts(model, [distance_m], amplitude=model.gain_m2[None, :] * reflectance / distance_m**2)[0]
    ref = expected_reference(model, 1)
    ref = np.zeros(model.n_bins) if ref is None else ref[0]
    return np.broadcast_to(lam, (n_sensors, *lam.shape)).copy(), np.broadcast_to(ref, (n_sensors, model.n_bins)).copy()
