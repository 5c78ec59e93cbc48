"""Score tests of the parameters a calibration holds fixed (tofjax.fit._scores): where the fit misfits, which held
values do the data contradict, and which way would they move?"""

import dataclasses

import numpy as np
import pytest
from small_scenes import calibration_scene

from tofjax.config import ConfigError
from tofjax.fit import Calibrator, FitConfig
from tofjax.fit.calibrate import DEFAULT_FREE, calibrate_many, fit_report
from tofjax.simulate import simulate

#: the default free parameters but the pulse's width, held at the scene's value
HELD = tuple(k for k in DEFAULT_FREE if k != "pulse_sigma_s")


@pytest.fixture(scope="module")
def fits():
    """One baseline of the small scene fitted with the pulse's width held at the truth and at 1.2x (the scene the
    fit starts from says so), both scored always (one compiled fit, up to 400 steps: the held fit crawls along a
    valley), and with the width free from the wrong scene. (Held at 1.3x, the held fit has two optima, at reduced
    chi-squares of 25.8 and 10.2; at the second the other parameters absorb most of the width and its scaled score
    is only -1.6. Which one a fit reaches changed with the rounding of the model's sums. At 1.2x both compile
    settings and both sum orders end at 6.20, with a scaled score of -24.)"""
    scene = calibration_scene()
    cap = simulate(scene, 60, seed=11)
    sm = scene.sensor
    wrong = scene.replace(sensor=dataclasses.replace(sm, pulse_sigma_s=1.2 * sm.pulse_sigma_s))
    always = FitConfig(free=HELD, fixed_score_chi2=0.0, max_steps=400)
    right = Calibrator(scene, always).fit(cap)
    held_wrong = Calibrator(wrong, always).fit(dataclasses.replace(cap, scene=wrong))
    freed = Calibrator(wrong, FitConfig()).fit(dataclasses.replace(cap, scene=wrong))
    return scene, right, held_wrong, freed, wrong, cap


def _row(res, name):
    return next(r for r in res.discrepancy["fixed_parameters"]["parameters"] if r["name"] == name)


def test_a_true_held_value_is_not_contradicted(fits):
    """At the true held values the statistic is N(0, 1): every tested one within 4 (a false alarm ~1e-4 each).
    Only held scalars are tested; a term the scene leaves out says so."""
    _, right, _, _, _, _ = fits
    rec = right.discrepancy["fixed_parameters"]
    tested = [r for r in rec["parameters"] if r["z"] is not None]
    assert "pulse_sigma_s" in {r["name"] for r in tested}
    assert all(abs(r["z"]) < 4.0 for r in tested), tested
    assert rec["contradicted"] == [] and "contradict" not in fit_report(right)
    names = {r["name"] for r in rec["parameters"]}
    assert not names & set(right.free) and not names & {"gain", "ambient_counts", "crosstalk_counts"}
    assert all(r["note"] for r in rec["parameters"] if r["z"] is None)


def test_a_wrong_held_value_is_contradicted_and_the_step_points_back(fits):
    """Held 20% wide, the pulse's width is the most contradicted, the report says so, and one Gauss-Newton step
    from the held fit's optimum moves the width most of the way to the fit that frees it, far nearer the truth
    than the held value. (The held fit reaches its optimum, refused for its chi-square.)"""
    scene, _, held_wrong, freed, _, _ = fits
    assert held_wrong.result == "refused_reduced_chi2"
    rec = held_wrong.discrepancy["fixed_parameters"]
    row = rec["parameters"][0]
    assert row["name"] == "pulse_sigma_s" and row["contradicted"] and rec["contradicted"][0] == "pulse_sigma_s"
    assert row["z"] < -5 and row["z_scaled"] == pytest.approx(row["z"] / np.sqrt(max(rec["reduced_chi2"], 1.0)))
    truth, held = scene.sensor.pulse_sigma_s, 1.2 * scene.sensor.pulse_sigma_s
    assert row["value"] == pytest.approx(held)
    free_value = float(freed.params.pulse_sigma_s)
    assert abs(free_value - truth) < 0.05 * truth
    assert free_value < row["gauss_newton_value"] < held
    assert abs(row["gauss_newton_value"] - free_value) < 0.5 * (held - free_value)
    text = fit_report(held_wrong)
    assert "held parameters the data contradict" in text and "pulse_sigma_s" in text


def test_scores_only_where_the_fit_misfits(fits):
    """The default gate (reduced chi-square above 1.5) keeps a fit that describes its capture free of the extra
    program; the config's checks name the key."""
    _, _, held_wrong, freed, _, _ = fits
    assert held_wrong.reduced_chi2 > FitConfig().fixed_score_chi2 > freed.reduced_chi2
    assert "fixed_parameters" not in freed.discrepancy and "fixed_parameters" not in freed.to_json()["discrepancy"]
    for bad in ({"fixed_score_chi2": -1.0}, {"fixed_score_chi2": float("nan")}, {"fixed_score_threshold": 0.0}):
        with pytest.raises(ConfigError, match=f"^{next(iter(bad))}: must be"):
            FitConfig(**bad)
    assert FitConfig(fixed_score_chi2=float("inf")).fixed_score_chi2 == float("inf")


def test_a_batch_of_calibrations_scores_its_held_parameters_as_one_does(fits):
    """calibrate_many scores each misfitting result's held parameters as calibrate does (it used not to): the same
    statistics for the same capture (the gate is calibrate's own, tested above)."""
    _, _, held_wrong, _, wrong, cap = fits
    cap = dataclasses.replace(cap, scene=wrong)
    [one] = calibrate_many([cap], FitConfig(free=HELD, fixed_score_chi2=0.0, max_steps=400), scene=wrong)
    got, want = one.discrepancy["fixed_parameters"], held_wrong.discrepancy["fixed_parameters"]
    assert [r["name"] for r in got["parameters"]] == [r["name"] for r in want["parameters"]]
    assert got["contradicted"] == want["contradicted"] == ["pulse_sigma_s"] + want["contradicted"][1:]
    for a, b in zip(got["parameters"], want["parameters"]):
        assert (a["z"] is None) == (b["z"] is None) and (a["z"] is None or a["z"] == pytest.approx(b["z"], rel=1e-3, abs=1e-3))
