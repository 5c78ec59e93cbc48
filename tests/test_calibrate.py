"""Calibration: recovery of known parameters, honest uncertainty, and clear errors."""

import json

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from tofjax import ConfigError
from tofjax.capture import write_capture
from tofjax.cli import main
from tofjax.fit.calibrate import CalibrationError, Calibrator, FitConfig, calibrate, load_fit_config
from tofjax.fit.transforms import Transform
from tofjax.scene import SensorModel, Touch
from tofjax.simulate import simulate


@pytest.fixture(scope="module")
def small(optoskin):
    """Three of the OptoSkin sensors, 3 zones, 96 bins: the same physics, faster fits."""
    sm = SensorModel(bin_width_s=1e-10, n_bins=96, zones=3, fov_deg=29.0)
    return optoskin.replace(sensor=sm, sensors=optoskin.sensors[:3])


@pytest.fixture(scope="module")
def fitted(small):
    cap = simulate(small, 60, seed=3)
    cal = Calibrator(small)
    return cal, cal.fit(cap), cap


@given(u=st.floats(-10, 10))
def test_transforms_round_trip_and_derivative(u):
    for t in (Transform("log", scale=1e-10), Transform("sigmoid", lo=1.0, hi=4.0), Transform("sigmoid", lo=0, hi=1.3e-8)):
        x = float(t.to_physical(u))
        if t.kind == "sigmoid" and not (t.lo < x < t.hi):
            continue  # saturated in float64: no inverse to check
        assert float(t.to_unconstrained(x)) == pytest.approx(u, rel=1e-6, abs=1e-6)
        eps = 1e-6
        fd = (float(t.to_physical(u + eps)) - float(t.to_physical(u - eps))) / (2 * eps)
        assert float(t.derivative(u)) == pytest.approx(fd, rel=1e-4, abs=1e-30)


def test_recovers_known_parameters(fitted, small):
    _, res, _ = fitted
    wg = small.waveguide
    assert res.converged, res.result
    assert res.values["n1"] == pytest.approx(wg.n1, rel=0.005)
    mu_t = res.values["mu_s_per_m"] + res.values["mu_a_per_m"]
    assert mu_t == pytest.approx(wg.mu_s_per_m + wg.mu_a_per_m, rel=0.05)
    assert 0.8 < res.reduced_chi2 < 1.25
    assert res.values["emission_time_s"] == pytest.approx(small.sensor.emission_time, rel=0.01)
    np.testing.assert_allclose(res.values["ambient_counts"], small.sensor.ambient_counts, rtol=0.05)
    # the truth lies inside the Laplace 95% interval of n1
    lo, hi = res.interval95["n1"]
    assert lo <= wg.n1 <= hi and lo < res.values["n1"] < hi
    # loss never increases by much over the run, and ends far below where it started
    h = np.asarray(res.loss_history)
    assert h[-1] < h[0] and np.isfinite(h).all()


def test_says_what_a_baseline_cannot_tell(fitted):
    _, res, _ = fitted
    i, j = res.labels.index("mu_s_per_m"), res.labels.index("mu_a_per_m")
    c = res.covariance
    corr = c[i, j] / np.sqrt(c[i, i] * c[j, j])
    assert corr < -0.8  # scattering and absorption trade off along mu_t
    # their marginal errors are wide next to the error of their sum
    sum_err = np.sqrt(c[i, i] + c[j, j] + 2 * c[i, j])
    assert sum_err < 0.5 * min(np.sqrt(c[i, i]), np.sqrt(c[j, j]))


def test_json_is_complete(fitted):
    _, res, _ = fitted
    out = res.to_json()
    for k in ("n1", "mu_s_per_m", "mu_a_per_m", "gain", "ambient_counts", "pulse_sigma_s", "end_reflectance"):
        assert set(out["parameters"][k]) == {"value", "stderr", "interval95"}
    assert out["converged"] is True and out["result"] == "successful"
    n = len(out["covariance"]["labels"])
    assert np.asarray(out["covariance"]["matrix"]).shape == (n, n)
    assert out["steps"] > 0 and len(out["loss_history"]) > 1
    json.dumps(out)  # serialisable


def test_warm_refit_reuses_compiled_solver(fitted, small):
    cal, _, _ = fitted
    res = cal.fit(simulate(small, 30, seed=9))
    assert res.converged and res.values["n1"] == pytest.approx(small.waveguide.n1, rel=0.005)


def test_unconverged_is_never_reported_as_converged(small):
    res = calibrate(simulate(small, 10, seed=1), FitConfig(max_steps=2))
    assert not res.converged and res.result == "nonlinear_max_steps_reached"


def test_bad_baselines_are_refused(small):
    cap = simulate(small, 3, seed=0)
    for mutate, message in (
        (lambda h: h.__setitem__((0, 0, 0, 5), np.nan), "non-finite counts"),
        (lambda h: h.__setitem__((slice(None), 1, 2), 0.0), r"all-zero histograms \(sensor 1, zone 2\)"),
        (lambda h: h.__setitem__((0, 0, 0, 20), 2**24 - 1), "saturation limit"),
    ):
        bad = simulate(small, 3, seed=0)
        mutate(bad.histograms)
        with pytest.raises(CalibrationError, match=message):
            calibrate(bad)
    with pytest.raises(CalibrationError, match="the scene has"):
        calibrate(cap, scene=small.replace(sensors=small.sensors[:2]))


def test_fit_config_validation(tmp_path):
    p = tmp_path / "fit.toml"
    p.write_text('solver = "newton"\n')
    with pytest.raises(ConfigError, match="solver: must be one of"):
        load_fit_config(p)
    p.write_text('free = ["n1", "colour"]\n')
    with pytest.raises(ConfigError, match="free: 'colour' cannot be fitted"):
        load_fit_config(p)
    p.write_text("max_step = 3\n")
    with pytest.raises(ConfigError, match="max_step: unknown key"):
        load_fit_config(p)
    p.write_text('solver = "dogleg"\nmax_steps = 50\n')
    assert load_fit_config(p).solver == "dogleg"


def test_cli_calibrate_and_touch_capture_refused(tmp_path, small, capsys):
    base = write_capture(tmp_path / "base.h5", simulate(small, 40, seed=2))
    out = tmp_path / "calib.json"
    assert main(["calibrate", str(base), "--out", str(out), "--plots", str(tmp_path / "plots")]) == 0
    report = capsys.readouterr().out
    assert "n1" in report and "95% interval" in report
    data = json.loads(out.read_text())
    assert data["converged"] and abs(data["parameters"]["n1"]["value"] - 1.4) < 0.007
    assert (tmp_path / "plots" / "fit_sensor0.png").exists() and (tmp_path / "plots" / "loss.png").exists()
    # a touch capture passed as a baseline: the fit is poor, and the user is told so in one line
    touched = small.replace(touches=(Touch(position_m=(0.12, 0.1), radius_m=0.01, strength=3.0),))
    touch = write_capture(tmp_path / "touch.h5", simulate(touched, 40, seed=2))
    assert main(["calibrate", str(touch), "--out", str(tmp_path / "t.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert "no-touch baseline" in err and "\n" not in err
    # unconverged: non-zero exit unless allowed
    cfg = tmp_path / "fit.toml"
    cfg.write_text("max_steps = 2\n")
    assert main(["calibrate", str(base), "--config", str(cfg), "--out", str(tmp_path / "u.json")]) == 3
    assert json.loads((tmp_path / "u.json").read_text())["converged"] is False
    assert main(["calibrate", str(base), "--config", str(cfg), "--out", str(tmp_path / "u.json"), "--allow-unconverged",
                 "--overwrite"]) == 0


def test_shipped_fit_config_is_the_default():
    from pathlib import Path

    assert load_fit_config(Path(__file__).parents[1] / "configs" / "fit" / "default.toml") == FitConfig()


def test_linear_parameters_alone_are_not_a_fit():
    with pytest.raises(ConfigError, match="at least one of n1"):
        FitConfig(free=("gain", "ambient_counts"))


def test_posterior_short_run_resume_and_guard(fitted, tmp_path, small):
    """A short emcee run (the full study is in experiments/): finite samples near the fit,
    summary complete, an interrupted chain resumes, and a chain from other data is refused."""
    from tofjax.fit.posterior import PosteriorOptions, sample_posterior

    cal, res, cap = fitted
    chain = tmp_path / "chain.h5"
    opts = PosteriorOptions(max_steps=150, check_every=50, progress=False, chain=str(chain))
    post = sample_posterior(cal, cap, res, opts)
    assert post.steps == 150 and np.isfinite(post.samples).all()
    s = post.summary()
    n1 = s["parameters"]["n1"]
    assert n1["interval95"][0] < n1["median"] < n1["interval95"][1]
    assert abs(n1["median"] - small.waveguide.n1) < 0.005
    assert 0.05 < s["acceptance_fraction"] < 0.9
    assert np.asarray(s["correlation"]["matrix"]).shape == (len(post.names), len(post.names))
    # resume: the same chain file continues to 200 steps instead of starting again
    more = sample_posterior(cal, cap, res, PosteriorOptions(max_steps=200, check_every=50, progress=False, chain=str(chain)))
    assert more.steps == 200
    other = simulate(small, 60, seed=11)
    cal.fit(other)
    with pytest.raises(CalibrationError, match="other data or settings"):
        sample_posterior(cal, other, res, opts)


def test_covariance_jacobian_matches_autodiff(fitted):
    """The linear columns written down from linear_parts equal forward-mode AD of the full residuals."""
    import jax
    import jax.flatten_util

    cal, res, _ = fitted
    problem = cal._problem
    u = problem.pack(res.params, problem.free)
    flat, unravel = jax.flatten_util.ravel_pytree(u)
    prior = problem.pack(cal.base_params(), problem.free)
    ad = np.asarray(jax.jacfwd(lambda f: problem.full_residuals(unravel(f), res.params, prior))(flat))
    ours = problem.covariance_jacobian(res.params, cal.base_params())
    assert ours.shape == ad.shape
    np.testing.assert_allclose(ours, ad, rtol=0, atol=1e-9 * np.abs(ad).max())


@given(mu_s=st.floats(1e-4, 1e3), mu_a=st.floats(1e-4, 1e3))
def test_extinction_albedo_coordinates_round_trip(fitted, mu_s, mu_a):
    cal, res, _ = fitted
    problem = cal._problem
    p = res.params.replace(mu_s_per_m=mu_s, mu_a_per_m=mu_a)
    u = problem.pack(p)
    assert "extinction" in u and "albedo" in u and "mu_s_per_m" not in u
    back = problem.physical(u)
    assert float(back["mu_s_per_m"]) == pytest.approx(mu_s, rel=1e-9)
    assert float(back["mu_a_per_m"]) == pytest.approx(mu_a, rel=1e-9)


def test_loss_rule_stops_early_within_a_fraction_of_a_standard_error(small):
    """The chi-square stopping rule saves steps and moves the answer by << 1 standard error."""
    cap = simulate(small, 60, seed=5)
    tight = Calibrator(small, FitConfig(loss_tol=0.0, rtol=1e-9, atol=1e-9)).fit(cap)
    quick = Calibrator(small, FitConfig(loss_tol=1e-3)).fit(cap)
    assert quick.converged and tight.converged
    assert quick.steps < tight.steps
    for k in ("n1", "mu_s_per_m", "mu_a_per_m", "pulse_sigma_s", "end_reflectance"):
        assert abs(float(quick.values[k]) - float(tight.values[k])) < 0.2 * float(tight.stderr[k]), k
