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


def test_recovery_study_fast(tmp_path):
    study = load("study_recovery")
    cfg = study.RecoveryConfig(frames=40, replicates=2, n1=(1.45,), mu_s_per_m=(0.6,), mu_a_per_m=(0.3,))
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
