"""Calibration studies (experiments/study_fit_speed.py, study_coverage.py): fast runs on a small scene."""

import json

import numpy as np
import pytest

from test_studies import load


@pytest.mark.slow  # 60 s cold (two fit compilations): over the suite's budget; the emcee part's test stays fast
def test_fit_speed_study_settings_and_scipy(tmp_path):
    """Settings and scipy parts on a small scene (the emcee part has its own test)."""
    study = load("study_fit_speed")
    cfg = study.FitSpeedConfig(
        sensors=3,
        zones=3,
        bins=96,
        frames=40,
        captures=1,
        repeats=1,
        settings=(study.Setting("default"),),
        scipy_methods=("trf",),
        scipy_jacobians=("2-point",),
        emcee=None,
    )
    r = study.run(cfg, tmp_path, progress=False)
    (row,) = r["settings"]
    assert row["converged"] == 1 and row["n1_rel_error_max"] < 0.005 and row["mu_t_rel_error_max"] < 0.05
    assert row["warm_fit_s_median"] > 0 and row["first_fit_s"] > 0
    sc = r["scipy"]["methods"]["trf 2-point"]
    # the same problem from the same start: scipy and tofjax agree to a fraction of a standard error
    assert sc["z_max_vs_tofjax_median"] < 0.5 and np.isfinite(sc["ratio_over_tofjax_median"])
    saved = json.loads((tmp_path / "fit_speed.json").read_text())
    assert saved["data"] == "simulated" and saved["emcee"] is None
    assert "scipy.optimize.least_squares" in (tmp_path / "fit_speed.md").read_text()
    assert (tmp_path / "fit_speed.png").stat().st_size > 5000


def test_fit_speed_emcee_steps_fast():
    study = load("study_fit_speed")
    from tofjax.scene import load_scene

    e = study.run_emcee(study.EmceeStudy(frames=40, walkers=24, max_steps=120, steps=(60,)), load_scene("optoskin"), False)
    assert [x["steps"] for x in e["rows"]] == [60, e["steps_run"]]
    # the whole chain against itself: no error; a prefix: a finite, non-negative one
    assert e["rows"][-1]["n1"]["endpoint_error_over_width"] == 0.0
    assert all(np.isfinite(e["rows"][0][k]["endpoint_error_over_width"]) for k in ("n1", "mu_t", "mu_s_per_m", "mu_a_per_m"))
    assert "emcee steps against interval accuracy" in study.markdown(
        {"data": "simulated", "scene": "x", "config": {"frames": 1, "captures": 1, "repeats": 1}, "machine": "m",
         "settings": [], "scipy": {"tofjax_warm_solve_s_median": 1.0, "tofjax_z_max_median": 0.0, "methods": {}}, "emcee": e}
    )


def test_coverage_study_fast(tmp_path):
    study = load("study_coverage")
    # NUTS with test_nuts.py's shapes and settings: one compiled program for both
    cfg = study.CoverageConfig(frames=30, replicates=3, posterior_replicates=1, chains=2, warmup=60, draws=60)
    r = study.run(cfg, tmp_path, progress=False)
    assert r["finished"] and r["laplace"]["replicates"] == 3 and r["posterior"]["replicates"] == 1
    for key in ("laplace", "posterior"):
        assert all(0.0 <= v <= 1.0 for v in r[key]["coverage"].values())
    row = r["replicates_run"][0]
    lo, hi = row["laplace"]["n1"]["interval"]
    assert lo < hi and row["laplace"]["n1"]["covers"] == (lo <= r["truth"]["n1"] <= hi)
    assert json.loads((tmp_path / "coverage.json").read_text())["data"] == "simulated"
    assert "| laplace (3) |" in (tmp_path / "coverage.md").read_text()
    assert set(r["posterior"]["coverage_stderr"]) == set(r["posterior"]["coverage"])
    assert row["posterior_rhat_max"] > 0.9 and row["posterior_seconds"] > 0
    assert (tmp_path / "coverage.png").stat().st_size > 5000


def test_coverage_config_rejects_unknown_keys(tmp_path):
    from tofjax.config import ConfigError, from_dict, load_toml

    study = load("study_coverage")
    p = tmp_path / "c.toml"
    p.write_text("replicate = 3\n")
    with pytest.raises(ConfigError, match="replicate"):
        from_dict(study.CoverageConfig, load_toml(p))


def test_independent_study_summary_counts_targets():
    """The independent-data study's summary: a fit counts for the targets only if converged,
    n1 within 1% and mu_t within 25%."""
    study = load("study_calib_independent")
    rows = [
        {"converged": True, "n1_rel_error": 0.005, "mu_t_rel_error": -0.2, "reduced_chi2": 1.1},
        {"converged": False, "n1_rel_error": 0.001, "mu_t_rel_error": 0.1, "reduced_chi2": 9.0},
        {"converged": True, "n1_rel_error": -0.02, "mu_t_rel_error": 0.1, "reduced_chi2": 1.0},
    ]
    s = study._summary(rows)
    assert (s["fits"], s["converged"], s["n1_within_1pct"], s["mu_t_within_25pct"], s["all_targets"]) == (3, 2, 2, 3, 1)
    assert s["n1_rel_error_max"] == pytest.approx(0.02) and s["reduced_chi2_max"] == 9.0


@pytest.mark.slow
def test_independent_study_quick(tmp_path):
    """The study end to end on a tiny scene: own data calibrate; batch and single fits agree."""
    study = load("study_calib_independent")
    r = study.run(tmp_path, quick=True, progress=False)
    assert json.loads((tmp_path / "calib_independent.json").read_text())["own"]["summary"]["fits"] == 1
    assert r["own"]["summary"]["converged"] == 1 and r["own"]["summary"]["n1_rel_error_max"] < 0.01
    assert r["batch_speed"]["max_n1_difference_batch_vs_single"] < 1e-6
    assert set(study.COLUMNS) <= set(r) and r["independent_scene_without_ms"]["summary"]["fits"] == 1


def test_detect_calibrated_study_is_a_script(tmp_path):
    """The six-contact study on calibrated independent data imports and says what it writes
    (its end-to-end run is the study itself: minutes, not a test)."""
    mod = load("eval_detect_calibrated")
    assert "detect_calibrated_<source>.json" in mod.__doc__ and "Simulated" in mod.__doc__
    # both columns: the own simulator beside the independent one; anything else is refused first
    with pytest.raises(ValueError, match="source"):
        mod.run(tmp_path, source="mine")
    with pytest.raises(SystemExit):
        mod.main(["--source", "mine", "--out", str(tmp_path)])


@pytest.mark.slow  # three fits of a 3 x 7 x 128 baseline: 76-157 s at load 15 on the shared VM
def test_second_basin_at_4_per_m_is_left(tmp_path):
    """Issue 13's second basin: the independent simulator at n1 = 1.3, mu_t = 4 /m, fitted
    from the nominal scene stating no multiple scattering, ended at mu_t of about 0.1 /m with
    a reduced chi-square of 3.2 (accepted, under 4.0). With the basin check it ends in the
    true basin."""
    study = load("study_calib_independent")
    r = study.run(tmp_path, columns=("independent_scene_without_ms",), n1s=(1.3,), mu_ts=(4.0,), batch=False, progress=False)
    row = r["independent_scene_without_ms"]["fits"][0]
    assert row["converged"] and abs(row["mu_t_rel_error"]) <= 0.25
    # n1 is -1.76% here (was -1.63% in the wrong basin): the emission time comes out 25 ps late
    # on this simulator at 4 /m (README, "On data tofjax did not make"); not the basin's doing
    assert abs(row["n1_rel_error"]) <= 0.025


def test_coverage_merge_counts_each_seed_once():
    """Runs side by side on overlapping seeds: a seed is one capture, kept once, with its
    posterior if either run has one; runs of other settings are refused."""
    study = load("study_coverage")
    cfg = {"sensors": 3, "zones": 3, "bins": 96, "frames": 40, "sampler": "nuts", "chains": 2, "warmup": 10, "draws": 10,
           "nuisance_width": 0.3, "pilot": True, "target_accept": 0.8}

    def row(seed, covers, post=None):
        q = {k: {"interval": [0, 1], "covers": covers, "width": 1.0} for k in study.QUANTITIES}
        r = {"seed": seed, "laplace": q}
        if post is not None:
            r |= {"posterior": {k: {"interval": [0, 1], "covers": post, "width": 1.0} for k in study.QUANTITIES},
                  "posterior_rhat_max": 1.0, "posterior_ess_min": 100.0, "posterior_divergences": 0}
        return r

    def part(seed, rows):
        return {"config": {**cfg, "seed": seed, "replicates": len(rows)}, "finished": True, "seconds": 1.0,
                "seconds_fits": 1.0, "seconds_posteriors": 1.0, "posterior": {"replicates": 0}, "replicates_run": rows}

    a = part(0, [row(0, True, True), row(1, True), row(2, False)])
    b = part(1, [row(1, True, False), row(2, False, True)])
    m = study.merge([a, b])
    assert m["laplace"]["replicates"] == 3 and m["posterior"]["replicates"] == 3
    assert m["laplace"]["coverage"]["n1"] == pytest.approx(2 / 3) and m["posterior"]["coverage"]["n1"] == pytest.approx(2 / 3)
    with pytest.raises(ValueError, match="settings"):
        study.merge([a, {**b, "config": {**b["config"], "draws": 11}}])


def _mu_low_rows(errors, stderr):
    return [{"mu_t_rel_error": e, "mu_t_stderr_rel": stderr, "converged": True, "n1_rel_error": 0.001,
             "reduced_chi2": 1.0, "seconds": 0.1} for e in errors]


def test_mu_low_summaries_fast():
    """The bias, z and shared-misfit summaries of experiments/study_mu_low.py on made-up fits (no fit: < 1 s)."""
    study = load("study_mu_low")
    rng = np.random.default_rng(0)
    e = 0.1 + 0.2 * rng.standard_normal(400)
    g = study._group(_mu_low_rows(e, 0.2), 0.5 * rng.standard_normal((400, 2, 3, 16)))
    assert g["mu_t_bias"] == pytest.approx(e.mean()) and abs(g["mu_t_bias_in_its_stderr"] - 10) < 3
    assert g["z_sd"] == pytest.approx(1.0, abs=0.1) and g["sd_over_laplace"] == pytest.approx(1.0, abs=0.1)
    assert g["within_25pct"] == int(np.sum(np.abs(e) <= 0.25))
    # residuals of sd 0.5 that replicates do not share: the scaled mean map has a mean square ~0.25
    assert g["shared_misfit"]["mean_square"] == pytest.approx(0.25, rel=0.45)  # 96 cells: chi-square sd 14%
    # a misfit every replicate shares stands out: one bin 1 sigma high in every zone
    r = 0.5 * rng.standard_normal((16, 2, 3, 16))
    r[..., 5] += 1.0
    s = study._group(_mu_low_rows(e[:16], 0.2), r)["shared_misfit"]
    assert s["by_bin_worst"] == 5 and s["by_bin_abs_max"] > 6  # expected 4 x sqrt(6) = 9.8
    # frame scaling: sd falling as 1/sqrt(frames) gives the exponent -1/2 and 2 sd = 25% at 4x60 frames for sd 0.25
    cfg = study.MuLowConfig(n1=(1.45,), frames=(60, 240, 960), replicates=2, columns=("own",))
    groups = {"own": {"1.45": {str(f): {"mu_t_rel_error_sd": 0.25 * (60 / f) ** 0.5, "mu_t_bias": 0.0} for f in cfg.frames}}}
    sc = study._scaling(groups, cfg)["own n1=1.45"]
    assert sc["sd_power_law_exponent"] == pytest.approx(-0.5)
    assert sc["frames_for_2sd_within_25pct"] == pytest.approx(240) and sc["frames_for_2sd_within_25pct_sqrt_law"] == pytest.approx(240)
    assert sc["frames_for_bias_plus_2sd_within_25pct"] == pytest.approx(240)
    groups["own"]["1.45"]["960"]["mu_t_bias"] = -0.3  # a bias over 25%: no frame count is enough
    assert study._scaling(groups, cfg)["own n1=1.45"]["frames_for_bias_plus_2sd_within_25pct"] is None
    with pytest.raises(ValueError, match="replicates"):
        study.MuLowConfig(replicates=1)
    with pytest.raises(ValueError, match="columns"):
        study.MuLowConfig(columns=("mine",))


def test_mu_low_planner_check_fast():
    """The planner check of experiments/study_mu_low.py on made-up fits: honest 1/sqrt(frames)
    errors are predicted (observed / predicted sd ~ 1, share within 25% as predicted); a bias
    leaves the sd predicted but the share below the prediction."""
    study = load("study_mu_low")
    rng = np.random.default_rng(1)
    mu = study.MU_T

    def rows(frames, bias, n=4000):
        sd = 0.27 * (60 / frames) ** 0.5
        e = bias + sd * rng.standard_normal(n)
        return [{"mu_t_rel_error": x, "mu_t_stderr_rel": sd, "mu_s_per_m": 0.8 * mu * (1 + x), "mu_a_per_m": 0.2 * mu * (1 + x),
                 "n1_stderr": 0.001, "n1_rel_error": 0.0} for x in e]

    fits = {"own": {"1.45": {str(f): rows(f, 0.0) for f in (60, 960)}},
            "independent": {"1.45": {"60": rows(60, 0.2), "960": rows(960, 0.2)}}}
    p = study.planner_check(fits)["by_point"]
    honest, biased = p["own n1=1.45"], p["independent n1=1.45"]
    assert honest["planned_frames_from_median_sd"] == int(np.ceil(60 * (1.959963984540054 * 0.27 / 0.25) ** 2))
    assert honest["at_more_frames"]["960"]["observed_over_predicted"] == pytest.approx(1.0, abs=0.05)
    assert honest["at_more_frames"]["960"]["observed_within"] == pytest.approx(honest["at_more_frames"]["960"]["predicted_within"], abs=0.02)
    b = biased["at_more_frames"]["960"]
    assert b["observed_over_predicted"] == pytest.approx(1.0, abs=0.05) and b["observed_within"] < b["predicted_within"] - 0.15  # 0.77 against 1.00
    assert honest["n1_planned_frames_max"] == 2  # 60 (1.96 x 0.069% / 1%)^2 = 1.1: 1% needs almost nothing


def test_mu_low_merge_replicates_fast(tmp_path):
    """Parts with other seeds join into one set of fits per point, figures recomputed; a seed twice is refused."""
    study = load("study_mu_low")
    rng = np.random.default_rng(2)

    def part(name, seeds, frames=(60, 960)):
        fits = {"own": {"1.45": {}}}
        for i, f in enumerate(frames):
            rows = _mu_low_rows(0.27 * (60 / f) ** 0.5 * rng.standard_normal(len(seeds)), 0.27 * (60 / f) ** 0.5)
            for r, sd in zip(rows, seeds):
                r.update(seed=100 * i + sd, mu_s_per_m=0.04, mu_a_per_m=0.01, n1_stderr=0.001)
            fits["own"]["1.45"][str(f)] = rows
        groups = {"own": {"1.45": {f: study._group(rows, None) for f, rows in fits["own"]["1.45"].items()}}}
        cfg = study.MuLowConfig(n1=(1.45,), frames=frames, replicates=len(seeds), columns=("own",))
        d = study._result(cfg, study.FitConfig(), groups, fits, None, 0.0, finished=True)
        (tmp_path / name).write_text(json.dumps(d))
        return tmp_path / name

    a, b = part("a.json", range(0, 4)), part("b.json", range(4, 10))
    m = study.merge_replicates([a, b], tmp_path / "m")
    g = m["groups"]["own"]["1.45"]["960"]
    assert g["replicates"] == 10 and m["config"]["replicates_by_part"] == [4, 6]
    e = [r["mu_t_rel_error"] for r in m["fits"]["own"]["1.45"]["960"]]
    assert g["mu_t_bias"] == pytest.approx(np.mean(e)) and m["planner"]["by_point"]["own n1=1.45"]["fits"] == 10
    with pytest.raises(ValueError, match="seed fitted twice"):
        study.merge_replicates([a, a], tmp_path / "m2")
    with pytest.raises(ValueError, match="seed fitted twice"):  # seed 100 at 960 frames, again at 60
        study.merge_replicates([a, part("c.json", range(100, 102), frames=(60,))], tmp_path / "m3")
    with pytest.raises(ValueError, match="first_replicate"):
        study.MuLowConfig(replicates=32, first_replicate=80)


@pytest.mark.slow  # a fit compilation (~15 s idle, minutes on the loaded VM): over the suite's budget
def test_mu_low_study_quick(tmp_path):
    study = load("study_mu_low")
    r = study.run(tmp_path, study.QUICK, progress=False)
    assert r["finished"] and r["data"].startswith("simulated")
    for col in ("own", "independent"):
        g = r["groups"][col]["1.45"]["20"]
        assert g["replicates"] == 2 and np.isfinite(g["mu_t_bias"]) and g["shared_misfit"]["mean_square"] > 0
    saved = json.loads((tmp_path / "mu_low.json").read_text())
    assert set(saved["pooled"]) == {"own frames=20", "independent frames=20"}
    merged = study.merge([tmp_path / "mu_low.json"], tmp_path / "m")
    assert merged["pooled"] == saved["pooled"]


def test_coverage_comparison_and_sampler_stats():
    """Laplace against posterior per quantity (target band, nominal 95% within 1.96 binomial
    errors, the paired discordant counts) and the NUTS statistics, on hand-made rows."""
    study = load("study_coverage")

    def q(covers):
        return {k: {"interval": [0, 1], "covers": covers, "width": 1.0} for k in study.QUANTITIES}

    rows = [{"seed": i, "laplace": q(True)} for i in range(100)]  # Laplace: 100 of 100
    for i in range(20):  # posterior on the first 20: 0 and 1 missed
        rows[i] |= {"posterior": q(i > 1), "posterior_ess_min": 100.0 + 10 * i, "posterior_rhat_max": 1.0 + i / 1000,
                    "posterior_divergences": int(i == 5) * 3, "posterior_seconds": 2.0,
                    "posterior_ess_n1_mu": {"n1": 300.0, "mu_s_per_m": 200.0, "mu_a_per_m": 150.0}}
    c = study.comparison(rows)["n1"]
    assert c["laplace"]["coverage"] == 1.0 and not c["laplace"]["within_90_98"]
    assert not c["laplace"]["matches_nominal_95"]  # 1.0 at 100: 2.29 nominal errors of 2.2% above 0.95
    assert c["posterior"]["coverage"] == pytest.approx(0.9) and c["posterior"]["within_90_98"]
    assert c["posterior"]["matches_nominal_95"]  # 0.90 at 20: 1.03 nominal errors of 4.9%
    assert (c["paired_replicates"], c["only_laplace_covers"], c["only_posterior_covers"]) == (20, 2, 0)
    s = study.sampler_stats(rows)
    assert s["posteriors"] == 20 and s["ess_min_at_least_200"] == 10 and s["rhat_max_at_most_1_01"] == 11
    assert (s["replicates_with_divergences"], s["divergences_total"], s["seconds_per_posterior_median"]) == (1, 3, 2.0)
    assert study.sampler_stats(rows[20:]) == {"posteriors": 0}
