"""A cold calibration with and without compiling the fit ahead (``tofjax.compile_cache.compile_ahead``:
the fit and its Laplace pieces compile on two background threads while the start stages run).

Each measurement is a fresh Python process (``--worker``), cold (``TOFJAX_PROGRAM_STORE=0
TOFJAX_COMPILATION_CACHE=0``, no JAX persistent cache), with the CLI's CPU compiler
(:func:`tofjax.compile_cache.use_fast_cpu_compiler`), ``TOFJAX_COMPILE_AHEAD`` 0 and 1 alternating
``--rounds`` times (the order flipped every round). Per process, float64, the default scene, a
**simulated** 100-frame baseline (seed 1000): the first ``Calibrator(scene).fit`` (wall and this
process's CPU seconds), the programs XLA compiled during it (``jax.monitoring``'s
backend-compile events: each program should compile once either way) and the fit's answer.

    python experiments/compile_ahead.py --rounds 5 --out docs/results/compile_ahead.json
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


def worker() -> dict:
    sys.path.insert(0, str(ROOT))
    from tofjax.compile_cache import use_fast_cpu_compiler

    use_fast_cpu_compiler()
    import jax.monitoring as mon

    from tofjax import enable_x64
    from tofjax.fit import Calibrator
    from tofjax.scene import default_scene
    from tofjax.simulate import simulate

    enable_x64()
    scene = default_scene()
    cap = simulate(scene, 100, seed=1000)
    compiles = []

    def listen(name, secs, fun_name="", **_):
        if name == "/jax/core/compile/backend_compile_duration":
            compiles.append([fun_name, secs])

    mon.register_event_duration_secs_listener(listen)
    cal = Calibrator(scene)
    t, c = time.perf_counter(), time.process_time()
    res = cal.fit(cap)
    wall, cpu = time.perf_counter() - t, time.process_time() - c
    return {"cold_s": wall, "cold_cpu_s": cpu, "compiles": compiles, "n1": float(res.params.n1), "steps": int(res.steps),
            "result": res.result}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", help="JSON file to write")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        print(json.dumps(worker()))
        return 0
    if not a.out or a.rounds < 1:
        ap.error("--out is required and --rounds must be >= 1")
    runs = {"0": [], "1": []}
    for r in range(a.rounds):
        for v in (("0", "1") if r % 2 == 0 else ("1", "0")):
            env = dict(os.environ, TOFJAX_COMPILE_AHEAD=v, TOFJAX_PROGRAM_STORE="0", TOFJAX_COMPILATION_CACHE="0",
                       JAX_PLATFORMS="cpu")
            env.pop("XLA_FLAGS", None)
            load = os.getloadavg()[0]
            out = subprocess.run([sys.executable, __file__, "--worker"], env=env, capture_output=True, text=True, check=False)
            if out.returncode != 0:
                print(out.stderr[-3000:], file=sys.stderr)
                raise SystemExit(f"worker (ahead={v}) failed with exit code {out.returncode}")
            rec = json.loads(out.stdout.strip().splitlines()[-1])
            rec["load_1min"] = load
            runs[v].append(rec)
            names = sorted(n for n, _ in rec["compiles"] if n in ("jit(fit_problem)", "jit(_covariance)"))
            print(f"round {r + 1} ahead={v}: cold {rec['cold_s']:.2f} s (CPU {rec['cold_cpu_s']:.2f} s), "
                  f"{len(rec['compiles'])} compiles {names}, n1 {rec['n1']:.12f}, load {load:.1f}", flush=True)
    med = {v: statistics.median(x["cold_s"] for x in runs[v]) for v in runs}
    ratios = [o["cold_s"] / n["cold_s"] for o, n in zip(runs["0"], runs["1"])]
    sys.path.insert(0, str(ROOT))
    import jax

    from tofjax.outputs import atomic_write_text

    result = {
        "what": "cold Calibrator.fit (compile + first fit) with TOFJAX_COMPILE_AHEAD=0 and 1, fresh process each, "
                "the CLI's CPU compiler (elemental emitters)",
        "simulated": True, "scene": "default", "frames": 100, "seed": 1000,
        "machine": f"{platform.node()} {platform.machine()}, {os.cpu_count()} cores; jax {jax.__version__}",
        "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()), "rounds": a.rounds,
        "median_cold_s": {"without": med["0"], "with": med["1"]},
        "ratio_without_over_with_per_round": ratios, "ratio_median": statistics.median(ratios),
        "same_n1": all(o["n1"] == n["n1"] for o, n in zip(runs["0"], runs["1"])),
        "runs": {"without": runs["0"], "with": runs["1"]},
    }
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(Path(a.out), json.dumps(result, indent=1) + "\n")
    print(f"cold calibration: {med['0']:.2f} s without, {med['1']:.2f} s with compile-ahead "
          f"(median paired ratio {result['ratio_median']:.2f}); same n1: {result['same_n1']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
