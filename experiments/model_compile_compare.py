"""Two checkouts side by side on what the forward model's programs cost to compile and to run: the model
(``jit(model)``) and its value and gradient (``jit(value_and_grad(sum(model(p) ** 0.6)))``), for the default
and the guided optics on the default scene (float64).

Each measurement is a fresh process of one tree's copy of the package (``--base``: a checkout of the commit
before, e.g. ``git archive REV | tar -x -C /tmp/base``; and this worktree), cold (no compilation cache, no
program store), with the XLA flags of ``--flags``: ``cli`` (the elemental CPU emitters the CLI selects, XLA's
default level) or ``tests`` (those plus ``tests/conftest.py``'s level 0, what the default test run compiles
with). The trees alternate, the order rotated every round. Per program: the compile's CPU seconds (all
threads) and wall seconds, the compiled program's instruction count, and the median of ``--calls`` calls.
Medians over rounds, and the per-round ratios this tree / base. Also the largest relative difference between
the two trees' model outputs (the first round's). The data are the scene's own parameters: nothing is fitted.

    python experiments/model_compile_compare.py --base /tmp/base --label "before (REV)" --out docs/results/NAME.json
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
sys.path.insert(0, str(ROOT / "experiments"))

from cpu_opt_level import fresh_record  # noqa: E402  (a fresh process's JSON record, as tree_compare's workers)
ELEMENTAL = "--xla_cpu_use_fusion_emitters=false"
FLAGS = {"cli": ELEMENTAL,
         "tests": f"{ELEMENTAL} --xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"}
OPTICS = ("default", "guided")
PROGRAMS = ("forward", "value_and_grad")


def worker(calls: int, out_file: str, optics=OPTICS) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    from tofjax.model import ModelOptions, Params, build_model
    from tofjax.scene import default_scene

    scene = default_scene()
    p = Params.from_scene(scene)
    rec, outputs = {}, {}
    for o in optics:
        model = build_model(scene, ModelOptions(optics=o))
        progs = {"forward": jax.jit(lambda q, m=model: m(q)),
                 "value_and_grad": jax.jit(jax.value_and_grad(lambda q, m=model: jnp.sum(m(q) ** 0.6)))}
        for name, f in progs.items():
            c0, w0 = time.process_time(), time.perf_counter()
            compiled = f.trace(p).lower().compile()
            cpu, wall = time.process_time() - c0, time.perf_counter() - w0
            y = jax.block_until_ready(compiled(p))
            ts = []
            for _ in range(calls):
                t0 = time.perf_counter()
                jax.block_until_ready(compiled(p))
                ts.append(time.perf_counter() - t0)
            rec[f"{o}/{name}"] = {"compile_cpu_s": cpu, "compile_wall_s": wall, "call_ms": 1e3 * statistics.median(ts),
                                       "instructions": sum(1 for line in compiled.as_text().splitlines() if " = " in line)}
            if name == "forward":
                outputs[o] = np.asarray(y)
    np.savez(out_file, **outputs)
    return rec


def run_worker(tree: Path, flags: str, calls: int, out_file: Path, optics=OPTICS) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_", "XLA_", "TOFJAX_", "PYTHONPATH"))}  # nothing inherited
    env.update(XLA_FLAGS=flags, TOFJAX_PROGRAM_STORE="0", TOFJAX_COMPILATION_CACHE="0", JAX_PLATFORMS="cpu", PYTHONPATH=str(tree))
    code = (f"import sys, json; sys.path.insert(0, {str(ROOT / 'experiments')!r}); import model_compile_compare as m; "
            f"print(json.dumps(m.worker({calls}, {str(out_file)!r}, {tuple(optics)!r})))")
    return fresh_record(["-c", code], env, tree, str(tree), timeout=1800)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--base", required=True, help="a checkout of the tree before the change")
    ap.add_argument("--label", default="before", help="what the base is (written to the JSON)")
    ap.add_argument("--out", required=True, help="JSON file to write")
    ap.add_argument("--flags", choices=sorted(FLAGS), default="tests", help="XLA flags: the test run's or the CLI's")
    ap.add_argument("--optics", default=",".join(OPTICS), help="comma-separated: default, guided")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--calls", type=int, default=200, help="timed calls per program (median)")
    a = ap.parse_args(argv)
    base = Path(a.base)
    if not (base / "tofjax" / "model" / "forward.py").is_file():
        ap.error(f"--base {base}: not a tofjax checkout")
    if a.rounds < 1 or a.calls < 1:
        ap.error("--rounds and --calls must be >= 1")
    optics = tuple(o.strip() for o in a.optics.split(",") if o.strip())
    if not optics or any(o not in OPTICS for o in optics):
        ap.error(f"--optics {a.optics!r}: a comma-separated list of {', '.join(OPTICS)}")
    import numpy as np

    trees = {"before": base, "after": ROOT}
    runs = {k: [] for k in trees}
    tmp = Path(a.out).resolve().with_suffix(".tmp")  # absolute: the workers run in their trees
    tmp.mkdir(parents=True, exist_ok=True)
    for r in range(a.rounds):
        for k in (("before", "after") if r % 2 == 0 else ("after", "before")):
            rec = run_worker(trees[k], FLAGS[a.flags], a.calls, tmp / f"{k}{r}.npz", optics)
            runs[k].append(rec)
            print(f"round {r + 1} {k:6s} " + "  ".join(
                f"{key} compile {v['compile_cpu_s']:.2f} s call {v['call_ms']:.2f} ms" for key, v in rec.items() if key != "load_1min"),
                flush=True)
    keys = [f"{o}/{p}" for o in optics for p in PROGRAMS]
    measures = ("compile_cpu_s", "compile_wall_s", "call_ms", "instructions")
    med = {k: {key: {m: statistics.median(x[key][m] for x in runs[k]) for m in measures} for key in keys} for k in trees}
    ratio = {key: {m: statistics.median(x[key][m] / y[key][m] for x, y in zip(runs["after"], runs["before"])) for m in measures}
             for key in keys}
    diff = {}
    b0, a0 = np.load(tmp / "before0.npz"), np.load(tmp / "after0.npz")
    for o in optics:
        diff[o] = float(np.max(np.abs(a0[o] - b0[o])) / np.max(np.abs(b0[o])))
    for f in tmp.iterdir():
        f.unlink()
    tmp.rmdir()
    import jax

    sys.path.insert(0, str(ROOT))
    from tofjax.outputs import atomic_write_text

    result = {
        "what": "two checkouts side by side: the forward model's and its value-and-gradient's compile (CPU and wall s, cold) "
                "and call (median ms), default scene, float64; fresh process each, alternating",
        "simulated": True, "scene": "default", "flags": a.flags, "xla_flags": FLAGS[a.flags], "before": a.label,
        "machine": f"{platform.node()} {platform.machine()}, {os.cpu_count()} cores; jax {jax.__version__}",
        "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()), "rounds": a.rounds, "calls": a.calls,
        "median": med, "ratio_after_over_before_median": ratio, "forward_max_relative_difference": diff, "runs": runs,
    }
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(Path(a.out), json.dumps(result, indent=1) + "\n")
    for key in keys:
        print(f"{key:22s} compile cpu {med['before'][key]['compile_cpu_s']:.2f} -> {med['after'][key]['compile_cpu_s']:.2f} s "
              f"(x{ratio[key]['compile_cpu_s']:.2f})  call {med['before'][key]['call_ms']:.2f} -> {med['after'][key]['call_ms']:.2f} ms "
              f"(x{ratio[key]['call_ms']:.2f})  instructions {med['before'][key]['instructions']:.0f} -> {med['after'][key]['instructions']:.0f}")
    print("forward max relative difference", diff)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
