"""Stability at the extremes, across the pipeline (issue 7).

tests/test_model.py::test_no_nan_or_inf_at_the_extremes already sweeps the forward model's
value and gradient over the corners of the grid (mu_s, mu_a in {0, 1e-3, 1e3} /m, n1 in
{1.0001, 1.4, 3.5}, 1e9 counts, bin 0, tiny and huge pulses, contacts at a sensor and the
far corner, float32 and float64). This module adds what that does not cover:

* the forward model along whole decades of mu_s and mu_a (0 to 1e3 /m) and of n1 (1.0001 to
  3.5), built from *scenes* (validation included), in float32 and float64 (its gradient along the
  same decades is in tests/test_model.py's sweep: one compiled value-and-gradient for both);
* simulated captures from 0 to 1e9 counts per bin (photon noise, saturation);
* calibration fits on a small scene at a few extreme truths: finite results, never NaN;
* the Monte Carlo reference at the extremes (scattering and absorption to 1e3 /m, n1 to 3.5,
  contacts at a sensor and at the far edge, both dtypes): finite tallies, conserved weight;
* physically impossible inputs: a clear one-line error naming the key.

* the touch correction, tactile maps and detection (tofjax.invert) with the optics at the
  corners of the sweep, on frames from 0 to 1e9 counts and contacts at a sensor and the far edge.
"""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tofjax import ConfigError, ModelOptions, Params, build_model, load_scene
from tofjax.cli import main
from tofjax.fit.calibrate import CalibrationError, Calibrator
from tofjax.mc import MCOptions, run_mc
from tofjax.scene import SensorModel, Touch, scene_from_dict
from tofjax.simulate import simulate

DECADES = (0.0, 1e-2, 1.0, 1e2, 1e3)
INDICES = (1.0001, 1.05, 1.4, 2.0, 3.5)


def finite(tree) -> bool:
    return all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree_util.tree_leaves(tree))


def with_waveguide(scene, **kw):
    return scene.replace(waveguide=dataclasses.replace(scene.waveguide, **kw))


def edge_contacts(scene):
    """Contacts on top of sensor 0 and at the corner farthest from it."""
    x0, y0 = scene.sensors[0].position_m
    lx, ly = scene.waveguide.size_m
    far = (lx - 0.002 if x0 < lx / 2 else 0.002, ly - 0.002 if y0 < ly / 2 else 0.002)
    return (Touch(position_m=(x0, y0), radius_m=0.004, strength=1.0), Touch(position_m=far, radius_m=0.004, strength=0.5))


# ---- forward model and gradient, from scenes --------------------------------------------


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_forward_over_decades(optoskin, dtype):
    """The forward model without pile-up (the default) along whole decades of mu_s and mu_a and of
    n1, from scenes: finite and never below zero by more than rounding. Its gradient over the same
    decades is checked in tests/test_model.py::test_no_nan_or_inf_at_the_extremes (with pile-up: the
    same program plus its last step), where one compiled value-and-gradient serves both sweeps
    (here it compiled a second one per dtype: about 20 s of CPU each)."""
    scene = optoskin.replace(touches=edge_contacts(optoskin))
    opts = ModelOptions(dtype=dtype)
    model = build_model(scene, opts)
    for mu_s in DECADES:
        for mu_a in DECADES:
            for n1 in (INDICES[0], INDICES[-1]) if mu_s in (0.0, 1e3) else (1.4,):
                s = with_waveguide(scene, mu_s_per_m=mu_s, mu_a_per_m=mu_a, n1=n1)  # scene validation accepts it
                y = np.asarray(model(Params.from_scene(s, opts.jnp_dtype)))  # compiled once (model.__call__)
                assert np.isfinite(y).all() and y.min() > -1e-3 * max(y.max(), 1.0), (mu_s, mu_a, n1, dtype)
    for n1 in INDICES:
        y = np.asarray(model(Params.from_scene(with_waveguide(scene, n1=n1), opts.jnp_dtype)))
        assert np.isfinite(y).all() and y.min() > -1e-3 * y.max(), n1


# ---- captures from 0 to 1e9 counts --------------------------------------------------------


def test_simulated_counts_from_zero_to_1e9(optoskin):
    """Photon noise and saturation from an all-dark scene to 1e9 counts per bin (its normal limit)."""
    from tofjax.model import sample_counts

    model = build_model(optoskin)
    fwd = model  # compiled (model.__call__); the same program as the next test's
    base = Params.from_scene(optoskin)
    for gain in (0.0, 1e-6, 150.0, 1e9):
        lam = fwd(base.replace(gain=np.full(6, gain), crosstalk_counts=np.full((6, 7), 20 * gain),
                               ambient_counts=np.full((6, 7), 0.0 if gain == 0 else 10.0)))
        h = np.asarray(sample_counts(jax.random.key(1), lam, saturation=1e12))
        assert np.isfinite(h).all() and (h >= 0).all(), gain
        assert (h.max() == 0) if gain == 0 else h.max() > 0
        if gain == 1e9:
            assert h.max() > 1e9
        clipped = np.asarray(sample_counts(jax.random.key(1), lam, saturation=optoskin.sensor.saturation_counts))
        assert clipped.max() <= optoskin.sensor.saturation_counts


def test_bin_zero_emission_and_pulse_widths(optoskin):
    """Light entering in bin 0, pulses of 1 fs and of 50 ns, through the simulator (one model, jitted once)."""
    model = build_model(optoskin)
    fwd = model  # compiled (model.__call__), as in the previous test
    base = Params.from_scene(optoskin)
    for kw in ({"emission_time_s": 0.0}, {"pulse_sigma_s": 1e-15, "pulse_tail_s": 1e-15},
               {"pulse_sigma_s": 5e-9, "pulse_tail_s": 5e-8}):
        y = np.asarray(fwd(base.replace(**kw)))
        assert np.isfinite(y).all() and y.sum() > 0, kw
    cap = simulate(optoskin.replace(sensor=dataclasses.replace(optoskin.sensor, emission_time_s=0.0)), 1)
    assert np.isfinite(cap.histograms).all()


# ---- calibration at a few extreme truths (one compiled problem) ----------------------------


def fit_extreme(truth_kw, frames=20, seed=3):
    # the scene and config tests/test_calibrate.py compiles (the compilation cache is shared)
    base = load_scene("optoskin")
    sm = SensorModel(bin_width_s=1e-10, n_bins=96, zones=3, fov_deg=29.0)
    scene = base.replace(sensor=sm, sensors=base.sensors[:3])
    cal = Calibrator(scene)
    res = cal.fit(simulate(with_waveguide(scene, **truth_kw), n_frames=frames, seed=seed))
    for k, v in res.values.items():
        assert np.isfinite(v).all(), (truth_kw, k)
    assert np.isfinite(res.reduced_chi2) and np.isfinite(res.loss_history).all(), truth_kw
    return cal, res


def test_calibration_of_a_perfectly_clear_guide_stays_finite():
    """mu_s = mu_a = 0: the log-scaled parameters run towards their floor, never to NaN."""
    cal, res = fit_extreme(dict(mu_s_per_m=0.0, mu_a_per_m=0.0))
    assert res.values["mu_s_per_m"] < 0.3 and res.values["mu_a_per_m"] < 0.3
    # counts that cannot be calibrated: a clear error, not NaN
    scene = cal.scene
    dark = simulate(scene.replace(sensor=dataclasses.replace(scene.sensor, gain=0.0, crosstalk_counts=0.0, ambient_counts=0.0)), 2)
    with pytest.raises(CalibrationError, match="all-zero"):
        cal.fit(dark)


@pytest.mark.slow
@pytest.mark.parametrize("truth", [dict(mu_s_per_m=30.0, mu_a_per_m=10.0), dict(n1=2.2), dict(n1=1.05)])
def test_calibration_at_more_extreme_truths(truth):
    fit_extreme(truth)


# ---- the Monte Carlo reference at the extremes ---------------------------------------------


def tiny_scene(**wg):
    d = {
        "waveguide": {"size_m": [0.05, 0.04], "thickness_m": 0.003, "n1": 1.4, "mu_s_per_m": 1.0, "mu_a_per_m": 0.1} | wg,
        "sensor": {"bin_width_s": 1e-10, "n_bins": 12, "zones": 2, "fov_deg": 30.0, "emission_time_s": 1e-10},
        "sensors": [{"position_m": [0.0, 0.02], "direction_deg": 0.0}],
    }
    return scene_from_dict(d)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_monte_carlo_at_the_extremes(dtype):
    cases = [dict(mu_s_per_m=1e3), dict(mu_a_per_m=1e3), dict(mu_s_per_m=0.0, mu_a_per_m=0.0), dict(n1=1.0001), dict(n1=3.5)]
    for kw in cases if dtype == "float64" else cases[-1:]:
        sc = tiny_scene(**kw)
        sc = sc.replace(touches=edge_contacts(sc))
        r = run_mc(sc, MCOptions(photons=256, batch=256, dtype=dtype))
        assert np.isfinite(r.counts).all() and (r.counts >= -1e-6 * max(r.counts.max(), 1)).all(), kw
        assert np.isfinite(list(r.ledger.values())).all(), kw
        assert sum(r.ledger.values()) == pytest.approx(1.0, abs=1e-3), kw  # roulette is unbiased, not exact


# ---- physically impossible inputs: clear errors --------------------------------------------


@pytest.mark.parametrize(
    "table, key, value, message",
    [
        ("waveguide", "n1", 0.9, "n1"),
        ("waveguide", "n1", 1.0, "n1"),
        ("waveguide", "mu_s_per_m", -1.0, "mu_s_per_m"),
        ("waveguide", "mu_a_per_m", -1e-3, "mu_a_per_m"),
        ("waveguide", "thickness_m", 0.0, "thickness_m"),
        ("waveguide", "end_reflectance", 1.5, "end_reflectance"),
        ("sensor", "bin_width_s", 0.0, "bin_width_s"),
        ("sensor", "pulse_sigma_s", -1e-12, "pulse_sigma_s"),
        ("sensor", "emission_time_s", -1e-10, "emission_time_s"),
        ("sensor", "gain", -1.0, "gain"),
    ],
)
def test_impossible_scene_values_are_clear_errors(tmp_path, capsys, table, key, value, message):
    d = load_scene("optoskin").to_dict()
    d[table][key] = value
    with pytest.raises(ConfigError, match=message):
        scene_from_dict({k: v for k, v in d.items()}, "bad.toml")
    path = tmp_path / "bad.toml"
    d = {k: ({kk: vv for kk, vv in v.items() if vv is not None} if isinstance(v, dict) else v) for k, v in d.items()}
    from tofjax.scene import _dump_toml

    path.write_text(_dump_toml(d))
    for cmd in (["mc", str(path), "--photons", "10", "--out", str(tmp_path / "x.h5")], ["prune", str(path)]):
        assert main(cmd) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_impossible_mc_and_contact_inputs():
    with pytest.raises(ConfigError, match="contact_n"):
        MCOptions(contact_n=0.5)
    with pytest.raises(ConfigError, match="radius_m"):
        Touch(position_m=(0.1, 0.1), radius_m=-0.01, strength=1.0)
    with pytest.raises(ConfigError, match="strength"):
        Touch(position_m=(0.1, 0.1), radius_m=0.01, strength=-1.0)


# ---- touch correction and tactile maps (tofjax.invert) -------------------------------------


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_correction_maps_and_detection_over_the_extremes(optoskin, dtype):
    """Algorithm 1, the Eq. 8 maps and detection with the optics at the corners of the sweep
    (mu_s, mu_a in {0, 1e3} /m, n1 in {1.0001, 3.5}), on frames of 0 counts, of 1e9 counts
    (saturated: flagged), of the baseline, and of contacts at a sensor and at the far edge:
    finite gains, finite maps, saturated frames flagged and zero, detections finite."""
    from tofjax.invert import InvertOptions, MapOptions, OpticalParams, build_inverter
    from tofjax.simulate import expected_counts

    options = InvertOptions(maps=MapOptions(resolution_m=0.01), dtype=dtype)
    touched = optoskin.replace(touches=edge_contacts(optoskin))
    for mu_s, mu_a, n1 in ((0.0, 0.0, 1.0001), (1e3, 0.0, 3.5), (0.0, 1e3, 1.4), (1e3, 1e3, 1.0001), (0.6, 0.14, 3.5)):
        base_scene = with_waveguide(optoskin, mu_s_per_m=mu_s, mu_a_per_m=mu_a, n1=n1)
        base = expected_counts(base_scene)
        touch = expected_counts(with_waveguide(touched, mu_s_per_m=mu_s, mu_a_per_m=mu_a, n1=n1))
        assert np.isfinite(base).all() and np.isfinite(touch).all()
        inv = build_inverter(base_scene, base, options, OpticalParams.from_scene(base_scene), n_baseline=100)
        assert np.isfinite(np.asarray(inv.corrector.gain)).all(), (mu_s, mu_a, n1)
        assert np.isfinite(inv.noise).all()
        frames = np.stack([np.zeros(optoskin.shape), np.full(optoskin.shape, 1e9), base, touch])
        res = inv.process(frames)
        assert np.isfinite(res.maps).all(), (mu_s, mu_a, n1, dtype)
        assert res.ok.tolist() == [True, False, True, True]
        assert np.all(res.maps[1] == 0) and res.detections[1].touches == []
        for det in res.detections:
            for t in det.touches:
                assert all(math.isfinite(t[k]) for k in ("x_m", "y_m", "strength"))
