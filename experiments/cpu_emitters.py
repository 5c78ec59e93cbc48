"""XLA's two CPU code generators side by side: the fusion emitters (XLA's default) against the
elemental emitters (``--xla_cpu_use_fusion_emitters=false``, what
:func:`tofjax.compile_cache.use_fast_cpu_compiler` selects for the CLI and the tests).

Each measurement runs in a fresh Python process (``--worker``) with an explicit ``$XLA_FLAGS``,
cold (``TOFJAX_PROGRAM_STORE=0 TOFJAX_COMPILATION_CACHE=0``, no JAX persistent cache), the two
emitters alternating ``--rounds`` times (first one, then the other, the order flipped every
round), so a shared machine's swings fall on both alike. Per process, float64, the default
scene, a **simulated** 100-frame baseline (seed 1000):

* ``calibration_cold_s``: ``Calibrator(scene).fit(capture)``, the first in the process (its
  compilations plus one fit's run: what "compile <= 10 s" of issue 13 is about);
* ``calibration_warm_s``: the median of ``--warm`` more fits of the same capture;
* ``model_compile_s`` / ``model_warm_s``: ``jit(value_and_grad(sum(model(p)^2)))`` compiled
  (trace, lower, compile) and its median warm call;
* ``posterior_gradient_s``: one value and gradient of the calibration's posterior log-density
  (a NUTS leapfrog step; :func:`tofjax.fit.posterior.log_density`), median of 20 warm calls;
* ``mc_events_per_s``: the Monte Carlo's packet-events per second (default scene, next-event
  estimation, float32, 10,000 photons per sensor; median of three runs after one to compile).
  Its transport program asks for the fusion emitters itself (``tofjax/mc/transport.py``,
  ``_compiler_options``: 2.2x faster there), so from that change on both columns run it alike;
  ``docs/results/cpu_emitters_before_mc_override.json`` has the run before it (5.4e6 against
  2.5e6 packet-events/s);
* ``n1``, ``mu_t``, ``steps``: the fit's answer, to show the emitters agree.

Wall seconds, medians over the rounds, and the per-round ratios (fusion / elemental).

    python experiments/cpu_emitters.py --rounds 3 --out docs/results/cpu_emitters.json
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
VARIANTS = {"fusion": "--xla_cpu_use_fusion_emitters=true", "elemental": "--xla_cpu_use_fusion_emitters=false"}
MEASURES = ("calibration_cold_s", "calibration_warm_s", "model_compile_s", "model_warm_s", "posterior_gradient_s",
            "mc_events_per_s")


def calibration_and_model_timings(warm: int):
    """In this process (float64, the default scene, the simulated 100-frame baseline of seed 1000): the first
    calibration's seconds, ``warm`` more fits' seconds, and the model's value-and-gradient compile and median call
    (the part of the worker ``experiments/cpu_opt_level.py`` shares). Returns ``(scene, capture, calibrator, result,
    cold_s, warm_s list, model_compile_s, model_warm_s)``."""
    sys.path.insert(0, str(ROOT))
    import jax
    import jax.numpy as jnp

    from tofjax import build_model, enable_x64
    from tofjax.fit import Calibrator
    from tofjax.model import Params
    from tofjax.scene import default_scene
    from tofjax.simulate import simulate
    from tofjax.timing import median_seconds

    enable_x64()
    scene = default_scene()
    cap = simulate(scene, 100, seed=1000)
    cal = Calibrator(scene)
    t = time.perf_counter()
    res = cal.fit(cap)
    cold = time.perf_counter() - t
    times = []
    for _ in range(warm):
        t = time.perf_counter()
        cal.fit(cap)
        times.append(time.perf_counter() - t)
    model = build_model(scene)
    p = Params.from_scene(scene, jnp.float64)

    def loss(q):
        return jnp.sum(model(q) ** 2)

    f = jax.jit(jax.value_and_grad(loss))
    t = time.perf_counter()
    compiled = f.lower(p).compile()
    m_compile = time.perf_counter() - t
    m_warm = median_seconds(compiled, p, 20)  # one call first, then the median of 20
    return scene, cap, cal, res, cold, times, m_compile, m_warm


def worker(warm: int) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np

    scene, cap, cal, res, cold, times, m_compile, m_warm = calibration_and_model_timings(warm)
    from tofjax.fit.posterior import log_density
    from tofjax.timing import median_seconds

    ld = log_density(cal, cap, res)
    vg = jax.jit(jax.value_and_grad(ld.fn))
    f0 = jnp.asarray(ld.flat0)
    g_warm = median_seconds(vg, f0, 20)
    from tofjax.mc import MCOptions, run_mc

    run_mc(scene, MCOptions(photons=10_000))  # compile; then the median rate of three runs
    mc_rate = statistics.median(run_mc(scene, MCOptions(photons=10_000, seed=s)).events_per_second for s in range(3))
    return {
        "mc_events_per_s": mc_rate, "posterior_gradient_s": g_warm,
        "calibration_cold_s": cold, "calibration_warm_s": statistics.median(times),
        "model_compile_s": m_compile, "model_warm_s": m_warm,
        "n1": float(res.params.n1), "mu_t": float(np.asarray(res.params.mu_s_per_m) + np.asarray(res.params.mu_a_per_m)), "steps": int(res.steps),
        "result": res.result, "xla_flags": os.environ.get("XLA_FLAGS", ""),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", help="JSON file to write")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--warm", type=int, default=10, help="warm fits per process (median)")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        print(json.dumps(worker(a.warm)))
        return 0
    if not a.out:
        ap.error("--out is required")
    if a.rounds < 1 or a.warm < 1:
        ap.error("--rounds and --warm must be >= 1")
    runs = {v: [] for v in VARIANTS}
    for r in range(a.rounds):
        order = list(VARIANTS) if r % 2 == 0 else list(VARIANTS)[::-1]
        for v in order:
            env = dict(os.environ, XLA_FLAGS=VARIANTS[v], TOFJAX_PROGRAM_STORE="0", TOFJAX_COMPILATION_CACHE="0",
                       JAX_PLATFORMS="cpu", TOFJAX_CPU_EMITTER="fusion")
            load = os.getloadavg()[0]
            out = subprocess.run([sys.executable, __file__, "--worker", "--warm", str(a.warm)], env=env, capture_output=True,
                                 text=True, check=False)
            if out.returncode != 0:
                print(out.stderr[-3000:], file=sys.stderr)
                raise SystemExit(f"worker ({v}) failed with exit code {out.returncode}")
            rec = json.loads(out.stdout.strip().splitlines()[-1])
            rec["load_1min"] = load
            runs[v].append(rec)
            print(f"round {r + 1} {v:9s} cold {rec['calibration_cold_s']:6.2f} s  warm {rec['calibration_warm_s'] * 1e3:6.0f} ms  "
                  f"model compile {rec['model_compile_s']:5.2f} s  warm {rec['model_warm_s'] * 1e3:6.2f} ms  "
                  f"posterior grad {rec['posterior_gradient_s'] * 1e3:5.2f} ms  MC {rec['mc_events_per_s']:.3g} ev/s  n1 {rec['n1']:.9f} ({rec['steps']} steps)  load {load:.1f}", flush=True)
    med = {v: {m: statistics.median(x[m] for x in runs[v]) for m in MEASURES} for v in VARIANTS}
    ratios = {m: [f[m] / e[m] for f, e in zip(runs["fusion"], runs["elemental"])] for m in MEASURES}
    n1_diff = max(abs(f["n1"] - e["n1"]) for f, e in zip(runs["fusion"], runs["elemental"]))
    mu_rel = max(abs(f["mu_t"] - e["mu_t"]) / e["mu_t"] for f, e in zip(runs["fusion"], runs["elemental"]))
    sys.path.insert(0, str(ROOT))
    import jax

    from tofjax.outputs import atomic_write_text

    result = {
        "what": "XLA CPU fusion emitters (default) vs elemental emitters (--xla_cpu_use_fusion_emitters=false): "
                "cold calibration (compile + first fit), warm fit, model value-and-grad compile and call; fresh process each",
        "simulated": True, "scene": "default", "frames": 100, "seed": 1000,
        "machine": f"{platform.node()} {platform.machine()}, {os.cpu_count()} cores; jax {jax.__version__}",
        "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()), "rounds": a.rounds, "warm_fits": a.warm,
        "median": med, "ratio_fusion_over_elemental_per_round": ratios,
        "ratio_median": {m: statistics.median(v) for m, v in ratios.items()},
        "n1_max_abs_difference": n1_diff, "mu_t_max_rel_difference": mu_rel, "runs": runs,
    }
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(Path(a.out), json.dumps(result, indent=1) + "\n")
    for m in MEASURES:
        print(f"{m:20s} fusion {med['fusion'][m]:.4g}  elemental {med['elemental'][m]:.4g}  ratio {result['ratio_median'][m]:.2f}")
    print(f"n1 differs by at most {n1_diff:.2e}, mu_s + mu_a by {mu_rel:.2e} (relative)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
