"""Benchmark: the calibration posterior to 50 autocorrelation times on the default baseline.

Simulates the default OptoSkin baseline (100 frames), fits it, then runs the emcee posterior
(``tofjax calibrate --mcmc``'s defaults: 32 walkers, a check every 100 steps, stop at 50 tau
with tau stable to 1%, or at ``--max-steps``) and writes the wall time, the steps, tau, the
acceptance and the cost of one vectorised log-probability call (all walkers) to
``posterior_speed.json``.

    python experiments/bench_posterior.py --out out/posterior_speed
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

import tofjax
from tofjax.fit.calibrate import Calibrator, FitConfig
from tofjax.fit.posterior import PosteriorOptions, sample_posterior
from tofjax.scene import load_scene
from tofjax.simulate import simulate


def run(scene_name: str, frames: int, max_steps: int, walkers: int | None, dtype: str, out: Path, progress=True) -> dict:
    scene = load_scene(scene_name)
    cap = simulate(scene, frames, seed=1)
    cal = Calibrator(scene, FitConfig(dtype=dtype))
    fit = cal.fit(cap)
    t = time.perf_counter()
    post = sample_posterior(cal, cap, fit, PosteriorOptions(walkers=walkers, max_steps=max_steps, progress=progress))
    seconds = time.perf_counter() - t
    tau = float(np.nanmax(post.tau))
    result = {
        "benchmark": "calibration posterior to 50 tau",
        "data": f"simulated {scene_name} baseline, {frames} frames",
        "machine": f"{os.cpu_count()} CPUs shared with other jobs (load average at the end {os.getloadavg()[0]:.1f})",
        "dtype": dtype,
        "walkers": int(post.chain.shape[1]),
        "parameters": int(post.chain.shape[2]),
        "seconds": seconds,
        "steps": post.steps,
        "ms_per_step": 1e3 * seconds / max(post.steps, 1),
        "tau_max": tau,
        "steps_over_tau": post.steps / tau,
        "converged_50_tau": post.converged,
        "acceptance": post.acceptance,
        "n_effective": post.n_effective,
        "target_s": 120.0,
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "posterior_speed.json").write_text(json.dumps(result, indent=1))
    return result


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="optoskin")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--max-steps", type=int, default=6000)
    ap.add_argument("--walkers", type=int, default=None)
    ap.add_argument("--dtype", default="float64")
    ap.add_argument("--out", default="out/posterior_speed")
    a = ap.parse_args(argv)
    tofjax.enable_x64()
    r = run(a.scene, a.frames, a.max_steps, a.walkers, a.dtype, Path(a.out))
    print(json.dumps(r, indent=1))


if __name__ == "__main__":
    main()
