"""The TMF882x sensor model (issue 12): the learned pulse, the sensor fit, ranging, the
free-space scene, and the CLI on a slice of the real TMF8820 sweep (tests/data)."""

import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from tofjax.cli import main
from tofjax.model.pulse import emg_mixture_cdf, template_bin_masses, template_cdf
from tofjax.sensor import SensorFitOptions, SensorModelError, SensorResponse, expected_counts, fit_sensor, range_histograms
from tofjax.sensor.response import C_AIR

DATA = Path(__file__).parent / "data" / "tmf8820-plane-sweep" / "captures.json"
FAST = SensorFitOptions(knots_per_bin=2, pulse_bins=16.0, max_iterations=25, walk_degree=-1, shape_drift=False)


def test_template_cdf_is_exact_for_a_triangle():
    # pdf: a triangle on [0, 2] peaking at 1 (area 1) on knots 0.5 apart
    pdf = jnp.array([0.0, 0.5, 1.0, 0.5, 0.0])
    u = jnp.linspace(-1.0, 3.0, 81)
    ref = np.where(u < 0, 0, np.where(u < 1, u**2 / 2, np.where(u < 2, 1 - (2 - u) ** 2 / 2, 1)))
    np.testing.assert_allclose(template_cdf(u, pdf, 0.0, 0.5), ref, atol=1e-12)
    m = template_bin_masses(jnp.array([3.3, 40.25]), pdf, 0.0, 0.5, 64)
    np.testing.assert_allclose(m.sum(-1), 1.0, atol=1e-12)


def _truth_model(n_zones=1, bin_width=94e-12, pile=3e6):
    step = 0.5
    knots = -2.0 + step * np.arange(int(16 / step) + 1)
    edges = np.concatenate([knots - step / 2, [knots[-1] + step / 2]])
    c = np.asarray(emg_mixture_cdf(jnp.asarray(edges), [0.8, 0.2], [0.35, 0.5], [0.7, 4.0], [0.0, 0.4]))
    pdf = np.diff(c) / step
    slope = 2.0 / (C_AIR * bin_width)
    return SensorResponse(
        bin_width_s=bin_width, n_bins=64, grid=(1, n_zones), zero_range_bins=np.full(n_zones, 12.4),
        bins_per_m=np.full(n_zones, slope), pulse=np.tile(pdf, (n_zones, 1)), pulse_start_bins=-2.0, pulse_step_bins=step,
        pulses_per_histogram=np.full(n_zones, pile), gain_m2=np.full(n_zones, 8e3), ambient_counts=np.full(n_zones, 100.0),
    )


@pytest.fixture(scope="module")
def synthetic():
    truth = _truth_model()
    rng = np.random.default_rng(3)
    d = np.linspace(0.05, 0.35, 14)  # enough sub-bin phases to pin the pulse between its knots
    lam = expected_counts(truth, d)
    model, details = fit_sensor(rng.poisson(lam).astype(float), d, FAST, grid=(1, 1))
    return truth, model, details, rng


def test_fit_recovers_a_known_sensor(synthetic):
    truth, model, details, _ = synthetic
    r = model.report
    assert abs(model.bin_width_s / truth.bin_width_s - 1) < 0.01
    assert r["bin_width_se_s"] < 0.01 * truth.bin_width_s
    assert 0.7 < r["median_reduced_chi2"] < 1.5  # the model reaches the Poisson floor
    assert abs(r["pulses_per_histogram"][0] / 3e6 - 1) < 0.3
    # the zero-range time of the pulse peak, not of the pulse's arbitrary origin
    assert abs(model.zero_range_s()[0] / truth.zero_range_s()[0] - 1) < 0.01
    n = r["parameters"]  # a fixed shape: knots, pile-up, line, echo law shared; 4 numbers per capture and zone
    assert n["shared_per_zone"]["shape_drift_knots"] == 0 and n["per_capture_per_zone"] == 4
    assert n["fitted_total"] == n["shared_total"] + 4 * len(r["frames"])


def test_range_on_fresh_noise(synthetic):
    truth, model, _, rng = synthetic
    d = np.array([0.07, 0.155, 0.31])
    res = range_histograms(model, rng.poisson(expected_counts(truth, d)).astype(float))
    err = res["distance_m"][:, 0] - d
    assert np.all(np.abs(err) < 5 * res["stderr_m"][:, 0] + 2e-4)
    assert np.all(res["stderr_m"] < 1e-3) and np.median(res["reduced_chi2"]) < 3


def test_single_distance_is_an_error():
    truth = _truth_model()
    lam = expected_counts(truth, np.full(4, 0.2))
    with pytest.raises(SensorModelError, match="bin width cannot be identified: 1 distinct"):
        fit_sensor(lam, np.full(4, 0.2), FAST)


def test_saturated_frames_are_named_and_left_out(synthetic):
    from tofjax.sensor.importer import DroppedFramesWarning

    truth = _truth_model()
    # the synthetic fit's 14 distances plus one saturated frame: the fit left has the same shapes
    # (its compiled problem is reused)
    d = np.insert(np.linspace(0.05, 0.35, 14), 2, 0.1)
    lam = expected_counts(truth, d)
    lam[2, 0, 20] = 2**24 - 1
    with pytest.warns(DroppedFramesWarning, match="frames 2 have saturated bins"):
        model, _ = fit_sensor(np.round(lam), d, FAST)
    assert 2 not in model.report["frames"] and len(model.report["frames"]) == 14


def test_second_order_shape_drift_round_trip_and_range(tmp_path):
    """A model whose pulse changes shape to second order with distance (the default fit on real
    data): the file keeps it and the expected counts use it."""
    from tofjax.sensor import load_sensor_model

    truth = _truth_model()
    K = truth.pulse.shape[1]
    x = np.linspace(-1, 1, K)
    bump = np.exp(-((x - 0.1) / 0.1) ** 2)
    d1 = bump - bump.mean() * (x + 1.1 > 0)  # zero area on the knots (trapezoid, to the penalty's precision)
    terms = np.stack([0.03 * d1, 0.02 * np.roll(d1, 4)])[None]  # (Z=1, order 2, K)
    m = SensorResponse(**{**truth.__dict__, "pulse_drift": terms})
    assert m.drift_order == 2 and m.drift_terms(0).shape == (2, K)
    back = load_sensor_model(m.save(tmp_path / "d2.json"))
    assert back.drift_order == 2
    d = np.array([0.06, 0.3])
    lam = expected_counts(back, d)
    np.testing.assert_allclose(lam, expected_counts(m, d))
    assert np.abs(lam - expected_counts(truth, d)).max() > 1.0  # the drift does change the shape
    # (ranging with a second-order drift: test_study_sensor_runs_on_the_slice, marked slow)
    bad = {**m.to_json(), "pulse_drift": np.zeros((1, 2, K + 1)).tolist()}
    with pytest.raises(SensorModelError, match="pulse_drift .* does not match the pulse"):
        SensorResponse.from_json(bad)


def test_range_refuses_saturated_histograms(synthetic):
    _, model, _, _ = synthetic
    h = np.round(expected_counts(model, [0.1, 0.2, 0.3]))
    h[1, 0, 30] = 2**24 - 1
    with pytest.raises(SensorModelError, match=r"^frame 1 has saturated bins \(a count of 2\^24 - 1\)[^\n]*$"):
        range_histograms(model, h)


def test_model_file_round_trip(tmp_path, synthetic):
    from tofjax.sensor import load_sensor_model

    _, model, _, _ = synthetic
    back = load_sensor_model(model.save(tmp_path / "s.json"))
    np.testing.assert_allclose(expected_counts(back, [0.1]), expected_counts(model, [0.1]))
    (tmp_path / "bad.json").write_text(json.dumps({"format": "other"}))
    with pytest.raises(SensorModelError, match="not a tofjax sensor model"):
        load_sensor_model(tmp_path / "bad.json")


def test_free_space_scene_and_grids(tmp_path, synthetic):
    from tofjax.config import ConfigError
    from tofjax.scene import scene_from_dict

    base = {"sensor": {"bin_width_s": 1e-10, "n_bins": 128, "zones": 16, "grid": [4, 4], "fov_deg": 45.0},
            "sensors": [{"position_m": [0.0, 0.0], "direction_deg": 0.0}], "target": {"distance_m": 0.2}}
    s = scene_from_dict(base)
    assert s.free_space and s.shape == (1, 16, 128) and s.components() == ("target", "ambient")
    with pytest.raises(ConfigError, match="grid: 3 x 3 zones do not make zones = 16"):
        scene_from_dict({**base, "sensor": {**base["sensor"], "grid": [3, 3]}})
    path = synthetic[1].save(tmp_path / "s.json")
    fitted = scene_from_dict({**base, "sensor": {**base["sensor"], "zones": 1, "grid": [1, 1]}}).with_sensor_model(str(path))
    assert fitted.sensor.bin_width_s == pytest.approx(synthetic[1].bin_width_s) and fitted.sensor.model == str(path)
    # a waveguide scene takes the measured bin width (what `tofjax calibrate --sensor` does)
    from tofjax import load_scene

    guide = load_scene("optoskin").with_sensor_model(str(path))
    assert guide.sensor.bin_width_s == pytest.approx(synthetic[1].bin_width_s) and not guide.free_space



def test_inversion_takes_the_sensor_model_a_calibration_was_made_with(tmp_path, synthetic):
    """A calibration made with `calibrate --sensor` carries the measured bin width in its scene
    fingerprint: `detect`/`process --sensor` accept it, and without the sensor model it is
    refused as another scene's."""
    from tofjax import load_scene
    from tofjax.capture import Capture, write_capture
    from tofjax.fit import scene_fingerprint
    from tofjax.invert.correction import InversionError
    from tofjax.invert.pipeline import load_inputs

    sensor = synthetic[1].save(tmp_path / "s.json")
    scene = load_scene("optoskin").without_touches()
    rng = np.random.default_rng(0)
    for name in ("base", "touch"):
        write_capture(tmp_path / f"{name}.h5", Capture(histograms=rng.poisson(50.0, (2, *scene.shape)).astype(float),
                                                       timestamps=np.arange(2.0), scene=scene))
    fitted = scene.with_sensor_model(str(sensor))
    cal = {
        "parameters": {"n1": {"value": 1.4, "stderr": 0.01}, "gain": {"value": [100.0] * scene.n_sensors}},
        "fixed": {"mu_s_per_m": 0.6, "mu_a_per_m": 0.14, "emission_time_s": 1.45e-9, "pulse_sigma_s": 6e-11,
                  "pulse_tail_s": 1.5e-10},
        "converged": True,
        "scene_fingerprint": scene_fingerprint(fitted),
    }
    (tmp_path / "cal.json").write_text(json.dumps(cal))
    args = (tmp_path / "touch.h5", tmp_path / "base.h5", tmp_path / "cal.json")
    touch, base, optical = load_inputs(*args, sensor_path=str(sensor))
    assert base.scene.sensor.bin_width_s == pytest.approx(synthetic[1].bin_width_s) == touch.scene.sensor.bin_width_s
    assert optical.n1 == 1.4
    with pytest.raises(InversionError, match="another scene"):
        load_inputs(*args)

@pytest.fixture(scope="module")
def real(tmp_path_factory):
    """The CLI on the real slice: import, sensor fit, range."""
    d = tmp_path_factory.mktemp("real")
    assert main(["import", str(DATA), "--format", "tmf882x-json", "--out", str(d / "c.h5")]) == 0
    assert main(["sensor", "fit", str(d / "c.h5"), "--out", str(d / "s.json"), "--knots-per-bin", "2",
                 "--max-iterations", "12", "--no-shape-drift", "--plots", str(d / "plots")]) == 0
    assert main(["range", str(d / "c.h5"), "--sensor", str(d / "s.json"), "--json", str(d / "r.json")]) == 0
    return d


def test_real_slice_sensor_fit(real):
    rep = json.loads((real / "s.json").read_text())["report"]
    # a bin near 94 ps (not the nominal 100), agreeing with the raw peak-time line within 1%
    assert 90e-12 < rep["bin_width_s"] < 97e-12
    assert abs(rep["bin_width_relative_difference"]) < 0.01
    assert np.all(np.isfinite(rep["frame_reduced_chi2"])) and rep["median_reduced_chi2"] < 30
    assert len(rep["frame_reduced_chi2"]) == 8 and (real / "plots" / "residuals.png").is_file()


def test_real_slice_range_json(real):
    out = json.loads((real / "r.json").read_text())
    assert len(out["frames"]) == 8 and all(len(f["zones"]) == 9 for f in out["frames"])
    truth = [e["dist_to_plane"] for e in json.loads(DATA.read_text())]
    centre = np.array([f["zones"][4]["distance_m"] for f in out["frames"]])
    assert np.all(np.abs(centre - truth) < 3e-3)
    assert all(f["zones"][4]["stderr_m"] > 0 for f in out["frames"])


def test_cli_single_distance_one_line(tmp_path, capsys):
    entries = json.loads(DATA.read_text())[3:4] * 3
    p = tmp_path / "one.json"
    p.write_text(json.dumps(entries))
    assert main(["import", str(p), "--format", "tmf882x-json", "--out", str(tmp_path / "c.h5")]) == 0
    assert main(["sensor", "fit", str(tmp_path / "c.h5"), "--out", str(tmp_path / "s.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "bin width cannot be identified" in err


def test_simulated_and_emulated_histograms_come_from_the_fitted_model(tmp_path, synthetic):
    from tofjax.hw import protocol as P
    from tofjax.hw.bus import SimClock
    from tofjax.hw.emulator import TMF8828Emulator
    from tofjax.scene import scene_from_dict
    from tofjax.sensor.simulate import simulate_free_space

    truth = _truth_model(n_zones=9)
    truth = SensorResponse(**{**truth.__dict__, "n_bins": 128})
    path = truth.save(tmp_path / "truth.json")
    scene = scene_from_dict({"sensor": {"bin_width_s": 94e-12, "n_bins": 128, "zones": 9, "grid": [3, 3], "fov_deg": 40.0,
                                        "model": str(path)},
                             "sensors": [{"position_m": [0.0, 0.0], "direction_deg": 0.0}], "target": {"distance_m": 0.2}})
    cap = simulate_free_space(scene, 3, seed=1)
    assert cap.histograms.shape == (3, 1, 9, 128) and np.all(cap.target_distance_m == 0.2)
    res = range_histograms(truth, cap.histograms[:, 0])
    assert np.all(np.abs(res["distance_m"] - 0.2) < 1e-3) and np.median(res["reduced_chi2"]) < 2
    emu = TMF8828Emulator.from_sensor_model(truth, 0.15, SimClock())
    counts, _ = emu._draw_frame(P.layout_for(9))
    zones = emu.last_frame[0]
    assert zones.shape == (9, 128) and counts.max() > 0
    assert np.all(np.abs(range_histograms(truth, zones[None].astype(float))["distance_m"] - 0.15) < 1e-3)


@pytest.mark.slow
def test_study_sensor_runs_on_the_slice(tmp_path):
    """experiments/study_sensor.py end to end on the 8-capture slice (a few iterations): it writes
    its JSON (held out and full parts, the parameter count) and refuses to overwrite it."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("study_sensor", Path(__file__).parents[1] / "experiments" / "study_sensor.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = tmp_path / "r.json"
    argv = ["--data", str(DATA), "--out", str(tmp_path / "o"), "--json", str(out), "--max-iterations", "3", "--knots-per-bin", "2"]
    res = mod.main(argv)
    back = json.loads(out.read_text())
    assert back["held_out"]["centre_range_std_m"] == res["held_out"]["centre_range_std_m"] > 0
    assert back["full"]["parameters"]["shared_per_zone"]["shape_drift_knots"] == 2 * back["full"]["parameters"]["shared_per_zone"]["pulse_knots"]
    assert "real" in back["data_kind"] and "2-core" in back["machine"]
    assert np.isfinite(back["held_out"]["centre_range_errors_m"]).all()  # ranging with the second-order drift
    from tofjax.outputs import OutputError

    with pytest.raises(OutputError):
        mod.main(argv)


def test_a_damaged_sensor_model_is_refused_in_one_line(tmp_path):
    """A sensor.json without its pulse, with a NaN bin width or NaN in an array is refused on reading
    (an AttributeError in `tofjax range` and 0 touches from `detect --sensor` before), and a free-space
    simulation whose model gives negative expected counts is refused, not a NumPy traceback."""
    import json

    from tofjax.sensor import load_sensor_model
    from tofjax.sensor.response import SensorModelError
    from tofjax.sensor.simulate import _check_expected

    good = _truth_model().to_json()
    for name, edit, msg in (("no_pulse", {"pulse": None}, "missing field: pulse"),
                            ("bin_width_nan", {"bin_width_s": float("nan")}, "bin_width_s must be finite"),
                            ("gain_nan", {"gain_m2": [float("nan")]}, "gain_m2 has non-finite values")):
        p = tmp_path / f"{name}.json"
        p.write_text(json.dumps({**good, **edit}))
        with pytest.raises(SensorModelError, match=msg):
            load_sensor_model(p)
    lam = np.ones((2, 1, 8))
    _check_expected(lam, np.array([0.1, 0.2]))
    lam[1, 0, 3] = -5.0
    with pytest.raises(SensorModelError, match="target at 0.2 m: the sensor model gives negative expected counts"):
        _check_expected(lam, np.array([0.1, 0.2]))
    with pytest.raises(SensorModelError, match="beyond any sensor"):
        _check_expected(np.full((1, 1, 8), 1e300), np.array([1e-300]))
