"""Where a NUTS gradient's time goes: the posterior's log-density split into the model's
linear parts (the per-unit-gain histograms R and the crosstalk P: the physics) and the
profile (the zone gains, ambient and crosstalk counts solved in closed form, with their log
determinant and the gain prior), each as a value and as a value and gradient, timed
interleaved (repeat after repeat, so a changing load hits them alike), medians.

    python experiments/nuts_gradient_parts.py --out out/nuts_gradient_parts.json

Simulated default 100-frame baseline (seed 1), the benchmark's posterior (NUTS's defaults)."""

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
    ap.add_argument("--out", default="out/nuts_gradient_parts.json")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)
    tofjax.enable_x64()
    from tofjax.compile_cache import enable_compilation_cache
    from tofjax.outputs import atomic_write_text, check_output

    out = Path(a.out)
    check_output(out, overwrite=a.overwrite)
    enable_compilation_cache()
    import jax
    import jax.numpy as jnp

    from tofjax.fit.calibrate import Calibrator, FitConfig
    from tofjax.fit.posterior import _to_fit, log_density
    from tofjax.scene import load_scene
    from tofjax.simulate import simulate

    scene = load_scene("optoskin")
    cap = simulate(scene, 100, seed=1)
    cal = Calibrator(scene, FitConfig())
    fit = cal.fit(cap)
    ld = log_density(cal, cap, fit)
    pr = ld.problem
    base, data, sigma, prior, widths, held, log_gain = ld.args
    _, unravel = jax.flatten_util.ravel_pytree(ld.template)
    x = jnp.asarray(ld.flat0)

    def params_of(flat):
        return pr.unpack({**held, **unravel(_to_fit(flat, ld.idx)[0])}, base)

    def parts(flat):
        R, P, E = pr._linear_parts(params_of(flat))
        return jnp.sum(R) + jnp.sum(P) + (0.0 if E is None else jnp.sum(E))

    R, P, E = pr._linear_parts(params_of(x))

    def profile(R, P):
        _, m, logdet, lin = pr.profile(params_of(x), data, sigma, (R, P, E))
        return jnp.sum(((m - data) / sigma) ** 2) + logdet + jnp.sum(jnp.log(lin["gain"]))

    fns = {
        "log_density_value": (jax.jit(ld.fn), (x,)),
        "log_density_value_and_gradient": (jax.jit(jax.value_and_grad(ld.fn)), (x,)),
        "model_linear_parts_value": (jax.jit(parts), (x,)),
        "model_linear_parts_value_and_gradient": (jax.jit(jax.value_and_grad(parts)), (x,)),
        "profile_value": (jax.jit(profile), (R, P)),
        "profile_value_and_gradient": (jax.jit(jax.value_and_grad(profile, argnums=(0, 1))), (R, P)),
    }
    for f, args in fns.values():
        jax.block_until_ready(f(*args))
    load0 = os.getloadavg()[0]
    rows = {k: [] for k in fns}
    for _ in range(a.repeats):
        for k, (f, args) in fns.items():
            ts = []
            for _ in range(20):
                t = time.perf_counter()
                jax.block_until_ready(f(*args))
                ts.append(time.perf_counter() - t)
            rows[k].append(float(np.median(ts)))
    ms = {k: 1e3 * float(np.median(v)) for k, v in rows.items()}
    res = {
        "study": "cost of the posterior's value and gradient by part (NUTS's leapfrog step)",
        "data": "simulated optoskin baseline, 100 frames (seed 1)",
        "machine": f"{platform.machine()} CPU, {os.cpu_count()} cores shared with other jobs (load average {load0:.1f} "
                   f"at the start, {os.getloadavg()[0]:.1f} at the end); JAX {jax.__version__}",
        "linear": list(pr.linear), "data_shape": list(data.shape),
        "median_ms": ms,
        "gradient_over_value": {k: ms[f"{k}_value_and_gradient"] / ms[f"{k}_value"] for k in ("log_density", "model_linear_parts", "profile")},
        "share_of_log_density_gradient": {k: ms[f"{k}_value_and_gradient"] / ms["log_density_value_and_gradient"]
                                          for k in ("model_linear_parts", "profile")},
    }
    atomic_write_text(out, json.dumps(res, indent=1))
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
