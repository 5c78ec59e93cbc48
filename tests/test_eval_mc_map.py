"""experiments/eval_mc_data.py's sensitivity-map check (``--check-map``): which contacts a saved result found,
read back from its ``false_detections`` frames, and the recall it predicts at other exposures. No model, no
Monte Carlo: hand-made detections."""

import numpy as np
from test_studies import load

from tofjax.invert.detect import Detection


def _detections(found_xy):
    return [Detection(touches=[{"x_m": x, "y_m": y, "strength": 0.8, "component": 0} for x, y in f]) for f in found_xy]


def test_found_read_back_from_a_result_is_the_scorers():
    """Two configurations of three contacts, two frames each: the contacts found (matched within 2 cm) are
    recovered from the saved ``missed`` lists, in the order of the truth, also when a detection is 3 cm off."""
    ev = load("eval_mc_data")
    contacts = np.array([[[0.05, 0.05, 0.7], [0.15, 0.05, 0.9], [0.10, 0.15, 1.0]],
                         [[0.06, 0.12, 0.8], [0.20, 0.20, 0.7], [0.12345678, 0.0812, 0.9]]])
    truth = np.repeat(contacts, 2, axis=0)
    dets = _detections([
        [(0.051, 0.05), (0.15, 0.052)],                      # third missed
        [(0.05, 0.05), (0.15, 0.05), (0.10, 0.18)],         # third 3 cm off: missed
        [],                                                  # all missed
        [(0.06, 0.12), (0.20, 0.20), (0.1235, 0.0812)],      # all found
    ])
    kinds = ev._false_kinds(dets, truth, 0.02)
    found = ev.found_from_result({"false_detections": kinds}, contacts, 2)
    expect = np.array([1, 1, 0, 1, 1, 0, 0, 0, 0, 1, 1, 1], bool)
    np.testing.assert_array_equal(found, expect)


def test_predicted_recall_at_the_results_exposure_is_its_recall_and_grows_with_exposure():
    ev = load("eval_mc_data")
    rng = np.random.default_rng(0)
    snr = rng.uniform(2.0, 30.0, 200)
    found = rng.uniform(size=200) < np.clip((snr - 4.0) / 10.0, 0.0, 1.0)
    by = ev._recall_by_snr(found, snr)
    pred = ev.predicted_recall(by, snr, 16.0, exposures=(16, 64, 1024))
    assert abs(pred["16"] - found.mean()) < 1e-12
    assert pred["16"] < pred["64"] < pred["1024"]
    assert abs(pred["1024"] - by["bins"][-1]["recall"]) < 1e-12  # every contact in the top bin


def test_mc_contact_walls_fast(tmp_path):
    """experiments/mc_contact_walls.py on one position with a few hundred packets and two of its variants (each
    variant compiles the guided model twice: all five took 55 s of the suite): each variant's profiled L2 is finite
    and no larger than the unscaled one, the Monte Carlo's noise is positive, and it names an unknown position or
    variant instead of failing later."""
    import json

    import pytest

    walls = load("mc_contact_walls")
    out = tmp_path / "walls.json"
    variants = ["first_order", "field_legs_shadowed"]
    assert walls.main(["--out", str(out), "--photons", "400", "--seeds", "2", "--positions", "wall_2cm",
                       "--variants", ",".join(variants), "--cache", str(tmp_path / "cache")]) == 0
    row = json.loads(out.read_text())["positions"]["wall_2cm"]
    assert row["mc_noise_relative"] > 0 and sorted(row["variants"]) == sorted(variants)
    for v in row["variants"].values():
        assert np.isfinite(v["relative_l2_strength_profiled"])
        assert v["relative_l2_strength_profiled"] <= v["relative_l2_unscaled"] + 1e-12
    with pytest.raises(SystemExit):
        walls.main(["--out", str(out), "--positions", "nowhere"])
    with pytest.raises(SystemExit):
        walls.main(["--out", str(out), "--variants", "first_order,nothing"])


def test_false_detections_keep_the_fits_standard_errors_and_bad_fit_options_are_refused(tmp_path):
    """A detection's standard errors (the fit method's) travel into ``false_detections`` (null where infinite);
    an unknown field of ``--fit-options`` or ``--fit-variants`` is a usage error before anything runs."""
    import pytest

    ev = load("eval_mc_data")
    truth = np.array([[[0.05, 0.05, 0.7], [0.15, 0.05, 0.9]]])
    det = [Detection(touches=[{"x_m": 0.05, "y_m": 0.05, "strength": 0.8, "x_stderr_m": 0.0012, "y_stderr_m": np.inf,
                               "strength_stderr": 0.1, "component": 0}])]
    rows = ev._false_kinds(det, truth, 0.02)["frames"][0]["detections"]
    assert rows == [[0.05, 0.05, 0.8, True, 0.0012, None]]
    for flag in ("--fit-options", "--fit-variants"):
        bad = '{"bad": 1}' if flag == "--fit-options" else '{"v": {"bad": 1}}'
        with pytest.raises(SystemExit):
            ev.main(["--out", str(tmp_path), flag, bad])


def test_calib_model_error_mc_refuses_bad_levels(tmp_path):
    """experiments/calib_model_error_mc.py: levels outside [0, 1) or unparsable, and fewer than two Monte Carlo
    runs, are usage errors before any work."""
    import pytest

    study = load("calib_model_error_mc")
    for bad in ("1.5", "x", ""):
        with pytest.raises(SystemExit):
            study.main(["--out", str(tmp_path / "o.json"), "--model-errors", bad])
    for bad in ("1", "0", "x"):  # the Monte Carlo's own variance needs two runs at least
        with pytest.raises(SystemExit):
            study.main(["--out", str(tmp_path / "o.json"), "--seeds", bad])
    assert not (tmp_path / "o.json").exists()


def test_mc_baseline_time_ratio_refuses_no_windows(tmp_path):
    """experiments/mc_baseline_time_ratio.py: --windows 0 is a usage error before any work."""
    import pytest

    study = load("mc_baseline_time_ratio")
    with pytest.raises(SystemExit):
        study.main(["--out", str(tmp_path / "o.json"), "--windows", "0"])
    assert not (tmp_path / "o.json").exists()


def test_calib_mc_late_light_oracle_refuses_bad_arguments(tmp_path):
    """experiments/calib_mc_late_light_oracle.py: a non-positive exposure or a negative start is a usage error
    before any work (the model's EDGE_REVERB switch, which the study turns off for its run, untouched)."""
    import pytest

    import tofjax.model.guided as guided

    study = load("calib_mc_late_light_oracle")
    for flag, bad in (("--exposure", "0"), ("--after", "-1")):
        with pytest.raises(SystemExit):
            study.main(["--out", str(tmp_path / "o.json"), flag, bad])
    assert not (tmp_path / "o.json").exists()
    assert guided.EDGE_REVERB is True


def test_eval_mc_data_guided_switches(monkeypatch):
    """experiments/eval_mc_data.py --guided-switch: a known switch is set with its own type (bool from true/false,
    int from digits), an unknown name, a bare name or a value of the wrong type is refused with the name in the
    message (and sets nothing), and the command line stops with a usage error."""
    import pytest

    import tofjax.model.guided as guided

    ev = load("eval_mc_data")
    monkeypatch.setattr(guided, "REVERB_LEGS", False)
    monkeypatch.setattr(guided, "REVERB_NODES", 64)
    assert ev.set_guided_switches(["REVERB_LEGS=true", " REVERB_NODES = 32"]) == {"REVERB_LEGS": True, "REVERB_NODES": 32}
    assert guided.REVERB_LEGS is True and guided.REVERB_NODES == 32
    for bad, word in (("NOPE=1", "REVERB_LEGS"), ("REVERB_LEGS", "NAME=VALUE"), ("REVERB_LEGS=maybe", "true or false"),
                      ("REVERB_NODES=1.5", "int"), ("_reverb=1", "NAME=VALUE")):
        with pytest.raises(ValueError, match=word):
            ev.set_guided_switches([bad])
    assert guided.REVERB_LEGS is True and guided.REVERB_NODES == 32
    with pytest.raises(SystemExit):
        ev.main(["--guided-switch", "NOPE=1", "--out", "unused"])


def test_false_detections_summary(tmp_path):
    """experiments/false_detections.py: counts, standard errors, the strength cap, the missed contact a false
    detection shares its frame with, and the precision / recall trade of dropping by standard error; unreadable
    input is a usage error."""
    import json

    import pytest

    study = load("false_detections")
    frames = [{"detections": [[0.1, 0.1, 0.8, True, 0.001, 0.0], [0.25, 0.2, 1.0, False, 0.012, 0.016]],
               "missed": [[0.25, 0.25]]},
              {"detections": [[0.1, 0.1, 0.9, True, 0.0006, 0.0008]], "missed": []}]
    res = {"detection": {"monte_carlo": {"methods": {"fit": {"contacts": 4, "false_detections": {"frames": frames}}}}}}
    r = study.summarize([res])["monte_carlo"]
    assert (r["matched"], r["false"], r["false_sharing_a_frame_with_a_missed_contact"]) == (2, 1, 1)
    assert r["stderr_cm_median_false"] == pytest.approx(2.0) and r["stderr_cm_median_matched"] == pytest.approx(0.1)
    assert r["at_strength_cap_false"] == 1.0 and r["at_strength_cap_matched"] == 0.0
    assert r["their_distance_to_it_cm_median"] == pytest.approx(5.0)
    assert r["dropping_by_stderr"]["all"] == {"precision": 2 / 3, "recall": 0.5}
    assert r["dropping_by_stderr"]["<= 1 cm"] == {"precision": 1.0, "recall": 0.5}
    # pooled over two results (the same one twice): the counts add, the interval narrows around the same share
    one, two = r["pooled"], study.summarize([res, res])["monte_carlo"]["pooled"]
    assert (one["precision"]["k"], one["precision"]["n"], one["recall"]["n"]) == (2, 3, 4)
    assert (two["precision"]["k"], two["precision"]["n"]) == (4, 6) and two["precision"]["value"] == pytest.approx(2 / 3)
    lo1, hi1 = one["precision"]["interval95"]
    lo2, hi2 = two["precision"]["interval95"]
    assert lo1 < lo2 < 2 / 3 < hi2 < hi1
    assert r["per_result"] == [one]
    # Wilson's interval against a known value (20 of 25: 0.609-0.911)
    assert study.share(20, 25)["interval95"] == pytest.approx([0.6087, 0.9114], abs=1e-3)
    src = tmp_path / "r.json"
    src.write_text(json.dumps(res))
    assert study.main([str(src), "--out", str(tmp_path / "o.json")]) == 0
    assert json.loads((tmp_path / "o.json").read_text())["columns"]["monte_carlo"]["false"] == 1
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(SystemExit):
        study.main([str(tmp_path / "bad.json"), "--out", str(tmp_path / "o2.json")])
    with pytest.raises(SystemExit):  # a variant the results do not hold
        study.main([str(src), "--out", str(tmp_path / "o3.json"), "--method", "fit:model_error_0.2"])
    # a variant is read under its own name
    res["detection"]["monte_carlo"]["methods"]["fit:model_error_0.2"] = res["detection"]["monte_carlo"]["methods"]["fit"]
    assert study.summarize([res], method="fit:model_error_0.2")["monte_carlo"]["pooled"] == one


def test_reverb_spread_grid_fast(tmp_path):
    """experiments/reverb_spread_grid.py: the field's shape against its grid on a small guide (two node counts): the
    reference's own L2 is 0, the others finite, the spread moves no light; a bad ``--variants`` is a usage error
    (exit 2) before anything runs."""
    import pytest

    from test_guided import _square

    rsg = load("reverb_spread_grid")
    sc = _square(mu_s=0.6, mu_a=0.14)  # test_guided's small square guide, one sensor
    out = rsg.field_shape(sc, nodes=(32, 128))
    for spread in ("spread", "no_spread"):
        assert out[spread]["128"]["relative_l2_vs_128_nodes"] == 0.0
        assert 0.0 < out[spread]["32"]["relative_l2_vs_128_nodes"] < 1.0
    assert out["spread"]["128"]["total_counts"] == pytest.approx(out["no_spread"]["128"]["total_counts"], rel=1e-3)
    for bad in ("on:1", "maybe:64", "on64"):
        with pytest.raises(SystemExit) as e:
            rsg.main(["--out", str(tmp_path / "x.json"), "--variants", bad])
        assert e.value.code == 2


def test_guided_fidelity_calibration_fast(tmp_path):
    """experiments/guided_fidelity_calibration.py: the forward-time ratio on a small guide (8:8 against itself: finite,
    about 1x within a loaded machine's noise), the variants' parser, and a bad ``--variants`` or ``--repeats`` is a
    usage error (exit 2) before anything runs or is written. (The calibrations need the eval's 64 cached Monte Carlo
    runs: the study itself is not run here.)"""
    import math

    import pytest

    from test_guided import _square

    gfc = load("guided_fidelity_calibration")
    sc = _square(mu_s=0.6, mu_a=0.14)
    same = gfc.forward_ratio(sc, 8, 8, repeats=5)
    assert math.isfinite(same["forward_ratio_to_8_8"]) and 0.2 < same["forward_ratio_to_8_8"] < 5.0
    assert gfc._variants("8:8, 16:32") == [(8, 8), (16, 32)]
    for args in (["--variants", "8:0"], ["--variants", "8x8"], ["--variants", "a:8"], ["--repeats", "0"]):
        with pytest.raises(SystemExit) as e:
            gfc.main(["--out", str(tmp_path / "x.json"), *args])
        assert e.value.code == 2
    assert not (tmp_path / "x.json").exists()


def test_guided_multiple_scattering_fast(tmp_path):
    """experiments/guided_multiple_scattering.py: a bad ``--exposures``, an existing ``--out`` without ``--overwrite``
    and an unknown variant are usage errors (2) before anything runs or is written. (Both parts need the eval's cached
    Monte Carlo runs: the study itself is not run here; its score tests are tests/test_fixed_scores.py's.)"""
    gms = load("guided_multiple_scattering")
    out = tmp_path / "x.json"
    for bad in ("0", "16,-1", "a", "inf", ""):
        assert gms.main(["--out", str(out), "--exposures", bad]) == 2
    assert not out.exists()
    out.write_text("{}")
    assert gms.main(["--out", str(out)]) == 2 and out.read_text() == "{}"
    assert gms.main(["--out", str(out), "--calibrate-one", "half:16"]) == 2


def test_refused_fit_n1_fast(tmp_path):
    """experiments/refused_fit_n1.py: a bad ``--quadratures`` and an existing ``--out`` without ``--overwrite`` are usage
    errors (2) before anything runs or is written. (The calibrations need the eval's cached Monte Carlo runs; the
    rule itself is tests/test_calibrate.py::test_a_refused_fit_within_the_timing_anchor_keeps_its_n1.)"""
    rf = load("refused_fit_n1")
    out = tmp_path / "x.json"
    for bad in ("0", "2,x", "", "17"):
        assert rf.main(["--out", str(out), "--quadratures", bad]) == 2
    assert not out.exists()
    out.write_text("{}")
    assert rf.main(["--out", str(out)]) == 2 and out.read_text() == "{}"


def test_near_field_aperture_fast(tmp_path):
    """experiments/near_field_aperture.py: a bad ``--exposures``, ``--repeats`` or ``--study``, a bad
    ``--calibrate-one`` and an existing ``--out`` without ``--overwrite`` are usage errors (2) before anything runs or
    is written. (Both parts
    need the eval's 64 cached Monte Carlo runs: the study itself is not run here; the near field's physics is
    tests/test_guided.py's.)"""
    import pytest

    nfa = load("near_field_aperture")
    out = tmp_path / "x.json"
    cases = [["--exposures", bad] for bad in ("0", "16,-1", "a", "inf", "")]
    cases += [["--repeats", "0"], ["--calibrate-one", "2:0.5:64"], ["--calibrate-one", "1:0.5"],
              ["--calibrate-one", "1:x:64"], ["--study", "nope"], ["--study", "edge_scatter", "--exposures", "0"]]
    for args in cases:
        with pytest.raises(SystemExit) as e:
            nfa.main(["--out", str(out), *args])
        assert e.value.code == 2, args
    assert not out.exists()
    out.write_text("{}")
    with pytest.raises(SystemExit) as e:
        nfa.main(["--out", str(out)])
    assert e.value.code == 2 and out.read_text() == "{}"


def test_calib_mc_seeds_fast(tmp_path, monkeypatch):
    """experiments/calib_mc_seeds.py: one row per baseline size with the calibration's figures, the Monte Carlo's own
    variance shrinking as its runs grow (the baseline and the fit stood in for by a small fake: the real study
    calibrates OptoSkin, minutes per row); bad arguments exit 2 before anything runs."""
    import dataclasses
    import json
    import types

    import pytest

    study = load("calib_mc_seeds")
    ev = load("eval_mc_data")
    rng = np.random.default_rng(0)

    @dataclasses.dataclass(frozen=True)
    class Guide:
        multiple_scattering: float = 0.0

    def baseline(exposure, seeds=64):
        runs = 100.0 + rng.normal(0.0, 10.0, (seeds, 2, 3, 8))
        mean, var = ev.mc_mean_and_variance(runs)
        return types.SimpleNamespace(replace=lambda **k: k, waveguide=Guide()), mean * exposure, var * exposure**2

    def calibrate(scene, cap, mc_var, optics):
        assert scene["waveguide"].multiple_scattering == 0.5 and optics == "guided"  # the held coupling, as the studies
        fig = {"result": "successful", "converged": True, "reduced_chi2_photon_noise": 1.0 + float(np.mean(mc_var)) / 1e4,
               "reduced_chi2_with_mc_variance": 1.0, "mc_variance_over_photon_variance_median": float(np.median(mc_var)),
               "mc_variance_share_of_photon_weighted_chi2": 0.0, "n1_rel_error": 0.0, "mu_t_rel_error": 0.0, "steps": 1,
               "seconds": 0.0}
        return fig, types.SimpleNamespace(params=types.SimpleNamespace(mu_s_per_m=0.6, mu_a_per_m=0.14))

    monkeypatch.setattr(ev, "calibration_baseline", baseline)
    monkeypatch.setattr(ev, "_capture", lambda scene, expected, frames, seed, source: expected)
    monkeypatch.setattr(ev, "calibrate_capture", calibrate)
    out = tmp_path / "s.json"
    assert study.main(["--seeds", "4,64", "--out", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert [r["mc_runs"] for r in rows] == [4, 64] and rows[0]["result"] == "successful"
    assert rows[1]["mc_variance_over_photon_variance_median"] < 0.2 * rows[0]["mc_variance_over_photon_variance_median"]
    for bad in (["--seeds", "1"], ["--seeds", "x"], ["--exposure", "0"], ["--guided-switch", "NOPE=1"]):
        with pytest.raises(SystemExit) as e:
            study.main(["--out", str(tmp_path / "b.json"), *bad])
        assert e.value.code == 2
    with pytest.raises(SystemExit) as e:  # an existing output needs --overwrite
        study.main(["--out", str(out)])
    assert e.value.code == 2
