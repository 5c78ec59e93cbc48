"""What the model costs to compile, before and after a change to the near field's correction
(``tofjax/model/components.py``), side by side; and whether the model's values moved.

Each tree (``--base``: a checkout of the commit before, e.g. ``git archive 7dc992e | tar -x -C
/tmp/base``; and this worktree) runs in its own fresh Python processes (``--worker``), one per
measurement, alternating base / this tree ``--rounds`` times (a loaded, shared machine's swings
fall on both alike), with ``TOFJAX_PROGRAM_STORE=0 TOFJAX_COMPILATION_CACHE=0`` and no JAX
persistent cache (cold). Measured, float64, the OptoSkin scene (simulated, no data):

* ``correction``: jit of value-and-gradient (in near field and shape) of the node integrals
  ``node_falloff_after_emission`` on the scene's node grid: trace + lower + compile;
* ``model``: jit of value-and-gradient of ``sum(model(p)^2)`` (``ForwardModel.__call__``),
  trace + lower + compile;
* ``calibration``: ``Calibrator(scene).fit(capture)`` on a simulated 100-frame capture, cold
  (the first fit in the process: its compilations plus one fit's run time).

Wall seconds and this process's CPU seconds (``time.process_time()``: XLA compiles on a thread
pool, so CPU can exceed wall). Medians over the rounds. The accuracy check evaluates the model in
both trees at the scene's parameters with ``near_field_shape`` in (2, 3) and at extremes (shape 1,
1.2, 65, 1000; near field 0.5 mm and 20 mm; mu_s, mu_a 0 and 1e3 /m; n1 1.0001 and 3.5) and
reports the largest relative difference (of counts above 1e-12 of each curve's peak).

    python experiments/compile_cost.py --base /tmp/base --out docs/results/compile_cost.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PARTS = ("correction", "model", "calibration")

#: (name, parameter overrides) for the accuracy check
POINTS = (
    ("default_shape2", {}),
    ("default_shape3", {"near_field_shape": 3.0}),
    ("shape1", {"near_field_shape": 1.0}),
    ("shape1.2", {"near_field_shape": 1.2}),
    ("shape65", {"near_field_shape": 65.0}),
    ("shape1000", {"near_field_shape": 1000.0}),
    ("shape3_near0.5mm", {"near_field_shape": 3.0, "near_field_m": 5e-4}),
    ("shape3_near20mm", {"near_field_shape": 3.0, "near_field_m": 0.02}),
    ("shape1_near20mm", {"near_field_shape": 1.0, "near_field_m": 0.02}),
    ("shape65_near0.5mm", {"near_field_shape": 65.0, "near_field_m": 5e-4}),
    ("shape3_clear_fast", {"near_field_shape": 3.0, "mu_s_per_m": 0.0, "mu_a_per_m": 0.0, "n1": 1.0001}),
    ("shape3_murky_slow", {"near_field_shape": 3.0, "mu_s_per_m": 1e3, "mu_a_per_m": 1e3, "n1": 3.5}),
)


def _patch(variant: str) -> None:
    """Diagnostics (this process only; not models to fit with): ``no_correction``, the node
    correction switched off (what it costs to compile); ``no_fallback``, the band on its window
    only, without the ``lax.cond`` to all edges (wrong for a near field deeper than the window)."""
    import jax.numpy as jnp

    import tofjax.model.components as C

    if variant == "no_correction":
        C.node_shape_correction = lambda lo, hi, d, shape: (jnp.zeros_like(lo),) * 3
    elif variant == "no_fallback":
        points = C._shape_points

        def window_only(e, d, shape, band=True):
            return points(e, d, shape, band if band in (True, False) else (band[0], band[1], True))

        C._shape_points = window_only
    elif variant != "as_is":
        raise SystemExit(f"unknown variant {variant}")


def worker(part: str, out: str, variant: str = "as_is") -> None:
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    _patch(variant)

    from tofjax.model import ModelOptions, Params, build_model
    from tofjax.scene import load_scene

    sc = load_scene("optoskin")
    res = {}
    if part == "accuracy":
        m = build_model(sc, ModelOptions())
        base = Params.from_scene(sc, jnp.float64)
        f = jax.jit(lambda p: m(p))
        arrays = {}
        for name, over in POINTS:
            p = base.replace(**{k: jnp.asarray(v, jnp.float64) for k, v in over.items()})
            arrays[name] = np.asarray(f(p))
        np.savez(out, **arrays)
        return
    if part == "calibration":
        from tofjax.fit.calibrate import Calibrator
        from tofjax.simulate import simulate

        cap = simulate(sc, 100, seed=1000)
        t, c = time.perf_counter(), time.process_time()
        r = Calibrator(sc).fit(cap)
        res = {"wall_s": time.perf_counter() - t, "cpu_s": time.process_time() - c, "steps": int(r.steps)}
    else:
        from near_field_cost import cost_probe

        loss, arg = cost_probe(sc, part == "correction")
        t, c = time.perf_counter(), time.process_time()
        fn = jax.jit(jax.value_and_grad(loss)).lower(arg).compile()
        res = {"wall_s": time.perf_counter() - t, "cpu_s": time.process_time() - c}
        jax.block_until_ready(fn(arg))
    Path(out).write_text(json.dumps(res))


def run_one(tree: Path, part: str, out: Path, variant: str = "as_is") -> None:
    env = dict(os.environ, TOFJAX_PROGRAM_STORE="0", TOFJAX_COMPILATION_CACHE="0", PYTHONPATH=str(tree))
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    subprocess.run([sys.executable, str(Path(__file__).resolve()), "--worker", part, "--variant", variant, "--out", str(out)],
                   env=env, check=True, cwd=str(tree))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", help="a checkout of the tree before the change (required)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--parts", default=",".join(PARTS))
    ap.add_argument("--base-label", default="before")
    ap.add_argument("--out", default="docs/results/compile_cost.json")
    ap.add_argument("--diagnostics", default="no_correction,no_fallback",
                    help="variants of this tree timed alongside (correction and model only; empty: none)")
    ap.add_argument("--worker")
    ap.add_argument("--variant", default="as_is")
    a = ap.parse_args(argv)
    if a.worker:
        worker(a.worker, a.out, a.variant)
        return 0
    if not a.base:
        ap.error("--base: required")
    import numpy as np

    here = Path(__file__).resolve().parents[1]
    trees = {"before": Path(a.base).resolve(), "after": here}
    parts = a.parts.split(",")
    diag = [v for v in a.diagnostics.split(",") if v]
    runs = {t: {p: [] for p in parts} for t in trees}
    diag_runs = {v: {p: [] for p in parts if p != "calibration"} for v in diag}
    loads = [os.getloadavg()[0]]
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(a.rounds):
            for part in parts:
                order = [(t, tree, "as_is") for t, tree in trees.items()]
                order += [(v, here, v) for v in diag if part != "calibration"]
                for t, tree, variant in (order if r % 2 == 0 else order[::-1]):
                    f = Path(tmp) / f"{t}-{part}-{r}.json"
                    run_one(tree, part, f, variant)
                    (runs if t in trees else diag_runs)[t][part].append(json.loads(f.read_text()))
                    print(t, part, r, f.read_text(), flush=True)
            loads.append(os.getloadavg()[0])
        acc = {}
        for t, tree in trees.items():
            run_one(tree, "accuracy", Path(tmp) / f"{t}.npz")
            acc[t] = dict(np.load(Path(tmp) / f"{t}.npz"))
    worst = {}
    for name in acc["before"]:
        b, x = acc["before"][name], acc["after"][name]
        keep = np.abs(b) > 1e-12 * np.abs(b).max(axis=-1, keepdims=True)
        worst[name] = float(np.max(np.abs(x - b)[keep] / np.abs(b)[keep]))
    median = {t: {p: {k: statistics.median(r[k] for r in runs[t][p]) for k in ("wall_s", "cpu_s")} for p in parts} for t in trees}
    ratio = {p: {k: median["after"][p][k] / median["before"][p][k] for k in ("wall_s", "cpu_s")} for p in parts}
    median_diag = {v: {p: {k: statistics.median(r[k] for r in rs) for k in ("wall_s", "cpu_s")} for p, rs in d.items()}
                   for v, d in diag_runs.items()}
    doc = {
        "what": "compile cost (trace + lower + compile) of the near field's node correction alone, of the model's value and gradient, "
                "and one cold calibration (compile + one fit), before and after a change to the correction; float64, OptoSkin scene",
        "data": "simulated scene, no data",
        "machine": f"{platform.node()}: {os.cpu_count()} CPUs, shared with other jobs (load average {loads[0]:.1f} to {max(loads):.1f}); "
                   "timings are medians of fresh processes alternating before/after",
        "before": f"{a.base_label} ({trees['before']})",
        "rounds": a.rounds,
        "median": median,
        "ratio_after_over_before": ratio,
        "runs": runs,
        "diagnostics": {"what": _patch.__doc__.replace("\n    ", " "), "median": median_diag, "runs": diag_runs},
        "accuracy": {"what": "largest relative difference after vs before of the model's counts (above 1e-12 of the peak), "
                             "at the scene's parameters and at extremes", "points": dict(POINTS), "max_rel_diff": worst,
                     "max_over_all": max(worst.values())},
    }
    from tofjax.outputs import atomic_write_text, check_output

    out = check_output(a.out, overwrite=True)
    atomic_write_text(out, json.dumps(doc, indent=1) + "\n")
    print(json.dumps({"median": median, "ratio": ratio, "accuracy_max": doc["accuracy"]["max_over_all"]}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
