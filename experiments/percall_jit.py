"""Per-call compiles removed (issue 13 cleanup): the second call's time, before and after.

Before (commit 4533487), each call of these built a new ``jax.jit`` of a lambda or of a bound
method, so every call compiled again: ``prune_model`` (the model, its breakdown and each model
without a component), ``bench tradeoff``'s forward models (``_models``), the model-based
reconstruction (its unit-contact responses and its FISTA solve, ``jax.jit(self._fista)``) and the
demo's forward-model timing. After, each is a module-level ``eqx.filter_jit`` function taking the
model (or the lasso problem) as an argument: one program per structure, reused. The reconstruction
also finds FISTA's step by Lanczos instead of a whole eigendecomposition (its largest cost on this
machine once nothing compiles), so its figure is both changes.

Each variant runs in its own process (``before``: the package at 4533487 from ``git archive``;
``after``: this tree), alternating ``--rounds`` times; in each process every case is called
twice, each call from scratch (a new model or reconstructor, as a new command or a second
capture would), and both calls are timed. The outputs of both variants are compared for bit
identity. Float64, OptoSkin scenes, no persistent compilation cache. Simulated scenes and
histograms, no data. Writes JSON.

    python experiments/percall_jit.py --out docs/results/percall_jit.json
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
from pathlib import Path

BASE = "4533487"
VARIANTS = ("before", "after")
CASES = ("reconstruct", "prune", "bench_models", "demo_timing")


def worker(variant: str, dump: str) -> dict:
    import time

    import jax
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    from tofjax.invert.reconstruct import build_reconstructor
    from tofjax.mc.bench import BenchOptions, _models
    from tofjax.mc.prune import prune_model
    from tofjax.model import ModelOptions, Params, build_model
    from tofjax.scene import load_scene
    from tofjax.simulate import expected_counts, simulate

    scene = load_scene("optoskin")
    touch = load_scene("configs/touch-three-line.toml")
    baseline = expected_counts(scene.without_touches())
    frames = simulate(touch, 4, 1).histograms

    def reconstruct():
        return build_reconstructor(scene, baseline, n_baseline=30).strengths(frames)[0]

    def prune():
        r = prune_model(touch)
        return np.array([r.effects[c] for c in r.components] + [r.dropped_effect])

    def bench_models():
        (fd, pd), (fg, pg) = _models(touch, BenchOptions(), touch.components())
        return np.concatenate([np.ravel(fd(pd)), np.ravel(fg(pg))])

    opts = ModelOptions()

    def demo_timing():
        # the demo's step [8/8]: one evaluation of the baseline scene's model, as each version writes it
        base = scene.without_touches()
        p0 = Params.from_scene(base, opts.jnp_dtype)
        if variant == "before":
            return jax.jit(lambda p: build_model(base, opts)(p))(p0)
        from tofjax.mc.prune import evaluate

        return evaluate(build_model(base, opts), p0)

    out, arrays = {}, {}
    for name, fn in (("reconstruct", reconstruct), ("prune", prune), ("bench_models", bench_models),
                     ("demo_timing", demo_timing)):
        ts = []
        for _ in range(2):
            t = time.perf_counter()
            y = np.asarray(jax.block_until_ready(fn()))
            ts.append(time.perf_counter() - t)
        out[name] = {"first_s": ts[0], "second_s": ts[1]}
        arrays[name] = y
    np.savez(dump, **arrays)
    return out


def worker_env(path) -> dict:
    """The environment of a worker process that imports the tofjax package at ``path``: no compilation
    caches (each process pays its own compiles), nothing else on ``PYTHONPATH``."""
    env = {key: val for key, val in os.environ.items() if key not in ("JAX_COMPILATION_CACHE_DIR", "PYTHONPATH")}
    env.update(TOFJAX_PROGRAM_STORE="0", PYTHONPATH=str(path))
    return env


def package_at(base: str, where: Path) -> Path:
    """``tofjax/`` and ``configs/`` of commit ``base``, extracted into ``where`` (``git archive``)."""
    root = Path(__file__).resolve().parents[1]
    where.mkdir(parents=True)
    archive = subprocess.run(["git", "-C", str(root), "archive", base, "tofjax", "configs"], capture_output=True, check=True)
    subprocess.run(["tar", "-x", "-C", str(where)], input=archive.stdout, check=True)
    return where


def run_variants(script: str, base: str, cases, rounds: int, prefix: str, worker_args: list[str]):
    """Run ``script``'s worker in its own process for each variant (``before``: the package at ``base``
    from ``git archive``; ``after``: this tree), alternating ``rounds`` times, without the compilation
    caches; each worker prints its timings as JSON and saves its outputs (one array per case) to the
    ``--dump`` file. Returns (runs per variant, bit identity per case with the largest relative
    difference where not identical, 1-min load averages)."""
    import numpy as np

    root = Path(__file__).resolve().parents[1]
    tmp = Path(tempfile.mkdtemp(prefix=prefix))
    paths = {"before": package_at(base, tmp / "before"), "after": root}
    runs: dict = {v: [] for v in VARIANTS}
    identical: dict = {}
    loads = [os.getloadavg()[0]]
    for k in range(rounds):
        for v in VARIANTS:
            env = worker_env(paths[v])
            dump = tmp / f"{v}{k}.npz"
            args = [x.format(variant=v) for x in worker_args]
            r = subprocess.run([sys.executable, script, *args, "--dump", str(dump)], env=env, cwd=paths[v],
                               capture_output=True, text=True)
            if r.returncode:
                raise SystemExit(f"worker {v} failed: {r.stderr.strip().splitlines()[-3:]}")
            runs[v].append(json.loads(r.stdout.strip().splitlines()[-1]))
            print(v, runs[v][-1], flush=True)
            loads.append(os.getloadavg()[0])
        b, f = np.load(tmp / f"before{k}.npz"), np.load(tmp / f"after{k}.npz")
        for c in cases:
            same = bool(b[c].shape == f[c].shape and np.array_equal(b[c], f[c]))
            identical[c] = identical.get(c, True) and same
            if not same and b[c].shape == f[c].shape:
                d = np.abs(b[c] - f[c])
                rel = float(np.max(d / np.maximum(np.abs(b[c]), 1e-300)))
                identical[c + "_max_abs_difference"] = max(identical.get(c + "_max_abs_difference", 0.0), float(d.max()))
                identical[c + "_max_rel_difference"] = max(identical.get(c + "_max_rel_difference", 0.0), rel)
    return runs, identical, loads


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", help="JSON file to write (required unless --worker)")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--worker", choices=VARIANTS, help=argparse.SUPPRESS)
    ap.add_argument("--dump", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        print(json.dumps(worker(a.worker, a.dump)))
        return 0
    if not a.out:
        ap.error("--out is required")
    from tofjax.outputs import atomic_write_text, check_output

    check_output(a.out, overwrite=True)
    runs, identical, loads = run_variants(__file__, BASE, CASES, a.rounds, "percall_jit_", ["--worker", "{variant}"])
    med = {v: {c: {t: statistics.median(x[c][t] for x in rs) for t in ("first_s", "second_s")} for c in CASES}
           for v, rs in runs.items()}
    out = {
        "what": "second-call time (each call from scratch in one process) of the code paths that built a jitted "
                "lambda or bound method per call, before (4533487) and after (module-level eqx.filter_jit)",
        "data": "simulated scenes and histograms (OptoSkin, touch-three-line), no data",
        "cases": {"reconstruct": "build_reconstructor(optoskin) + strengths of 4 frames (after: also FISTA's step by "
                                 "Lanczos, not a whole eigendecomposition)",
                  "prune": "prune_model(touch-three-line)",
                  "bench_models": "bench tradeoff's _models (default and guided) + one evaluation each",
                  "demo_timing": "the demo's step 8 (one evaluation of a freshly built baseline model)"},
        "runs": runs, "median_s": med,
        "second_call_speedup_before_over_after": {c: med["before"][c]["second_s"] / med["after"][c]["second_s"] for c in CASES},
        "bit_identical": identical,
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "load_average_1min": loads,
                    "note": "the 2-core shared CPU VM, loaded by other jobs: compare only within one run"},
    }
    atomic_write_text(a.out, json.dumps(out, indent=1) + "\n")
    print(json.dumps(out["second_call_speedup_before_over_after"]), json.dumps(identical))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
