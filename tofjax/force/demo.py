"""The force part of ``make demo``: a small force model trained on simulated indentations."""

from __future__ import annotations

import json
from pathlib import Path

from .train import run_config_from_dict, train

__all__ = ["DEMO_CONFIG", "run"]

#: A short protocol (two velocities, six forces, two repetitions) and a short schedule: ~15 s.
DEMO_CONFIG = {
    "name": "demo",
    "data": {
        "protocol": {
            "velocities_mm_s": [1.0, 5.0],
            "train_forces_n": [10.0, 20.0, 30.0, 40.0, 50.0, 60.0],
            "repetitions": 2,
            "test_forces_per_velocity": 4,
            "test_captures_per_velocity": 1,
            "hold_s": 2.0,
            "rest_s": 1.0,
            "baseline_s": 1.0,
        },
    },
    "features": {"variant": "derivative"},
    "training": {"epochs": 80, "patience": 30, "batch_size": 32, "learning_rate": 3e-3},
    "forest": {"trees": 30, "max_depth": 12},
    "plots": True,
}


def run(out_dir: str | Path = "out/demo", *, seed: int = 0) -> list[str]:
    """Simulate a short indentation protocol, train a derivative-enhanced dual-input MLP + forest, return summary lines."""
    out = Path(out_dir)
    cfg = run_config_from_dict(DEMO_CONFIG | {"seed": seed, "data": DEMO_CONFIG["data"] | {"cache_dir": str(out / "force-data")}})
    run_dir = train(cfg, out / "force-runs", log=None)
    m = json.loads((run_dir / "metrics.json").read_text())
    lines = ["force estimation (seed 001): derivative-enhanced dual-input MLP + residual random forest, short simulated protocol"]
    for k, v in m["mae_n"].items():
        by = ", ".join(f"{vel} mm/s {e:.2f} N" for vel, e in v["by_velocity_mm_s"].items())
        lines.append(f"  test MAE {k:7s} {v['overall']:.2f} N  ({by})")
    lines.append(f"  {m['frames']['train']} training frames, {m['frames']['test']} test frames (unseen forces); run: {run_dir}")
    return lines
