"""What the near field's shape costs one model evaluation (issue 13 / issue 16 trade-off).

Times the default model's value and value-and-gradient (float64, the OptoSkin scene at its
parameters with ``near_field_shape`` 3) as it is and with the shape's terms switched off in this
process only (the node integrals' correction ``node_shape_correction``, and/or the per-ray
``falloff`` at p = 2), or replaced (``main_quadrature``: main's correction at 4533487, 6-point
Gauss-Legendre in ``u = atan(r/d)`` on both halves of every node; ``all_edges``: today's
correction without its window, the quadrature on every edge). All variants are compiled in one
process, then timed in turn, ``--rounds`` rounds of ``--calls`` calls each, medians of the
per-round means, wall and this process's CPU time (``*_cpu_ms``: on a loaded machine the less
disturbed of the two, with XLA's CPU work on one thread, ``--one-thread``, the default): the swings
fall on all variants alike. The variants are
diagnostics, not models anyone should fit with. Simulated scene, no data. Writes JSON.

    python experiments/near_field_cost.py --out docs/results/near_field_cost_cheap.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics

import numpy as np

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


def _patched(variant: str):
    """Patch the model's near-field pieces for ``variant`` (this process only); returns an undo."""
    import jax.numpy as jnp

    import tofjax.model.components as C

    saved = (C.falloff, C.node_shape_correction)
    if variant in ("no_ray_shape", "no_shape"):
        f0 = C.falloff
        C.falloff = lambda r, d, shape=2.0: f0(r, d, 2.0)
    if variant in ("no_node_correction", "no_shape"):
        C.node_shape_correction = lambda lo, hi, d, shape: (jnp.zeros_like(lo),) * 3
    if variant == "main_quadrature":
        C.node_shape_correction = _main_shape_correction
    if variant == "all_edges":
        C.node_shape_correction = C.shape_correction

    def undo():
        C.falloff, C.node_shape_correction = saved

    return undo


def cost_probe(scene, part: bool):
    """``(loss, argument)``: a scalar of the whole model's counts (``sum(model(p)^2)`` at the scene's parameters
    with the near field's shape 3), or, with ``part``, of the node integrals alone in (near field, shape) on the
    scene's node grid (mass, offset and variance summed). What this script and ``compile_cost.py`` time."""
    import jax.numpy as jnp

    from tofjax.model import ModelOptions, Params, build_model

    m = build_model(scene, ModelOptions())
    p = Params.from_scene(scene, jnp.float64).replace(near_field_shape=3.0)
    if not part:
        return (lambda q: jnp.sum(m(q) ** 2)), p
    import tofjax.model.components as C

    nodes = C.make_nodes(p, m.bin_width_s, m.n_bins, m.options.quadrature)

    def loss(q):
        mass, spread = C.node_falloff_after_emission(nodes, q[0], q[1])
        return jnp.sum(mass) + jnp.sum(spread.offset) + jnp.sum(spread.variance)

    return loss, jnp.asarray([float(p.near_field_m), 3.0])


def interleaved(variants, rounds: int, calls: int, part: bool = False) -> dict:
    """Compile every variant in this process (each traced under its patch), then time them in
    turn, ``calls`` calls per variant per round, ``rounds`` rounds: a loaded machine's swings fall
    on all variants alike. Per-round mean times; medians over the rounds."""
    import time

    import jax

    jax.config.update("jax_enable_x64", True)
    from tofjax.scene import load_scene

    loss, p = cost_probe(load_scene("optoskin"), part)
    fns, compile_s = {}, {}
    for v in variants:
        jax.clear_caches()  # the model's own jit (eqx.filter_jit) would hand back the last variant's trace
        undo = _patched(v)
        try:
            for name, f in (("value", loss), ("value_and_grad", jax.value_and_grad(loss))):
                t = time.perf_counter()
                fns[v, name] = jax.jit(f).lower(p).compile()
                compile_s[f"{v}/{name}"] = time.perf_counter() - t
                jax.block_until_ready(fns[v, name](p))
        finally:
            undo()
    runs = {v: [] for v in variants}
    for _ in range(rounds):
        for v in variants:
            row = {}
            for name in ("value", "value_and_grad"):
                fn = fns[v, name]
                t, c = time.perf_counter(), time.process_time()
                for _ in range(calls):
                    jax.block_until_ready(fn(p))
                row[name + "_ms"] = 1e3 * (time.perf_counter() - t) / calls
                row[name + "_cpu_ms"] = 1e3 * (time.process_time() - c) / calls
            runs[v].append(row)
    return {"runs": runs, "compile_s": compile_s}


FIT_VARIANTS = ("as_is", "main_quadrature")


def fit_worker(variant: str, captures: int, repeats: int) -> dict:
    """``Calibrator.fit`` on ``captures`` simulated 100-frame baselines with ``variant``'s
    correction: the end points and the warm fit's wall and CPU time (after a first, compiling fit)."""
    import time

    import jax

    jax.config.update("jax_enable_x64", True)
    _patched(variant)
    from tofjax.fit.calibrate import Calibrator
    from tofjax.scene import load_scene
    from tofjax.simulate import simulate

    scene = load_scene("optoskin")
    cal = Calibrator(scene)
    caps = [simulate(scene, 100, seed=1000 + i) for i in range(captures)]
    t = time.perf_counter()
    cal.fit(caps[0])
    out = {"first_fit_s": time.perf_counter() - t, "fits": [], "wall_s": [], "cpu_s": []}
    for r in range(repeats):
        for i, c in enumerate(caps):
            t, cpu = time.perf_counter(), time.process_time()
            res = cal.fit(c)
            out["wall_s"].append(time.perf_counter() - t)
            out["cpu_s"].append(time.process_time() - cpu)
            if r == 0:
                v, e = res.values, res.stderr
                pick = lambda x: {k: float(np.asarray(x[k]).ravel()[0]) for k in ("n1", "mu_s_per_m", "mu_a_per_m", "near_field_shape", "near_field_m") if k in x}  # noqa: E731
                out["fits"].append({"values": pick(v), "stderr": pick(e), "reduced_chi2": float(res.reduced_chi2), "steps": int(res.steps)})
    return out


def fit_compare(captures: int, repeats: int, out_path: str, note: str) -> int:
    """Each of :data:`FIT_VARIANTS` in its own process (a compiled fit is cached by its function,
    not by the patched model), at the same time (the same load for both)."""
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ, TOFJAX_PROGRAM_STORE="0", TOFJAX_COMPILATION_CACHE="0",
               PYTHONPATH=os.pathsep.join(filter(None, (str(root), os.environ.get("PYTHONPATH")))))
    loads = [os.getloadavg()[0]]
    with tempfile.TemporaryDirectory() as tmp:
        procs = {v: subprocess.Popen([sys.executable, __file__, "--fit-worker", v, "--captures", str(captures), "--repeats", str(repeats),
                                      "--out", str(Path(tmp) / f"{v}.json")], env=env) for v in FIT_VARIANTS}
        for p in procs.values():
            if p.wait() != 0:
                raise SystemExit("a fit worker failed")
        runs = {v: json.loads((Path(tmp) / f"{v}.json").read_text()) for v in FIT_VARIANTS}
    loads.append(os.getloadavg()[0])
    a, b = runs["as_is"], runs["main_quadrature"]
    diffs = []
    for fa, fb in zip(a["fits"], b["fits"]):
        d = {k: {"as_is": fa["values"][k], "main_quadrature": fb["values"][k], "difference_in_stderr": (fa["values"][k] - fb["values"][k]) / fb["stderr"][k]}
             for k in fa["values"] if fb["stderr"].get(k)}
        mt = [f["values"]["mu_s_per_m"] + f["values"]["mu_a_per_m"] for f in (fa, fb)]
        d["mu_t_per_m"] = {"as_is": mt[0], "main_quadrature": mt[1], "relative_difference": mt[0] / mt[1] - 1.0}
        d["reduced_chi2"] = {"as_is": fa["reduced_chi2"], "main_quadrature": fb["reduced_chi2"]}
        diffs.append(d)
    med = {v: {"wall_s": statistics.median(r["wall_s"]), "cpu_s": statistics.median(r["cpu_s"])} for v, r in runs.items()}
    out = {"what": "Calibrator.fit on simulated 100-frame OptoSkin baselines (seeds 1000..): the near field's correction as it is against main's",
           "data": "simulated", "comparison": diffs, "warm_fit_median": med,
           "ratio_as_is_over_main": {k: med["as_is"][k] / med["main_quadrature"][k] for k in ("wall_s", "cpu_s")},
           "runs": runs, "note": note,
           "machine": {"description": "x86_64 CPU VM, 2 cores shared with other jobs (loaded: see load_average_1min); the two variants ran at the same time",
                       "platform": platform.platform(), "cpus": os.cpu_count(), "load_average_1min": loads}}
    from tofjax.outputs import atomic_write_text

    atomic_write_text(out_path, json.dumps(out, indent=1) + "\n")
    print(json.dumps(out["ratio_as_is_over_main"]), json.dumps(diffs, indent=1))
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="JSON file to write")
    ap.add_argument("--rounds", type=int, default=15)
    ap.add_argument("--calls", type=int, default=20)
    ap.add_argument("--note", default="")
    ap.add_argument("--one-thread", action=argparse.BooleanOptionalAction, default=True,
                    help="XLA's CPU work on one thread (set before jax starts)")
    ap.add_argument("--variants", nargs="+", choices=VARIANTS, help="a subset (no_node_correction is always added)")
    ap.add_argument("--part", action="store_true", help="time the node integrals (node_falloff_after_emission) alone")
    ap.add_argument("--fit", action="store_true", help="instead: Calibrator.fit end points and warm time, as_is against main_quadrature")
    ap.add_argument("--captures", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--fit-worker", choices=FIT_VARIANTS, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.fit_worker:
        from tofjax.outputs import atomic_write_text

        atomic_write_text(a.out, json.dumps(fit_worker(a.fit_worker, a.captures, a.repeats)))
        return 0
    if a.fit:
        return fit_compare(a.captures, a.repeats, a.out, a.note)
    if a.one_thread:
        os.environ["XLA_FLAGS"] = " ".join(filter(None, (os.environ.get("XLA_FLAGS"), "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")))
    loads = [os.getloadavg()[0]]
    variants = tuple(a.variants or (("as_is", "main_quadrature", "all_edges", "no_node_correction") if a.part else VARIANTS))
    if "no_node_correction" not in variants:
        variants += ("no_node_correction",)
    res = interleaved(variants, a.rounds, a.calls, a.part)
    loads.append(os.getloadavg()[0])
    runs = res["runs"]
    med = {v: {k: statistics.median(x[k] for x in rs) for k in rs[0]} for v, rs in runs.items()}
    low = {v: {k: min(x[k] for x in rs) for k in rs[0]} for v, rs in runs.items()}
    base = "no_node_correction"
    out = {"part": "node_falloff_after_emission alone (value: sum of mass, offset, variance; gradient in near field and shape)" if a.part else "the whole model",
           "min_ms": low, "ratio_of_min_over_no_node_correction": {v: {k: low[v][k] / low[base][k] for k in low[v]} for v in variants},
           "what": "cost of one default-model evaluation (OptoSkin, float64, near_field_shape 3) with the near field's shape terms as they are, as on main, or off",
           "data": "simulated scene, no data", "variants": list(variants),
           "method": f"one process, all variants compiled, then {a.rounds} rounds of {a.calls} calls per variant in turn; medians of the per-round means (wall, and process CPU time)",
           "xla_flags": os.environ.get("XLA_FLAGS", ""),
           "median_ms": med,
           "ratio_over_no_node_correction": {v: {k: med[v][k] / med[base][k] for k in med[v]} for v in variants},
           "compile_s": res["compile_s"], "runs": runs, "note": a.note,
           "machine": {"description": "x86_64 CPU VM, 2 cores shared with other jobs (loaded: see load_average_1min)",
                       "platform": platform.platform(), "cpus": os.cpu_count(), "load_average_1min": loads}}
    from tofjax.outputs import atomic_write_text

    atomic_write_text(a.out, json.dumps(out, indent=1) + "\n")
    print(json.dumps(out["ratio_over_no_node_correction"]), json.dumps(out["ratio_of_min_over_no_node_correction"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
