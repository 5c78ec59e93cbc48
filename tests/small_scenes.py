"""Small scenes shared by several test files (not a test module)."""

import dataclasses

from tofjax import load_scene
from tofjax.scene import SensorPlacement

EDGE_BIN, BINS = 30, 48


def three_sensor_square():
    """OptoSkin physics on a 15 x 15 cm guide with three corner sensors and 48 bins."""
    sc = load_scene("optoskin").without_touches()
    wg = dataclasses.replace(sc.waveguide, size_m=(0.15, 0.15))
    sensors = (
        SensorPlacement((0.0, 0.0), 45.0, name="A"),
        SensorPlacement((0.15, 0.0), 135.0, name="B"),
        SensorPlacement((0.0, 0.15), 315.0, name="C"),
    )
    return sc.replace(waveguide=wg, sensors=sensors, sensor=dataclasses.replace(sc.sensor, n_bins=BINS))


def calibration_scene():
    """Three of the OptoSkin sensors, 3 zones, 96 bins: the calibration tests' small scene."""
    from tofjax.scene import SensorModel

    sc = load_scene("optoskin").without_touches()
    sm = SensorModel(bin_width_s=1e-10, n_bins=96, zones=3, fov_deg=29.0)
    return sc.replace(sensor=sm, sensors=sc.sensors[:3])


def slow_tail_capture(scene, frames, seed, weight=0.1, ratio=4.0):
    """A baseline of ``scene`` simulated with a second, slow pulse tail (share ``weight`` at
    ``ratio`` x the fast time constant): what a real SPAD's response has and a scene does not state."""
    import numpy as np

    from tofjax.model import ModelOptions, Params
    from tofjax.simulate import simulate

    truth = Params.from_scene(scene, np.float64)
    truth = truth.replace(pulse_slow_weight=np.asarray(weight), pulse_slow_tail_s=np.asarray(ratio * float(truth.pulse_tail_s)))
    return simulate(scene, frames, seed=seed, options=ModelOptions(pulse_tails=2), params=truth)
