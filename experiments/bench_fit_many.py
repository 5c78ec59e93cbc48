"""Benchmark: many calibrations of one scene (:func:`tofjax.fit.calibrate_many`), the fits run as one
vmapped call (:func:`~tofjax.fit.fit_problem_batch`) against one after the other
(:func:`~tofjax.fit.fit_problem_loop`, the default on a CPU since this benchmark).

Each mode runs in its own fresh process (no compilation cache, ``TOFJAX_PROGRAM_STORE=0``), the
modes alternating over ``--rounds``: a first ``calibrate_many`` call (compile and run: what a study
pays once) and then ``--repeats`` warm calls on the same captures (median). The captures are
**simulated** baselines (``--frames`` frames, seeds 100..), of the test suite's small scene (three
OptoSkin sensors, 3 zones, 96 bins; ``--scene small``) or the default OptoSkin scene
(``--scene optoskin``). Also recorded: each fit's steps and n1, and the largest difference in n1
between the modes (the same fits, so it should be round-off).

    python experiments/bench_fit_many.py --out docs/results --fits 8 --rounds 2
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MODES = ("loop", "vmap")


def _scene(name: str):
    from tofjax.scene import SensorModel, load_scene

    scene = load_scene("optoskin")
    if name == "small":
        return scene.replace(sensor=SensorModel(bin_width_s=1e-10, n_bins=96, zones=3, fov_deg=29.0),
                             sensors=scene.sensors[:3])
    if name != "optoskin":
        raise SystemExit(f"--scene: 'small' or 'optoskin', got {name!r}")
    return scene


def worker(a) -> dict:
    import jax

    from tofjax.compile_cache import use_fast_cpu_compiler  # noqa: E402
    use_fast_cpu_compiler()  # the CLI's CPU compiler (before JAX's backend starts)
    jax.config.update("jax_enable_x64", True)
    import numpy as np

    from tofjax.fit import calibrate_many, fit_problem_batch, fit_problem_loop
    from tofjax.simulate import simulate

    scene = _scene(a.scene)
    caps = [simulate(scene, a.frames, seed=100 + i) for i in range(a.fits)]
    batch = {"loop": fit_problem_loop, "vmap": fit_problem_batch}[a.worker]

    def run():
        t = time.perf_counter()
        res = calibrate_many(caps, scene=scene, restart_failures=False, fit_batch=batch)
        return time.perf_counter() - t, res

    first_s, res = run()
    warm = [run()[0] for _ in range(a.repeats)]
    return {
        "mode": a.worker,
        "first_call_s": first_s,
        "warm_call_s": warm,
        "warm_median_s": statistics.median(warm),
        "steps": [int(r.steps) for r in res],
        "results": [r.result for r in res],
        "n1": [float(np.asarray(r.values["n1"])) for r in res],
        "backend": jax.default_backend(),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="folder for fit_many_bench.json")
    p.add_argument("--scene", default="small", help="small (default) or optoskin")
    p.add_argument("--fits", type=int, default=8, help="captures per call")
    p.add_argument("--frames", type=int, default=60, help="frames per simulated baseline")
    p.add_argument("--repeats", type=int, default=3, help="warm calls per process")
    p.add_argument("--rounds", type=int, default=2, help="processes per mode, alternating")
    p.add_argument("--name", default="fit_many_bench.json")
    p.add_argument("--worker", choices=MODES, help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if min(a.fits, a.frames, a.repeats, a.rounds) < 1:
        print("bench_fit_many: --fits, --frames, --repeats and --rounds must be >= 1", file=sys.stderr)
        return 2
    if a.worker:
        print(json.dumps(worker(a)))
        return 0
    env = {**os.environ, "TOFJAX_PROGRAM_STORE": "0", "PYTHONPATH": str(ROOT)}
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    runs = []
    for r in range(a.rounds):
        for mode in MODES if r % 2 == 0 else MODES[::-1]:
            cmd = [sys.executable, __file__, "--out", str(a.out), "--scene", a.scene, "--fits", str(a.fits),
                   "--frames", str(a.frames), "--repeats", str(a.repeats), "--worker", mode]
            load = os.getloadavg()[0]
            out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
            if out.returncode != 0:
                print(out.stderr[-3000:], file=sys.stderr)
                return 1
            row = json.loads(out.stdout.strip().splitlines()[-1])
            row["round"], row["load_before"] = r, load
            runs.append(row)
            print(f"round {r} {mode}: first call {row['first_call_s']:.1f} s, warm {row['warm_median_s']:.2f} s, "
                  f"steps {row['steps']}, load {load:.1f}", file=sys.stderr)

    def med(mode, key):
        return statistics.median(x[key] for x in runs if x["mode"] == mode)

    loop, vmap = ([x for x in runs if x["mode"] == m][0] for m in MODES)
    summary = {
        "first_call_s": {m: med(m, "first_call_s") for m in MODES},
        "warm_call_s": {m: med(m, "warm_median_s") for m in MODES},
        "loop_speedup_first_call": med("vmap", "first_call_s") / med("loop", "first_call_s"),
        "loop_speedup_warm": med("vmap", "warm_median_s") / med("loop", "warm_median_s"),
        "max_abs_n1_difference": max(abs(x - y) for x, y in zip(loop["n1"], vmap["n1"])),
        "steps": loop["steps"],
        "steps_mean": statistics.mean(loop["steps"]),
        "steps_max": max(loop["steps"]),
    }
    report = {
        "what": "calibrate_many on --fits simulated baselines: fits one after the other (loop) against one vmapped "
                "call (vmap); each mode in fresh processes, alternating; medians over rounds",
        "data": "simulated",
        "command": "python experiments/bench_fit_many.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "machine": f"{platform.machine()} {os.cpu_count()} cores, {platform.platform()}",
        "scene": a.scene, "fits": a.fits, "frames": a.frames,
        "summary": summary,
        "runs": runs,
    }
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / a.name).write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
