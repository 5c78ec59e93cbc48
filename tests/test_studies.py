"""Studies in experiments/: a fast run of each here; the full ones are marked slow."""

import importlib.util
import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]


def load(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / "experiments" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


def test_recovery_study_fast(tmp_path, optoskin):
    from tofjax.scene import SensorModel

    study = load("study_recovery")
    # three of the OptoSkin sensors, 3 zones, 96 bins (test_calibrate's small scene): the full
    # scene's batched fit cost 44-155 s here, most of it running the vmapped fit
    small = optoskin.replace(sensor=SensorModel(bin_width_s=1e-10, n_bins=96, zones=3, fov_deg=29.0),
                             sensors=optoskin.sensors[:3])
    (tmp_path / "small.toml").write_text(small.to_toml())
    cfg = study.RecoveryConfig(scene=str(tmp_path / "small.toml"), frames=40, replicates=2, n1=(1.45,),
                               mu_s_per_m=(0.6,), mu_a_per_m=(0.3,))
    result = study.run(cfg, tmp_path, progress=False)
    (point,) = result["points"]
    assert point["truth"] == {"n1": 1.45, "mu_s_per_m": 0.6, "mu_a_per_m": 0.3}
    assert point["n1_rel_error_max"] < 0.005
    assert abs(point["bias"]["mu_t"]) < 0.05 * 0.9
    assert json.loads((tmp_path / "recovery.json").read_text())["data"] == "simulated"
    assert (tmp_path / "recovery.png").stat().st_size > 5000


@pytest.mark.slow
def test_recovery_study_full(tmp_path):
    study = load("study_recovery")
    study.main(["--config", str(ROOT / "configs" / "studies" / "recovery.toml"), "--out", str(tmp_path)])
    assert (tmp_path / "recovery.json").exists()


def test_cpu_opt_level_refuses_bad_arguments(tmp_path):
    """experiments/cpu_opt_level.py (a benchmark: each round runs three cold calibrations in fresh processes, so the
    run itself is not repeated here): no output file or no rounds is a usage error, before any worker starts."""
    study = load("cpu_opt_level")
    for argv in ([], ["--out", str(tmp_path / "x.json"), "--rounds", "0"], ["--out", str(tmp_path / "x.json"), "--warm", "0"]):
        with pytest.raises(SystemExit) as e:
            study.main(argv)
        assert e.value.code == 2
    assert not (tmp_path / "x.json").exists()
    assert set(study.VARIANTS) == {"default", "level1", "level0"} and "optimization_level" not in study.VARIANTS["default"]


def test_tree_compare_refuses_bad_arguments(tmp_path):
    """experiments/tree_compare.py (a benchmark: each round runs two cold calibrations in fresh processes): a base that
    is not a checkout, no rounds, or no output is a usage error before any worker starts."""
    study = load("tree_compare")
    out = str(tmp_path / "x.json")
    for argv in ([], ["--base", str(tmp_path), "--out", out], ["--base", str(study.ROOT), "--out", out, "--rounds", "0"],
                 ["--base", str(study.ROOT)]):
        with pytest.raises(SystemExit) as e:
            study.main(argv)
        assert e.value.code == 2
    assert not (tmp_path / "x.json").exists()


def test_node_terms_jvp_benchmark_fast(tmp_path):
    """experiments/node_terms_jvp.py with one round of two calls: its record, and the two derivatives' Jacobians agree."""
    study = load("node_terms_jvp")
    for argv in ([], ["--out", str(tmp_path / "x.json"), "--rounds", "0"]):
        with pytest.raises(SystemExit) as e:
            study.main(argv)
        assert e.value.code == 2
    assert study.main(["--out", str(tmp_path / "n.json"), "--rounds", "1", "--calls", "2"]) == 0
    rec = json.loads((tmp_path / "n.json").read_text())
    assert set(rec["median_s"]) == {"reverse_direct", "reverse_matrix_product", "jacfwd4_direct", "jacfwd4_matrix_product"}
    assert all(v > 0 for v in rec["median_s"].values())
    assert rec["jacobian_max_relative_difference"] < 1e-10


def test_fit_valley_study_fast(tmp_path):
    """experiments/fit_valley.py --quick: at the default fit's optimum the interface backscatter, the edge
    reflectance and the zones' gains are nearly one direction (the amplitude near-gauge the study measures),
    and holding the backscatter removes it: the held fit converges, within about a standard error of the
    free one, at a chi-square no more than a few units above it."""
    study = load("fit_valley")
    out = tmp_path / "v.json"
    assert study.main(["--quick", "--variants", "ib_held", "--out", str(out)]) == 0
    rec = json.loads(out.read_text())
    assert [r["baseline"] for r in rec["fits"]] == ["own", "independent"]
    for r in rec["fits"]:
        c = r["correlations"]
        assert c["ib_R"] > 0.9 and c["ib_gain_median"] < -0.9
        assert c["relative_stderr"]["end_reflectance"] > 0.3  # the gauge: R's scale is barely determined
        assert c["mu_t_relative_stderr"] < c["relative_stderr"]["mu_a_per_m"]
        assert r["data_share"]["end_reflectance"] < 0.5 < r["data_share"]["extinction"]
        assert r["default"]["converged"] and r["ib_held"]["converged"]
        assert max(abs(x) for x in r["ib_held"]["shift_in_stderr"].values()) < 2.0
        assert -1.0 < r["ib_held"]["chi2_minus_default"] < 5.0  # either may stop short along the flat valley by < 1
        # the held value fixes the scale: the gains are then the data's
        assert r["ib_held"]["gain_data_share"] > 0.5 > r["default"]["gain_data_share"]
    assert set(rec["summary"]) == {"default", "ib_held"}
    with pytest.raises(SystemExit) as e:
        study.main(["--quick", "--variants", "newton", "--out", str(tmp_path / "w.json")])
    assert e.value.code == 2


def test_position_bound_study_fast(tmp_path):
    """experiments/position_bound.py --quick: the joint position bound of two six-contact configurations on
    OptoSkin at 64x; border contacts are placed less well than interior ones (the bound's recall lower, their
    standard deviation larger), every probability is one, and an eval_mc_data.py result is set beside the
    bound of its contact set and exposure. Bad arguments exit 2."""
    study = load("position_bound")
    obs = tmp_path / "eval.json"
    obs.write_text(json.dumps({"settings": {"config_seed": 6, "exposure": 64.0, "configs": 2}, "detection": {
        "own": {"methods": {"fit": {"recall": 0.9, "recall_border": 0.8, "recall_interior": 1.0, "precision": 0.95}}}}}))
    out = tmp_path / "b.json"
    assert study.main(["--quick", "--out", str(out), "--observed", str(obs)]) == 0
    rec = json.loads(out.read_text())
    (b,) = rec["bound"]
    assert (b["config_seed"], b["exposure"], b["contacts"]) == (6, 64.0, 12) and 0 < b["border_contacts"] < 12
    assert b["recall_bound_border"] < b["recall_bound_interior"]
    sd_b, sd_i = b["position_sd_major_cm_border_quantiles_10_50_90"][1], b["position_sd_major_cm_interior_quantiles_10_50_90"][1]
    assert sd_b > sd_i > 0
    assert all(0.0 <= p <= 1.0 for p in b["per_contact"]["match_probability"])
    (o,) = rec["observed"]
    assert o["column"] == "own" and o["recall_bound_border"] == b["recall_bound_border"]
    for bad in (["--exposures", "x"], ["--exposures", "-1"]):
        with pytest.raises(SystemExit) as e:
            study.main(["--out", str(tmp_path / "c.json"), *bad])
        assert e.value.code == 2


def test_solver_secant_study_fast(tmp_path):
    """experiments/solver_secant.py --quick: both solvers fit one own and one independent baseline of
    a small scene, converge, and end at the same optimum; its record has the paired summary."""
    study = load("solver_secant")
    out = tmp_path / "s.json"
    assert study.main(["--quick", "--out", str(out)]) == 0
    rec = json.loads(out.read_text())
    assert [r["baseline"] for r in rec["fits"]] == ["own", "independent"]
    for r in rec["fits"]:
        assert r["plain"]["converged"] and r["secant"]["converged"]
        assert r["plain"]["steps"] > 0 and r["secant"]["steps"] > 0
        assert abs(r["secant"]["n1"] / r["plain"]["n1"] - 1) < 1e-4
        assert abs(r["secant"]["reduced_chi2"] - r["plain"]["reduced_chi2"]) < 1e-3
    assert set(rec["summary"]) == {"quick", "all"}
    assert rec["summary"]["all"]["plain"]["fits"] == 2
    with pytest.raises(SystemExit) as e:  # an existing record is not overwritten without --overwrite
        study.main(["--quick", "--out", str(out)])
    assert e.value.code == 2


def test_model_compile_compare_fast(tmp_path):
    """experiments/model_compile_compare.py's worker on the default optics, in this process: every program's compile,
    call and instruction count, and the model's output saved for the comparison. Bad arguments exit 2 (the
    side-by-side run itself starts fresh processes, too slow for the default run)."""
    study = load("model_compile_compare")
    rec = study.worker(2, str(tmp_path / "y.npz"), ("default",))
    assert set(rec) == {"default/forward", "default/value_and_grad"}
    for v in rec.values():
        assert v["compile_cpu_s"] > 0 and v["call_ms"] > 0 and v["instructions"] > 10
    import numpy as np

    y = np.load(tmp_path / "y.npz")["default"]
    assert y.ndim == 3 and np.isfinite(y).all() and y.max() > 0
    for bad in (["--optics", "bulk"], ["--rounds", "0"], ["--base", str(tmp_path)]):
        argv = ["--base", str(ROOT), "--out", str(tmp_path / "x.json"), *bad]
        with pytest.raises(SystemExit) as e:
            study.main(argv)
        assert e.value.code == 2
