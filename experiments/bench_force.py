"""Benchmark: one warm force prediction (features in, newtons out) of seed 001's derivative-enhanced
MLP plus the residual forest, as packed complete trees (issue 17: <= 100 us).

For both feature layouts (seed 001's counts window, 4 beams x 5 bins -> 60 raw values; the
inversion's zone-summed window, 5 bins -> 15 raw values + range and ambient), times in one
run, on the same input (a NumPy vector, as a frame arrives):

- ``mlp_us``: normalisation + MLP, one jitted JAX call;
- ``mlp_rf_us``: normalisation + MLP + forest (100 trees, depth 8), one jitted JAX call: what
  ``ForcePredictor`` runs;
- ``forest_jax_us`` / ``forest_numpy_us``: the forest walk alone, jitted JAX and NumPy.

The MLP has random weights and the forest is fitted to random residuals until every tree is 8
levels deep: the packed trees are complete, so every prediction walks exactly 8 levels whatever
the data, and the time does not depend on what was learned. With ``--run RUN`` a trained run's
predictor is timed as well. Medians (and 10th/90th percentiles) of ``--repeats`` warm calls,
the four functions called in turn so that the shared machine's load hits them alike; the
1/5/15-minute load average is recorded.

    python experiments/bench_force.py --out docs/results --overwrite
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import tofjax
from tofjax.force.forest import ForestOptions, fit_forest, forest_predict, forest_predict_numpy, forest_to_arrays
from tofjax.force.models import build_mlp, mlp_spec
from tofjax.force.train import ForcePredictor, load_predictor
from tofjax.outputs import atomic_write_text, check_output

TARGET_US = 100.0


def _stats(fns: dict, args: dict, repeats: int) -> dict:
    """Warm times of several functions, called in turn (round robin), so the machine's load
    changes hit them alike: median, 10th and 90th percentile in us."""
    for k, f in fns.items():
        for _ in range(min(50, repeats) + 1):
            jax.block_until_ready(f(args[k]))
    ts = {k: np.empty(repeats) for k in fns}
    for i in range(repeats):
        for k, f in fns.items():
            x = args[k]
            t = time.perf_counter()
            jax.block_until_ready(f(x))
            ts[k][i] = time.perf_counter() - t
    return {k: {"median": float(np.median(v) * 1e6), "p10": float(np.percentile(v, 10) * 1e6),
                "p90": float(np.percentile(v, 90) * 1e6)} for k, v in ts.items()}


def _layout(name: str, n: int, extra: int, trees: int, depth: int, repeats: int, seed: int, samples: int = 20_000) -> dict:
    rng = np.random.default_rng(seed)
    spec = mlp_spec("mlp", "derivative", n, dropout=0.0, extra=extra)
    mlp = build_mlp(spec, jax.random.key(seed))
    n_in = 3 * n + extra
    x_fit = rng.uniform(size=(samples, n_in)).astype(np.float32)
    rf = fit_forest(x_fit, rng.standard_normal(samples), ForestOptions(trees=trees, max_depth=depth, min_samples_leaf=5, n_jobs=1), seed)
    forest = forest_to_arrays(rf, depth)
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    ex = (f32(np.zeros(extra)), f32(np.ones(extra))) if extra else (None, None)
    pred = ForcePredictor(mlp, forest, f32(np.zeros(n)), f32(np.full(n, 1000.0)), 0.0, 60.0, "derivative", *ex,
                          *((f32(np.zeros(n)), f32(np.full(n, 1000.0))) if extra else (None, None)))
    raw = rng.uniform(0, 1000, n_in).astype(np.float32)
    x_in = np.asarray(pred.inputs(raw))
    full = jax.jit(lambda r: pred(r))
    mlp_only = jax.jit(lambda r: pred.mlp(pred.inputs(r)))
    fj = jax.jit(lambda v: forest_predict(forest, v))
    npf = forest.numpy()
    # The packed forest equals scikit-learn's on this input.
    assert abs(float(fj(x_in)) - float(rf.predict(x_in[None])[0])) < 1e-4
    fns = {"mlp_us": mlp_only, "mlp_rf_us": full, "forest_jax_us": fj,
           "forest_numpy_us": lambda v: forest_predict_numpy(npf, v)}
    args = {"mlp_us": raw, "mlp_rf_us": raw, "forest_jax_us": x_in, "forest_numpy_us": x_in}
    return {"layout": name, "raw_features": n_in, "model_inputs": int(x_in.shape[0]), "trees": trees,
            "depth": forest.depth} | _stats(fns, args, repeats)


def run(out: Path | None, *, repeats: int = 3000, trees: int = 100, depth: int = 8, run_dir: str | None = None,
        overwrite: bool = False, seed: int = 0) -> dict:
    path = None
    if out is not None:
        path = check_output(Path(out) / "bench_force.json", overwrite=overwrite)
    t0 = time.perf_counter()
    res = {
        "what": "one warm force prediction (raw features in, newtons out), microseconds",
        "target_us": TARGET_US,
        "machine": f"{platform.machine()} {platform.system()}, {os.cpu_count()} CPU cores (shared, loaded), "
                   f"JAX {jax.__version__} {jax.default_backend()} backend",
        "tofjax": tofjax.__version__,
        "load_average_1_5_15": list(os.getloadavg()),
        "repeats": repeats,
        "layouts": [
            _layout("seed 001 counts window (4 beams x 5 bins)", 20, 0, trees, depth, repeats, seed),
            _layout("inversion window (5 bins, zones summed) + range, ambient", 5, 2, trees, depth, repeats, seed),
        ],
        "before_us": {"mlp_rf": [150, 186], "source": "docs/force_study.md before issue 17: padded per-tree arrays, depth up to 20"},
    }
    if run_dir:
        pred, header = load_predictor(run_dir)
        n = len(header["scaling"]["lo"]) * 3 + len(header["scaling"].get("extra_lo", []))
        raw = np.random.default_rng(seed).uniform(0, 1000, n).astype(np.float32)
        res["run"] = {"run": str(run_dir)} | _stats({"mlp_rf_us": jax.jit(lambda r: pred(r))}, {"mlp_rf_us": raw}, repeats)
    res["met"] = all(lay["mlp_rf_us"]["median"] <= TARGET_US for lay in res["layouts"])
    res["seconds"] = time.perf_counter() - t0
    if path is not None:
        atomic_write_text(path, json.dumps(res, indent=2) + "\n", overwrite=overwrite)
    return res


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/bench_force", help="folder for bench_force.json")
    ap.add_argument("--overwrite", action="store_true")
    ap.add_argument("--repeats", type=int, default=3000)
    ap.add_argument("--trees", type=int, default=100)
    ap.add_argument("--depth", type=int, default=8)
    ap.add_argument("--run", default=None, help="also time this trained run's predictor")
    a = ap.parse_args(argv)
    res = run(Path(a.out), repeats=a.repeats, trees=a.trees, depth=a.depth, run_dir=a.run, overwrite=a.overwrite)
    for lay in res["layouts"]:
        print(f"{lay['layout']}: MLP {lay['mlp_us']['median']:.0f} us, MLP + forest {lay['mlp_rf_us']['median']:.0f} us "
              f"(p10 {lay['mlp_rf_us']['p10']:.0f}, p90 {lay['mlp_rf_us']['p90']:.0f}) "
              f"(forest alone: JAX {lay['forest_jax_us']['median']:.0f} us, NumPy {lay['forest_numpy_us']['median']:.0f} us)")
    print(f"target {TARGET_US:.0f} us: {'met' if res['met'] else 'NOT met'}; {res['machine']}")
    return res


if __name__ == "__main__":
    main()
