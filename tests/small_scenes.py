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
