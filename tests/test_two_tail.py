"""The two-tail pulse (ModelOptions.pulse_tails = 2): limits, mass, and the independent simulator's pulse."""

import numpy as np
import pytest

from tofjax.model import ModelOptions, Params, build_model, speed_in_guide
from tofjax.model.params import SPEED_OF_LIGHT_M_PER_S, ParamsError
from tofjax.model.pulse import binned_response, emg_cdf, pulse_cdf
from tofjax.scene import SensorModel, load_scene


@pytest.fixture(scope="module")
def small():
    base = load_scene("optoskin")
    sm = base.sensor
    return base.replace(sensor=SensorModel(bin_width_s=sm.bin_width_s, n_bins=64, zones=2, fov_deg=sm.fov_deg * 2 / sm.zones),
                        sensors=base.sensors[:1])


def test_zero_slow_weight_is_the_one_tail_model(small):
    p = Params.from_scene(small)
    one = np.asarray(build_model(small)(p))
    two = np.asarray(build_model(small, ModelOptions(pulse_tails=2))(p.replace(pulse_slow_tail_s=7e-10)))
    np.testing.assert_allclose(two, one, rtol=1e-12, atol=1e-9 * one.max())


def test_slow_tail_keeps_mass_and_moves_it_late(small):
    """The pulse is normalised: a slow tail moves counts later without adding any (far from the window's end)."""
    p = Params.from_scene(small).replace(ambient_counts=np.zeros((1, 2)))
    model = build_model(small, ModelOptions(pulse_tails=2))
    a = np.asarray(model(p))
    b = np.asarray(model(p.replace(pulse_slow_weight=0.3, pulse_slow_tail_s=4e-10)))
    t = np.arange(a.shape[-1])
    assert (b * t).sum() / b.sum() > (a * t).sum() / a.sum()
    # mass lost past the last bin only: the tail of the latest light
    assert b.sum() <= a.sum() * (1 + 1e-9) and b.sum() > 0.95 * a.sum()


def test_pulse_cdf_matches_the_independent_simulators_response():
    """Gaussian convolved with (1 - w) fast + w slow exponential == the two-EMG mixture (tests/indep_sim.py's _irf)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from indep_sim import IndepOptions, _irf

    o = IndepOptions()
    dt = 1e-12
    irf, zero = _irf(o, dt)
    t = (np.arange(len(irf)) - zero) * dt
    cdf = np.asarray(pulse_cdf(t + 0.5 * dt, o.pulse_sigma_s, o.tail_fast_s, o.slow_weight, o.tail_slow_s))
    np.testing.assert_allclose(np.cumsum(irf), cdf, atol=5e-3)
    one = np.asarray(emg_cdf(t, o.pulse_sigma_s, o.tail_fast_s))
    assert np.abs(np.asarray(pulse_cdf(t, o.pulse_sigma_s, o.tail_fast_s)) - one).max() == 0


def test_binned_response_sums_to_one():
    w = 1e-10
    t = np.arange(-5, 80) * w
    r = binned_response(t, w, 6e-11, 1.2e-10, 0.2, 5.5e-10)
    assert r.sum() == pytest.approx(1.0, abs=1e-3)


def test_c1_in_one_place():
    p = Params.from_scene(load_scene("optoskin"))
    assert float(p.c1) == pytest.approx(SPEED_OF_LIGHT_M_PER_S / float(p.n1), rel=1e-15)
    assert speed_in_guide(1.5) == SPEED_OF_LIGHT_M_PER_S / 1.5


def test_slow_weight_range_checked():
    p = Params.from_scene(load_scene("optoskin"))
    with pytest.raises(ParamsError, match="pulse_slow_weight"):
        p.replace(pulse_slow_weight=1.5)
    with pytest.raises(Exception, match="pulse_tails"):
        ModelOptions(pulse_tails=3)


def test_guided_optics_take_the_edge_angle_law():
    """The guided optics support Params.end_incidence_power: cos^p multiplies their Lambertian
    edge (p = 0 leaves it as it was; p = 2 dims every zone, whose rays meet the edges obliquely)."""
    import jax

    from tofjax.model import ModelOptions
    from tofjax.scene import scene_from_dict

    sc = scene_from_dict({
        "waveguide": {"size_m": [0.2, 0.1], "thickness_m": 0.004, "n1": 1.4, "mu_s_per_m": 0.0, "mu_a_per_m": 0.1},
        "sensor": {"bin_width_s": 5e-11, "n_bins": 96, "zones": 2, "fov_deg": 60.0, "emission_time_s": 5e-10},
        "sensors": [{"position_m": [0.0, 0.05], "direction_deg": 0.0}],
        "touches": [],
    })
    model = build_model(sc, ModelOptions(optics="guided"), ("end",))
    p = Params.from_scene(sc)
    f = jax.jit(lambda q: model(q))
    e0 = np.asarray(f(p)).sum(-1)
    e2 = np.asarray(f(p.replace(end_incidence_power=2.0))).sum(-1)
    assert (e2 < e0).all() and (e2 > 0).all()
