"""Where the compile of a calibration goes: the fit program's kernels, with and without its parts.

The warm process's largest cost is loading the compiled fit (one object file per group of
kernels), and the cold process's is compiling it; both grow with the number of kernels (XLA
fusions). This compiles the fit of ``tofjax calibrate`` on a simulated baseline (the default
config: Marquardt's Levenberg-Marquardt, the Laplace pieces on) and variants without the
Laplace pieces (``with_cov=False``), and counts the fusions in the program's entry computation
and in its solver loop, with the compile seconds (one compile each, on a loaded machine: the
counts are the exact figures, the seconds indicative).

    python experiments/first_fit_kernels.py --out docs/results [--frames 20]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import sys
import time
from pathlib import Path


def _count(hlo: str) -> dict[str, int]:
    """Fusions in the entry computation and in all other computations (the loop bodies)."""
    where, out = "other", {"entry": 0, "loops_and_branches": 0, "while_loops": 0}
    for line in hlo.splitlines():
        if line and not line.startswith(" ") and line.endswith("{"):
            where = "entry" if line.startswith("ENTRY") else "other"
        elif " fusion(" in line:
            out["entry" if where == "entry" else "loops_and_branches"] += 1
        if re.search(r"\swhile\(", line):
            out["while_loops"] += 1
    out["fusions"] = out["entry"] + out["loops_and_branches"]
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True)
    p.add_argument("--scene", default="optoskin")
    p.add_argument("--frames", type=int, default=20)
    a = p.parse_args(argv)
    import equinox as eqx
    import jax
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    from tofjax.fit._start import timing_start
    from tofjax.fit.calibrate import FitConfig, _anchor, _data, _fit_positional, base_params, build_problem
    from tofjax.outputs import atomic_write_text
    from tofjax.scene import load_scene
    from tofjax.simulate import simulate

    scene = load_scene(a.scene).without_touches()
    cap = simulate(scene, a.frames, 0)
    config = FitConfig()
    problem = build_problem(scene, config)
    solver, objective = config.make_solver(), config.make_objective()
    dtype = problem.model.geometry.ray_length.dtype
    data, sigma = _data(cap, dtype, config.model_error)
    base = base_params(scene, config, dtype)
    start, found = timing_start(problem, np.asarray(data), cap.n_frames, scene, base)
    anchor = _anchor(start, found, config, dtype)
    rows = {}
    for label, with_cov in (("fit with the Laplace pieces (what calibrate runs)", True), ("fit without them", False)):
        args = (problem, objective, solver, start, data, sigma, base, anchor, config.max_steps, config.loss_tol,
                config.gn_first, with_cov)
        dyn, static = eqx.partition(args, eqx.is_array)  # as tofjax.compile_cache.call_stored does
        leaves, treedef = jax.tree_util.tree_flatten(dyn)

        def flat(*xs, treedef=treedef, static=static):
            return _fit_positional(*eqx.combine(jax.tree_util.tree_unflatten(treedef, xs), static))

        t0 = time.perf_counter()
        lowered = jax.jit(flat).lower(*leaves)
        t1 = time.perf_counter()
        compiled = lowered.compile()
        t2 = time.perf_counter()
        rows[label] = {"trace_and_lower_s": t1 - t0, "compile_s": t2 - t1, **_count(compiled.as_text())}
        print(label, rows[label], flush=True)
    full, bare = rows["fit with the Laplace pieces (what calibrate runs)"], rows["fit without them"]
    report = {
        "what": "kernels (XLA fusions) of the compiled calibration fit, and its compile time",
        "data": "simulated (tofjax simulate)",
        "scene": a.scene,
        "frames": a.frames,
        "solver": config.solver,
        "programs": rows,
        "laplace_share_of_fusions": 1 - bare["fusions"] / full["fusions"],
        "laplace_share_of_compile": 1 - bare["compile_s"] / full["compile_s"],
        "load_average_1min": os.getloadavg()[0],
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "python": sys.version.split()[0],
                    "what": "the shared 2-core CPU VM, loaded by other sessions"},
    }
    out = Path(a.out)
    atomic_write_text(out / "first_fit_kernels.json", json.dumps(report, indent=2))
    print(f"wrote {out / 'first_fit_kernels.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
