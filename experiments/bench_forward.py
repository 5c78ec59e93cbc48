"""Benchmark: forward model speed and accuracy per fidelity setting and dtype.

For the OptoSkin scene (6 sensors x 7 zones x 128 bins) this measures, side by
side in one run:

* compile time (trace + XLA compile of the forward and of value-and-gradient),
* warm forward time and warm value-and-gradient time (medians over repeats of
  a jitted call, Python dispatch included), and the forward time per
  evaluation inside one compiled loop (what a solver or sampler sees),
* relative L2 error against a high-fidelity reference (quadrature 16, 32 rays
  per zone, float64),

for each fidelity setting and dtype, and the cost of each component (the model
with one component left out), to show that a left-out component costs nothing.

Writes ``forward.json`` and ``forward.md`` to ``--out``. Targets (2-core CPU):
forward <= 200 us, value and gradient <= 1 ms, compile <= 5 s.

    python experiments/bench_forward.py --out out/bench [--repeats 200] [--scene touch-six]
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
from tofjax import ModelOptions, Params, build_model, load_scene
from tofjax.timing import median_seconds

TARGETS_US = {"forward": 200.0, "value_and_grad": 1000.0, "compile_s": 5.0}


def timed(f, arg, repeats):
    return median_seconds(f, arg, repeats, warm=False)


def looped(model, params, n=100):
    """A compiled loop of ``n`` model evaluations: what a solver or sampler sees, free of
    Python dispatch (about 30-60 us per call here for a pytree of 18 parameter arrays).
    n1 moves by 1e-12 per step so XLA cannot hoist the model out of the loop."""

    @jax.jit
    def run(p):
        def body(i, acc):
            return acc + jnp.sum(model(p.replace(n1=p.n1 + 1e-12 * i)))

        return jax.lax.fori_loop(0, n, body, jnp.zeros((), p.n1.dtype))

    jax.block_until_ready(run(params))
    return run, params, n


def in_loop(model, params, n=100):
    """Seconds per evaluation inside one compiled loop (median of 20 runs)."""
    run, p, n = looped(model, params, n)
    return timed(run, p, 20) / n


def measure(scene, opts, repeats, reference=None, components=None):
    model = build_model(scene, opts, components)
    params = Params.from_scene(scene, opts.jnp_dtype)
    fwd = jax.jit(lambda p: model(p))
    vg = jax.jit(jax.value_and_grad(lambda p: jnp.sum(model(p) ** 2)))
    t = time.perf_counter()
    y = jax.block_until_ready(fwd(params))
    compile_fwd = time.perf_counter() - t
    t = time.perf_counter()
    jax.block_until_ready(vg(params))
    compile_vg = time.perf_counter() - t
    row = {
        "quadrature": opts.quadrature,
        "angles_per_zone": opts.angles_per_zone,
        "dtype": opts.dtype,
        "components": list(model.components),
        "compile_forward_s": compile_fwd,
        "compile_value_and_grad_s": compile_vg,
        "forward_us": 1e6 * timed(fwd, params, repeats),
        "value_and_grad_us": 1e6 * timed(vg, params, max(repeats // 4, 10)),
        "forward_in_loop_us": 1e6 * in_loop(model, params),
    }
    if reference is not None:
        y = np.asarray(y, np.float64)
        row["rel_l2_error"] = float(np.linalg.norm(y - reference) / np.linalg.norm(reference))
    return row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/bench")
    ap.add_argument("--scene", default="optoskin", help="scene file or built-in name (default optoskin)")
    ap.add_argument("--repeats", type=int, default=200)
    args = ap.parse_args(argv)
    from tofjax.compile_cache import use_fast_cpu_compiler  # noqa: E402
    use_fast_cpu_compiler()  # the CLI's CPU compiler (before JAX's backend starts)
    tofjax.enable_x64()
    scene = load_scene(args.scene)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    ref_opts = ModelOptions(quadrature=16, angles_per_zone=32)
    reference = np.asarray(build_model(scene, ref_opts)(Params.from_scene(scene)))

    settings = [
        ModelOptions(quadrature=q, angles_per_zone=a, dtype=d)
        for d in ("float32", "float64")
        for q, a in ((1, 4), (1, 8), (2, 4), (2, 8), (4, 8), (8, 16))
    ]
    rows = []
    for opts in settings:
        row = measure(scene, opts, args.repeats, reference)
        rows.append(row)
        print(
            f"{opts.dtype} q={opts.quadrature} A={opts.angles_per_zone}: forward {row['forward_us']:7.0f} us "
            f"({row['forward_in_loop_us']:5.0f} in a loop), "
            f"value+grad {row['value_and_grad_us']:7.0f} us, compile {row['compile_forward_s']:.2f} s, "
            f"error {row['rel_l2_error']:.2e}",
            flush=True,
        )

    # What each component costs: the default model with one component left out. The
    # variants are timed in interleaved rounds (medians), so drift on a shared machine
    # hits them all alike.
    default = ModelOptions()
    full = measure(scene, default, args.repeats)
    variants = {"(none)": full["components"]}
    variants.update({c: tuple(x for x in full["components"] if x != c) for c in full["components"]})
    loops = {}
    for name, comps in variants.items():
        model = build_model(scene, default, comps)
        loops[name] = looped(model, Params.from_scene(scene, default.jnp_dtype))
    samples = {name: [] for name in loops}
    for _ in range(15):
        for name, (run, p, n) in loops.items():
            samples[name].append(timed(run, p, 1) / n)
    base = float(np.median(samples["(none)"]))
    full["forward_in_loop_us"] = 1e6 * base
    ablation = []
    for c in full["components"]:
        t = float(np.median(samples[c]))
        ablation.append({"left_out": c, "forward_in_loop_us": 1e6 * t, "ratio_to_full": t / base})
        print(f"without {c:20s}: {1e6 * t:5.0f} us in a loop ({t / base:.2f} x full)")

    result = {
        "benchmark": "forward model",
        "scene": scene.name,
        "shape": list(scene.shape),
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(),
            "jax": jax.__version__,
            "backend": jax.default_backend(),
        },
        "repeats": args.repeats,
        "reference": {"quadrature": 16, "angles_per_zone": 32, "dtype": "float64"},
        "targets": TARGETS_US,
        "settings": rows,
        "default": full,
        "component_ablation": ablation,
    }
    (out / "forward.json").write_text(json.dumps(result, indent=2))
    lines = [
        f"# Forward model benchmark: {scene.name} {tuple(scene.shape)}",
        "",
        f"Machine: {result['machine']['platform']}, {result['machine']['cpu_count']} CPUs, jax {jax.__version__} "
        f"({jax.default_backend()}). Medians of {args.repeats} calls (value and gradient: {max(args.repeats // 4, 10)}).",
        "",
        "| dtype | quadrature | rays/zone | forward (us) | in a loop (us) | value+grad (us) | compile (s) | rel. L2 error |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['dtype']} | {r['quadrature']} | {r['angles_per_zone']} | {r['forward_us']:.0f} | "
            f"{r['forward_in_loop_us']:.0f} | "
            f"{r['value_and_grad_us']:.0f} | {r['compile_forward_s']:.2f} | {r['rel_l2_error']:.1e} |"
        )
    lines += [
        "",
        f"Default model ({full['dtype']}, quadrature {full['quadrature']}): {full['forward_in_loop_us']:.0f} us per "
        "evaluation in a loop. With one component left out:",
        "",
        "| left out | in a loop (us) | x full |",
        "|---|---|---|",
    ]
    lines += [f"| {a['left_out']} | {a['forward_in_loop_us']:.0f} | {a['ratio_to_full']:.2f} |" for a in ablation]
    (out / "forward.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out / 'forward.json'} and {out / 'forward.md'}")


if __name__ == "__main__":
    main()
