"""The cost of the posterior's log-density gradient by reverse mode (``value_and_grad``, what
NUTS uses) and forward mode (10 ``jvp``s vmapped; ``jacfwd``) against one value, each as
``--n`` evaluations in one compiled scan (no dispatch between them, as inside NUTS), repeated
interleaved; medians. Also checks that the two modes' gradients agree. Simulated default
100-frame baseline (seed 1), the fit's log-density (:func:`tofjax.fit.posterior.log_density`).

    python experiments/nuts_gradient_modes.py --out docs/results/nuts_gradient_modes.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

import tofjax


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/nuts_gradient_modes.json")
    ap.add_argument("--n", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)
    from tofjax.outputs import atomic_write_text, check_output

    out = Path(a.out)
    check_output(out, overwrite=a.overwrite)
    tofjax.enable_x64()
    from tofjax.compile_cache import enable_compilation_cache

    enable_compilation_cache()
    import jax
    import jax.numpy as jnp

    from tofjax.fit.calibrate import Calibrator, FitConfig
    from tofjax.fit.posterior import GAIN_PRIOR, HELD, NUISANCE_WIDTH, log_density
    from tofjax.scene import load_scene
    from tofjax.simulate import simulate

    scene = load_scene("optoskin")
    cap = simulate(scene, 100, seed=1)
    cal = Calibrator(scene, FitConfig())
    ld = log_density(cal, cap, cal.fit(cap), NUISANCE_WIDTH, HELD, GAIN_PRIOR)
    P = ld.flat0.size
    f = ld.fn

    def fwd(x):
        return jax.vmap(lambda t: jax.jvp(f, (x,), (t,)), out_axes=(None, 0))(jnp.eye(P))

    modes = {"value": lambda x: (f(x), jnp.zeros_like(x)), "reverse": jax.value_and_grad(f), "forward_vmapped_jvp": fwd,
             "forward_jacfwd": lambda x: (f(x), jax.jacfwd(f)(x))}

    def scanned(g):
        @jax.jit
        def run(x0):
            def body(c, _):
                v, gr = g(c)
                return c + 1e-12 * gr + 1e-12, v
            return jax.lax.scan(body, x0, None, length=a.n)[1]
        return run

    x0 = jnp.asarray(ld.flat0)
    progs, compile_s = {}, {}
    for k, g in modes.items():
        t = time.perf_counter()
        progs[k] = scanned(g)
        jax.block_until_ready(progs[k](x0))
        compile_s[k] = time.perf_counter() - t
    times = {k: [] for k in progs}
    for _ in range(a.repeats):
        for k, p in progs.items():
            t = time.perf_counter()
            jax.block_until_ready(p(x0))
            times[k].append((time.perf_counter() - t) / a.n)
    med = {k: float(np.median(v)) for k, v in times.items()}
    g_rev, g_fwd = jax.grad(f)(x0), fwd(x0)[1]
    res = {
        "study": "cost of the posterior log-density's gradient: reverse against forward mode",
        "data": "simulated optoskin baseline, 100 frames (seed 1); the fit's posterior log-density",
        "machine": f"{platform.machine()} CPU, {os.cpu_count()} cores shared with other jobs (load average "
                   f"{os.getloadavg()[0]:.1f} at the end); JAX {jax.__version__}",
        "parameters": P, "evaluations_per_timing": a.n, "repeats": a.repeats,
        "seconds_per_evaluation": med, "relative_to_value": {k: v / med["value"] for k, v in med.items()},
        "compile_and_first_run_s": compile_s,
        "gradients_max_relative_difference": float(jnp.max(jnp.abs(g_rev - g_fwd)) / jnp.max(jnp.abs(g_rev))),
    }
    atomic_write_text(out, json.dumps(res, indent=1))
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
