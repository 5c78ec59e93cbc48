"""The sensitivity map (``tofjax.invert.sensitivity``, ``tofjax sensitivity``): its noise is the model
method's, its scalings, what it predicts about the detector, and one-line errors on bad input.
Small scene (15 cm guide, three sensors, 48 bins); one model-method inverter shared by the module."""

import dataclasses
import json

import numpy as np
import pytest
from small_scenes import three_sensor_square

from tofjax.capture import write_capture
from tofjax.cli import main
from tofjax.config import ConfigError
from tofjax.invert import InvertOptions, build_inverter
from tofjax.invert.sensitivity import SensitivityOptions, sensitivity, sensitivity_of
from tofjax.invert.synth import simulate_contacts
from tofjax.simulate import expected_counts, simulate

N_BASE = 50
WELL_SEEN = (0.09, 0.09)  # inside every sensor's view, away from the edge
FAR = (0.125, 0.125)  # the cell farthest from the three corner sensors (inside the edge band)


@pytest.fixture(scope="module")
def small():
    return three_sensor_square()


@pytest.fixture(scope="module")
def baseline(small):
    return expected_counts(small)


@pytest.fixture(scope="module")
def inverter(small, baseline):
    """The model method as ``detect --method model`` builds it (its reconstructor is the map's source)."""
    return build_inverter(small, baseline, InvertOptions(method="model"), n_baseline=N_BASE)


@pytest.fixture(scope="module")
def sens(inverter):
    return sensitivity_of(inverter.reconstructor, SensitivityOptions())


def test_noise_is_the_reconstructors(small, baseline, inverter, sens):
    """The map's noise is the reconstructor's (the one ``detect`` thresholds), the per-cell noise is the
    matched filter's (``1/sqrt(sum r^2 / sigma^2)`` of a unit contact's column, computed here directly),
    and the library entry builds the same reconstructor."""
    rec = inverter.reconstructor
    np.testing.assert_array_equal(sens.noise, rec.noise_map())
    np.testing.assert_array_equal(sens.noise, inverter.noise)
    # matched filter at two cells, from the response matrix itself
    from tofjax.invert.correction import OpticalParams
    from tofjax.invert.reconstruct import response_matrix

    pts = np.array([WELL_SEEN, (0.04, 0.11)])
    cells = sens.grid.centres()[(pts[:, 1] / sens.grid.dy).astype(int), (pts[:, 0] / sens.grid.dx).astype(int)]
    R = response_matrix(small, OpticalParams.from_scene(small), cells, 0.006)
    # in chunks of one size (5 centres in chunks of 2: three of 2, the last padded): the same rows, the padding dropped
    more = np.concatenate([cells, [[0.03, 0.03], [0.12, 0.05], [0.07, 0.13]]])
    R5 = response_matrix(small, OpticalParams.from_scene(small), more, 0.006, chunk=2)
    assert R5.shape == (5, *small.shape)
    np.testing.assert_allclose(R5[:2], R, rtol=1e-12, atol=1e-12 * np.abs(R).max())
    assert np.all(R5[2:].sum(axis=(1, 2, 3)) > 0) and not np.allclose(R5[3], R5[4])
    var = np.maximum(baseline, 1.0) * (1 + 1 / N_BASE)
    mf = 1 / np.sqrt(np.sum(R**2 / var[None], axis=(1, 2, 3)))
    np.testing.assert_allclose(sens.at(pts)["cell_noise"], mf, rtol=1e-9)
    # the threshold: the lasso's shrinkage (at least tau sigma; more with the cell's shadow column on)
    # plus n_sigma of the summed noise, in strength units
    ok = sens.sensed
    np.testing.assert_array_equal(sens.shrinkage, rec.shrinkage_map())
    np.testing.assert_allclose(sens.min_strength[ok], sens.shrinkage[ok] + 1.0 * sens.noise[ok])
    assert (sens.shrinkage[ok] >= 4.0 * sens.cell_noise[ok] * (1 - 1e-9)).all()
    assert (sens.shrinkage[ok] > 4.0 * sens.cell_noise[ok] * 1.01).mean() > 0.5
    assert np.isinf(sens.min_strength[~ok]).all() and (sens.snr[~ok] == 0).all()
    lib = sensitivity(small, baseline, options=SensitivityOptions(), n_baseline=N_BASE)
    np.testing.assert_allclose(lib.noise[ok], sens.noise[ok], rtol=1e-12)
    np.testing.assert_array_equal(lib.sensed, ok)


def test_frames_and_strength_scalings(inverter, sens):
    """SNR grows as sqrt(frames); the frames needed for strength s go as 1/s^2, and are the fewest that
    make the contact detectable; the threshold follows --n-sigma."""
    rec = inverter.reconstructor
    ok = sens.sensed
    four = sensitivity_of(rec, SensitivityOptions(frames=4))
    np.testing.assert_allclose(four.snr[ok], 2.0 * sens.snr[ok], rtol=1e-12)
    np.testing.assert_array_equal(four.min_strength, sens.min_strength)  # a one-frame quantity
    s = float(np.median(sens.min_strength[ok])) / 3.0  # needs ~9 frames on half the cells
    a = sensitivity_of(rec, SensitivityOptions(strength=s))
    b = sensitivity_of(rec, SensitivityOptions(strength=s / 2))
    exact = (a.min_strength[ok] / s) ** 2
    assert (a.frames_needed[ok] >= exact - 1e-9).all() and (a.frames_needed[ok] < exact + 1).all()
    assert (b.frames_needed[ok] >= 4 * exact - 1e-9).all() and (b.frames_needed[ok] < 4 * exact + 1).all()
    for f in (1, 3, 9):
        more = a.frames_needed[ok] > 1
        assert (a.detectable(f)[ok] == (a.frames_needed[ok] <= f)).all()
        assert not a.detectable(1)[ok][more].any()
    looser = sensitivity_of(rec, SensitivityOptions(n_sigma=3.0))
    np.testing.assert_allclose(looser.min_strength[ok] - sens.min_strength[ok], 2.0 * sens.noise[ok])
    half = sensitivity_of(rec, SensitivityOptions(strength=float(np.median(sens.min_strength[ok])))).summary()
    assert half["detectable_one_frame"]["all"] == pytest.approx(0.5, abs=0.02)


def test_the_map_predicts_the_detector(small, inverter, sens):
    """Noise-free frames, one contact (touch return and shadow) at each of 16 cells: 1.5 times the map's
    minimum strength is detected there, 0.7 times is not, and the summed strength the method reports is
    the strength less the map's shrinkage (within 15%; tau sigma alone, without the shadow column's
    share, would be further off). The map describes the model method, not a matched filter in general."""
    g = sens.grid
    pts = np.array([(x, y) for x in (0.05, 0.07, 0.09, 0.11) for y in (0.05, 0.07, 0.09, 0.11)])
    pts = (np.floor(pts / g.dx) + 0.5) * g.dx  # cell centres
    at = sens.at(pts)
    i, j = (pts[:, 0] / g.dx).astype(int), (pts[:, 1] / g.dy).astype(int)
    for m, expect in ((1.5, 1), (0.7, 0)):
        s = m * at["min_strength"]
        res = inverter.process(simulate_contacts(small, np.array([[[x, y, v]] for (x, y), v in zip(pts, s)]),
                                                 noise=False))
        for d, p in zip(res.detections, pts):
            pos = d.positions()
            assert len(pos) == expect and (expect == 0 or np.hypot(*(pos[0] - p)) < 0.012)
        if m == 1.5:
            got = res.maps[np.arange(len(pts)), j, i]
            err_map = np.abs(got / (s - at["shrinkage"]) - 1)
            err_tau = np.abs(got / (s - 4.0 * at["cell_noise"]) - 1)
            assert np.median(err_map) < 0.15 and np.median(err_map) < np.median(err_tau)


def test_a_more_attenuating_guide_needs_stronger_contacts_far_away(small, sens):
    murky = small.replace(waveguide=dataclasses.replace(small.waveguide, mu_a_per_m=small.waveguide.mu_a_per_m + 3.0))
    m = sensitivity(murky, expected_counts(murky), options=SensitivityOptions(), n_baseline=N_BASE)
    far, near = sens.at(np.array(FAR))["min_strength"], sens.at(np.array((0.04, 0.04)))["min_strength"]
    far_m, near_m = m.at(np.array(FAR))["min_strength"], m.at(np.array((0.04, 0.04)))["min_strength"]
    assert far_m > 1.2 * far
    assert far_m / far > near_m / near  # the farther from the sensors, the more the guide costs


def test_options_are_validated(inverter):
    with pytest.raises(ConfigError, match="response"):
        sensitivity_of(inverter.reconstructor, SensitivityOptions(response="signed"))  # built with "added"
    for bad in ({"strength": 0.0}, {"strength": float("nan")}, {"frames": 0}, {"frames": 1.5}, {"n_sigma": -1.0},
                {"response": "both"}, {"border_m": -0.1}):
        with pytest.raises(ConfigError):
            SensitivityOptions(**bad)


@pytest.fixture(scope="module")
def files(tmp_path_factory, small):
    d = tmp_path_factory.mktemp("sens")
    (d / "small.toml").write_text(small.to_toml())
    write_capture(d / "base.h5", simulate(small, 20, 0))
    other = small.replace(waveguide=dataclasses.replace(small.waveguide, size_m=(0.16, 0.15)))
    write_capture(d / "other.h5", simulate(other, 2, 0))
    from tofjax.fit import scene_fingerprint

    w = small.waveguide
    cal = {"parameters": {"n1": {"value": w.n1}, "gain": {"value": [1.0e4] * 3}},
           "fixed": {"mu_s_per_m": w.mu_s_per_m, "mu_a_per_m": w.mu_a_per_m, "emission_time_s": 1.45e-9,
                     "pulse_sigma_s": 6e-11, "pulse_tail_s": 1.5e-10},
           "converged": False, "result": "refused_reduced_chi2", "scene_fingerprint": scene_fingerprint(small)}
    (d / "refused.json").write_text(json.dumps(cal))
    return d


def test_cli_writes_json_and_png(files, small, capsys):
    out = files / "out"
    rc = main(["sensitivity", str(files / "small.toml"), "--baseline", str(files / "base.h5"), "--strength", "0.01",
               "--frames", "4", "--out", str(out)])
    assert rc == 0
    data = json.loads((out / "sensitivity.json").read_text())
    assert (out / "sensitivity.png").stat().st_size > 1000
    assert data["options"]["strength"] == 0.01 and data["options"]["frames"] == 4 and data["options"]["n_sigma"] == 1.0
    s = data["summary"]
    assert 0 < s["detectable_one_frame"]["all"] <= s["detectable_with_frames"]["all"] <= 1
    ms = np.array([[np.inf if v is None else v for v in row] for row in data["maps"]["min_strength"]])
    assert ms.shape == (data["grid"]["ny"], data["grid"]["nx"]) and np.isfinite(ms).any()
    captured = capsys.readouterr()
    assert "no calibration given" in captured.err and "sensitivity.json" in captured.out


def test_cli_fit_position_map(files, small, capsys):
    """``--method fit --position`` with a guided calibration: the position maps in the JSON (a standard deviation
    where the map senses a contact, a share in [0, 1]), position.png, and the printed placement shares; on the 1 cm
    grid ``--cell-m`` asks for (a quarter of the default grid's cells and time)."""
    cal = json.loads((files / "refused.json").read_text())
    cal.update(converged=True, result="successful", optics="guided")
    (files / "guided.json").write_text(json.dumps(cal))
    out = files / "pos"
    rc = main(["sensitivity", str(files / "small.toml"), "--baseline", str(files / "base.h5"), "--calibration",
               str(files / "guided.json"), "--method", "fit", "--position", "--strength", "0.5", "--cell-m", "0.01",
               "--out", str(out)])
    assert rc == 0
    data = json.loads((out / "sensitivity.json").read_text())
    assert data["options"]["position"] is True and data["options"]["match_radius_m"] == 0.02
    w = small.waveguide.size_m
    assert data["grid"]["dx_m"] == pytest.approx(0.01, rel=0.1) and data["grid"]["nx"] == pytest.approx(w[0] / 0.01, abs=1)
    sd = np.array([[np.inf if v is None else v for v in row] for row in data["maps"]["position_sd_m"]])
    share = np.array(data["maps"]["match_share"], float)
    assert np.isfinite(sd).any() and np.all((share >= 0) & (share <= 1))
    assert (out / "position.png").stat().st_size > 1000
    assert "placed within 2 cm" in capsys.readouterr().out


@pytest.mark.parametrize("extra, message", [
    (["--strength", "-1"], "--strength"),
    (["--frames", "0"], "--frames"),
    (["--n-sigma", "nan"], "--n-sigma"),
    (["--calibration", "refused.json"], "refused"),
    (["--baseline", "other.h5"], "different scenes"),
    (["--baseline", "missing.h5"], "missing.h5"),
    (["--position"], "add --method fit"),
    (["--method", "fit", "--position", "--match-radius-m", "0"], "--match-radius-m"),
    (["--cell-m", "0.01"], "add --method fit"),
    (["--method", "fit", "--cell-m", "0"], "--cell-m"),
    (["--method", "fit", "--cell-m", "nan"], "--cell-m"),
])
def test_cli_bad_input_is_one_line(files, extra, message, capsys):
    args = ["sensitivity", str(files / "small.toml"), "--baseline", str(files / "base.h5"), "--out", str(files / "bad")]
    extra = [str(files / e) if e.endswith((".json", ".h5")) else e for e in extra]
    i = args.index("--baseline")
    if extra[0] == "--baseline":
        args[i + 1] = extra[1]
        extra = []
    rc = main(args + extra)
    err = capsys.readouterr().err.strip()
    assert rc != 0 and message in err and "\n" not in err and "Traceback" not in err
    assert not (files / "bad" / "sensitivity.json").exists()


@pytest.mark.parametrize("extra, message", [
    ([], "guided optics"),  # no calibration: the scene's (default) optics, which the fit method cannot use
    (["--contact-response", "added"], "signed contact response"),
])
def test_cli_fit_method_needs_guided_optics_one_line(files, extra, message, capsys):
    """``--method fit`` (the contact fit's map) refuses the default optics in one line, before any model is built."""
    rc = main(["sensitivity", str(files / "small.toml"), "--baseline", str(files / "base.h5"), "--method", "fit",
               "--out", str(files / "badfit"), *extra])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert rc != 0 and message in err and "Traceback" not in err
    assert not (files / "badfit" / "sensitivity.json").exists()
