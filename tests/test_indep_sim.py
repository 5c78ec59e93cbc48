"""Smoke tests of the independent simulator fixture (tests/indep_sim.py)."""

import math

import numpy as np
import pytest

from indep_sim import IndepOptions, IndepRig, simulate
from tofjax.capture import read_capture, write_capture
from tofjax.scene import load_scene


@pytest.fixture(scope="module")
def rig():
    return IndepRig.from_scene(load_scene("configs/touch-six.toml").without_touches(), seed=1)


def test_contact_adds_light_at_its_round_trip_time(rig):
    """A contact adds counts that peak near emission + 2 d / c1 (plus the pulse delay), in the zone that holds it."""
    sc = rig.scene
    s = sc.sensors[0]
    axis = math.radians(s.direction_deg)
    d = 0.15
    xy = np.array(s.position_m) + d * np.array([math.cos(axis), math.sin(axis)])
    diff = rig.expected(np.array([[*xy, 1.0]])) - rig.expected(np.zeros((0, 3)))
    z = sc.sensor.zones // 2
    assert diff[0, z].sum() > 0.5 * diff[0].sum() > 0
    t_peak = (np.argmax(diff[0, z]) + 0.5) * sc.sensor.bin_width_s
    t_expect = rig.emission_time_s + 2 * d / rig.c1
    assert abs(t_peak - t_expect) < 3 * sc.sensor.bin_width_s


def test_conventions_differ_from_the_scene(rig):
    """Per-zone gains differ by several percent, the emission time is offset, no multiple scattering."""
    g = rig.gain_sz / rig.gain_sz.mean(axis=1, keepdims=True)
    assert 0.02 < g.std() < 0.15
    assert rig.emission_time_s != pytest.approx(rig.scene.sensor.emission_time)
    assert rig.truth()["multiple_scattering"] == 0.0


def test_capture_round_trip_keeps_truth(rig, tmp_path):
    contacts = np.array([[0.05, 0.01, 1.0], [0.2, 0.2, 0.8]])  # one 1 cm from the border
    cap = simulate(rig, contacts, frames=2, seed=3)
    assert cap.histograms.shape == (2, *rig.scene.shape)
    assert np.all(cap.histograms >= 0) and np.all(cap.histograms == np.round(cap.histograms))
    back = read_capture(write_capture(tmp_path / "c.h5", cap))
    np.testing.assert_allclose(back.truth_touches[0], contacts)
    assert back.truth["n1"] == rig.scene.waveguide.n1
    assert len(back.scene.touches) == 2


def test_border_contact_is_visible(rig):
    """A contact 5 mm from the edge still adds light (disk points outside the guide are dropped)."""
    diff = rig.expected(np.array([[0.15, 0.005, 1.0]])) - rig.expected(np.zeros((0, 3)))
    assert diff.max() > 10


def test_histograms_vectorised_over_configurations():
    sc = load_scene("configs/touch-six.toml").without_touches()
    rig = IndepRig.from_scene(sc, seed=2, options=IndepOptions(angles_per_zone=4, end_rays=16))
    H = rig.histograms(np.array([[[0.1, 0.1, 1.0]], [[0.2, 0.2, 1.0]]]), seed=0)
    assert H.shape == (2, *sc.shape)
    assert not np.array_equal(H[0], H[1])


def test_geometry_seed_resamples_only_the_jitter():
    """geometry_seed draws the sampling jitter from its own stream: the rig's per-zone draws stay,
    the expected counts change only by the sampling noise (the default, None, is what it was)."""
    sc = load_scene("configs/touch-six.toml").without_touches()
    small = IndepOptions(angles_per_zone=4, end_rays=16, range_step_m=2e-3)
    a = IndepRig.from_scene(sc, seed=2, options=small)
    b = IndepRig.from_scene(sc, seed=2, options=IndepOptions(**{**small.__dict__, "geometry_seed": 5}))
    np.testing.assert_array_equal(a.gain_sz, b.gain_sz)
    np.testing.assert_array_equal(a.ambient_sz, b.ambient_sz)
    la, lb = a.expected(np.zeros((0, 3))), b.expected(np.zeros((0, 3)))
    assert not np.array_equal(la, lb)
    assert abs(la.sum() / lb.sum() - 1) < 0.01
