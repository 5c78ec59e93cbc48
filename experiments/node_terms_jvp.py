"""The node terms' derivative as a matrix product (``ForwardModel._node_terms``, ``linear_masses(...,
node_jvp=True)``) against the direct derivative, in one process, interleaved: the masses' forward-mode
Jacobian by four scalars (n1, mu_s, the near field, the emission time) and their value and gradient in
reverse mode (of the sum of squares), medians of ``--calls`` calls per round. Also the largest relative
difference of the two Jacobians. The default scene, float64, the CLI's XLA flags; no data (a model
evaluation at the scene's parameters).

    python experiments/node_terms_jvp.py --out docs/results/node_terms_jvp_modes.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="JSON file to write")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--calls", type=int, default=100)
    a = ap.parse_args(argv)
    if a.rounds < 1 or a.calls < 1:
        ap.error("--rounds and --calls must be >= 1")
    sys.path.insert(0, str(ROOT))
    from tofjax.compile_cache import use_fast_cpu_compiler

    use_fast_cpu_compiler()
    import jax
    import jax.numpy as jnp
    import numpy as np

    from tofjax import build_model, enable_x64
    from tofjax.model import Params
    from tofjax.scene import default_scene
    from tofjax.timing import median_seconds

    enable_x64()
    scene = default_scene()
    model = build_model(scene)
    p = Params.from_scene(scene, jnp.float64)
    x = jnp.asarray([float(p.n1), float(p.mu_s_per_m), float(p.near_field_m), float(p.emission_time_s)])

    def masses(x, node_jvp):
        q = p.replace(n1=x[0], mu_s_per_m=x[1], near_field_m=x[2], emission_time_s=x[3])
        return model.linear_masses(q, node_jvp=node_jvp)[0]

    modes = (False, True)
    rev = {m: jax.jit(jax.value_and_grad(lambda x, m=m: jnp.sum(masses(x, m) ** 2))).lower(x).compile() for m in modes}
    fwd = {m: jax.jit(jax.jacfwd(lambda x, m=m: masses(x, m))).lower(x).compile() for m in modes}
    j0, j1 = (np.asarray(fwd[m](x)) for m in modes)
    scale = np.max(np.abs(j0), axis=tuple(range(j0.ndim - 1)), keepdims=True)
    times = {f"{kind}_{'matrix_product' if m else 'direct'}": [] for kind in ("reverse", "jacfwd4") for m in modes}
    for r in range(a.rounds):
        for m in modes:
            name = "matrix_product" if m else "direct"
            times[f"reverse_{name}"].append(median_seconds(rev[m], x, a.calls))
            times[f"jacfwd4_{name}"].append(median_seconds(fwd[m], x, a.calls))
        print(f"round {r + 1}: " + ", ".join(f"{k} {v[-1] * 1e3:.3f} ms" for k, v in times.items()), flush=True)
    med = {k: statistics.median(v) for k, v in times.items()}
    out = {
        "what": "the masses' derivative: direct against the node terms as a matrix product (node_jvp), interleaved in one process",
        "simulated": "no data: model evaluations at the default scene's parameters",
        "machine": f"{platform.node() or 'vm'} {platform.machine()}, {os.cpu_count()} cores; jax {jax.__version__}",
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
        "rounds": a.rounds, "calls_per_round": a.calls,
        "seconds": times, "median_s": med,
        "ratio_matrix_product_over_direct": {k: med[f"{k}_matrix_product"] / med[f"{k}_direct"] for k in ("reverse", "jacfwd4")},
        "jacobian_max_relative_difference": float(np.max(np.abs(j1 - j0) / np.where(scale > 0, scale, 1.0))),
    }
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out["ratio_matrix_product_over_direct"]), "Jacobians differ by", out["jacobian_max_relative_difference"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
