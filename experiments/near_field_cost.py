"""What the near field's shape costs one model evaluation (issue 13 / issue 16 trade-off).

Times the default model's value and value-and-gradient (float64, the OptoSkin scene, 50 calls x 7
rounds, medians) as it is and with the shape's terms switched off in this process only (the node
integrals' correction ``node_shape_correction``, and/or the per-ray ``falloff`` at p = 2), or
replaced (``main_quadrature``: the correction of main at 4533487, 6-point Gauss-Legendre in
``u = atan(r/d)`` on both halves of every node; ``all_edges``: today's correction without the
window, its quadrature on every edge), each variant in its own process, alternating ``--rounds``
times. The variants are diagnostics, not models anyone should fit with. The model is evaluated at
the scene's parameters with ``near_field_shape`` 3 (the correction is computed whatever p is, but a
traced 2 is the case a fit starts from; 3 keeps it honest). Simulated scene, no data. Writes JSON.

    python experiments/near_field_cost.py --out docs/results/near_field_cost.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
from pathlib import Path

VARIANTS = ("as_is", "main_quadrature", "all_edges", "no_node_correction", "no_ray_shape", "no_shape")


def _main_shape_correction(lo, hi, near_field, shape, points=6):
    """main's (4533487) correction, copied for the comparison: Gauss-Legendre in ``u = atan(r/d)``,
    ``points`` per half of each node (split at ``r = d``), graded towards ``u = pi/4``."""
    import jax.numpy as jnp
    import numpy as np

    from tofjax.model.components import _pow_small

    def excess(u):
        s = jnp.tan(jnp.clip(jnp.minimum(u, 0.5 * jnp.pi - u), 0.0, 0.25 * jnp.pi))
        return jnp.expm1(jnp.log1p(s * s) - (2.0 / shape) * jnp.log1p(_pow_small(s, shape)))

    d = near_field
    ulo, uhi = jnp.arctan(lo / d), jnp.arctan(hi / d)
    q = 0.25 * jnp.pi
    x, wts = np.polynomial.legendre.leggauss(points)
    x, wts = jnp.asarray(x, lo.dtype), jnp.asarray(wts, lo.dtype)
    v = 0.5 * (x + 1.0)
    dm = df1 = df2 = 0.0
    for bend, far_end in ((jnp.maximum(jnp.minimum(uhi, q), ulo), ulo), (jnp.minimum(jnp.maximum(ulo, q), uhi), uhi)):
        width = (far_end - bend)[..., None]
        u = bend[..., None] + width * v * v
        g = excess(u) * (wts * v) * jnp.abs(width)
        t = jnp.tan(u)
        dm = dm + jnp.sum(g, -1) / d
        df1 = df1 + jnp.sum(g * t, -1)
        df2 = df2 + d * jnp.sum(g * t * t, -1)
    return dm, df1, df2


def worker(variant: str) -> dict:
    import time

    import jax
    import jax.numpy as jnp
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    import tofjax.model.components as C

    if variant in ("no_ray_shape", "no_shape"):
        f0 = C.falloff
        C.falloff = lambda r, d, shape=2.0: f0(r, d, 2.0)
    if variant in ("no_node_correction", "no_shape"):
        C.node_shape_correction = lambda lo, hi, d, shape: (jnp.zeros_like(lo),) * 3
    if variant == "main_quadrature":
        C.node_shape_correction = _main_shape_correction
    if variant == "all_edges":
        C.node_shape_correction = C.shape_correction
    from tofjax.model import ModelOptions, Params, build_model
    from tofjax.scene import load_scene

    sc = load_scene("optoskin")
    m = build_model(sc, ModelOptions())
    p = Params.from_scene(sc, jnp.float64).replace(near_field_shape=3.0)
    fns = {"value": jax.jit(lambda p: jnp.sum(m(p) ** 2)),
           "value_and_grad": jax.jit(jax.value_and_grad(lambda p: jnp.sum(m(p) ** 2)))}
    out = {}
    for name, fn in fns.items():
        jax.block_until_ready(fn(p))
        ts = []
        for _ in range(7):
            t = time.perf_counter()
            for _ in range(50):
                jax.block_until_ready(fn(p))
            ts.append((time.perf_counter() - t) / 50)
        out[name + "_ms"] = 1e3 * float(np.median(ts))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", help="JSON file to write (required unless --worker)")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--note", default="")
    ap.add_argument("--worker", choices=VARIANTS, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        print(json.dumps(worker(a.worker)))
        return 0
    if not a.out:
        ap.error("--out is required")
    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ, TOFJAX_PROGRAM_STORE="0", PYTHONPATH=os.pathsep.join(filter(None, (str(root), os.environ.get("PYTHONPATH")))))
    runs: dict = {v: [] for v in VARIANTS}
    loads = [os.getloadavg()[0]]
    for _ in range(a.rounds):
        for v in VARIANTS:
            r = subprocess.run([sys.executable, __file__, "--worker", v], env=env, capture_output=True, text=True, check=True)
            runs[v].append(json.loads(r.stdout.strip().splitlines()[-1]))
            print(v, runs[v][-1], flush=True)
        loads.append(os.getloadavg()[0])
    med = {v: {k: statistics.median(x[k] for x in rs) for k in rs[0]} for v, rs in runs.items()}
    out = {"what": "cost of one default-model evaluation (OptoSkin, float64) with and without the near field's shape terms",
           "data": "simulated scene, no data", "variants": list(VARIANTS), "runs": runs, "median_ms": med,
           "ratio_over_no_shape": {v: {k: med[v][k] / med["no_shape"][k] for k in med[v]} for v in VARIANTS},
           "ratio_over_no_node_correction": {v: {k: med[v][k] / med["no_node_correction"][k] for k in med[v]} for v in VARIANTS},
           "note": a.note,
           "machine": {"description": "x86_64 CPU VM, 2 cores shared with other jobs (loaded: see load_average_1min)", "platform": platform.platform(), "cpus": os.cpu_count(), "load_average_1min": loads}}
    from tofjax.outputs import atomic_write_text

    atomic_write_text(a.out, json.dumps(out, indent=1) + "\n")
    print(json.dumps(out["median_ms"]), json.dumps(out["ratio_over_no_shape"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
