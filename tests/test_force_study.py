"""experiments/study_force.py: a fast run here; the full study is marked slow."""

import json
from pathlib import Path

import pytest
from test_studies import load

ROOT = Path(__file__).parents[1]



def test_force_study_fast(tmp_path):
    study = load("study_force")
    override = {
        "plots": False,
        "data": {"cache_dir": str(tmp_path / "data"), "protocol": {
            "velocities_mm_s": [1.0, 5.0], "train_forces_n": [10.0, 40.0], "repetitions": 2,
            "test_forces_per_velocity": 2, "test_captures_per_velocity": 1, "hold_s": 1.0, "rest_s": 1.0,
            "baseline_s": 1.0}},
        "training": {"epochs": 2},
        "forest": {"trees": 3, "max_depth": 4, "n_jobs": 1},
    }
    cfg = study.ForceStudyConfig(mlp_configs=("configs/force/mlp_dual.toml",),
                                 alternative_configs=("configs/force/nonlinear.toml",), variants=("single",),
                                 override=override, prediction_repeats=5)
    s = study.run(cfg, tmp_path, progress=False)
    assert [m["name"] for m in s["runs"]] == ["mlp_dual", "nonlinear_single"]
    assert set(s["forest_mae_reduction_by_run"]) == {"mlp_dual"}
    assert s["prediction_time_us"]["mlp_dual"]["mlp_rf_us"] > 0
    saved = json.loads((tmp_path / "force.json").read_text())
    assert saved["data"] == "simulated"
    md = (tmp_path / "force.md").read_text()
    assert "MLP + RF" in md and "nonlinear" in md and "v = 5.0 mm/s" in md
    assert (tmp_path / "force_velocity.png").stat().st_size > 5000


def test_study_config_loads():
    study = load("study_force")
    cfg = study.load_study_config(ROOT / "configs" / "studies" / "force.toml")
    assert len(study._configs(cfg)) == len(cfg.mlp_configs) + len(cfg.alternative_configs) * len(cfg.variants)


@pytest.mark.slow
def test_force_study_full(tmp_path):
    study = load("study_force")
    study.main(["--config", str(ROOT / "configs" / "studies" / "force.toml"), "--out", str(tmp_path)])
    assert (tmp_path / "force.json").exists()


def test_force_position_study_fast(tmp_path):
    study = load("study_force_position")
    protocol = {"velocities_mm_s": [5.0], "train_forces_n": [20.0, 50.0], "hold_s": 1.0, "rest_s": 0.5,
                "baseline_s": 1.0, "test_forces_per_velocity": 2, "repetitions": 1,
                "positions_m": [[0.09, -0.01], [0.19, 0.01]], "unseen_positions_m": [[0.14, 0.0]],
                "two_contacts_m": [[[0.09, 0.0], [0.21, 0.0]]]}
    runs = [r for r in study.RUNS if r[0] in ("mlp_derivative", "nonlinear")]
    res = study.run(tmp_path, epochs=2, runs=runs, protocol=protocol, indep_frames=(6, 3))
    models = {(r["run"], r["model"]) for r in res["rows"]}
    assert models == {("mlp_derivative", "mlp"), ("mlp_derivative", "mlp_rf"), ("nonlinear", "nonlinear")}
    assert all(r["unseen_over_seen"] > 0 for r in res["rows"])
    assert set(res["independent"]["mlp_rf"]["by_split"]) == {"seen", "unseen"}
    assert "seen, v = 5 mm/s" in res["forest_where"]["mlp_derivative"]
    assert {r["split"] for r in res["by_position_mlp_derivative"]} == {"seen", "unseen"}
    md = (tmp_path / "force_position.md").read_text()
    assert "unseen / seen" in md and "simulated" in md and "Independent" in md
    with pytest.raises(Exception, match="exists"):
        study.run(tmp_path, epochs=2, runs=runs, protocol=protocol, independent=False)


def test_force_seed001_study_fast(tmp_path):
    study = load("study_force_position")
    override = {"data": {"protocol": {"velocities_mm_s": [5.0], "train_forces_n": [20.0, 50.0], "repetitions": 1,
                                      "test_forces_per_velocity": 2, "test_captures_per_velocity": 1, "hold_s": 1.0,
                                      "rest_s": 0.5, "baseline_s": 1.0}},
                "training": {"epochs": 2}, "forest": {"trees": 3, "max_depth": 4, "n_jobs": 1}}
    res = study.run_seed001(tmp_path, configs=(("configs/force/mlp_derivative.toml", {}),), override=override)
    assert set(res["runs"][0]["mae_n"]) == {"mlp", "mlp_rf"} and res["data"].startswith("simulated")
    assert json.loads((tmp_path / "force_seed001.json").read_text())["targets"]["mlp_rf_overall_max_n"] == 1.0


def test_force_bench_fast(tmp_path):
    bench = load("bench_force")
    res = bench.run(tmp_path, repeats=5, trees=4, depth=3)
    assert [lay["depth"] for lay in res["layouts"]] == [3, 3]
    assert all(lay["mlp_rf_us"]["median"] > 0 for lay in res["layouts"])
    assert json.loads((tmp_path / "bench_force.json").read_text())["target_us"] == 100.0
    with pytest.raises(Exception, match="exists"):
        bench.run(tmp_path, repeats=5, trees=4, depth=3)
