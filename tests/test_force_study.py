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
