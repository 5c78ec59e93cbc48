"""The fusion emitters where XLA does not optimise: the Monte Carlo's transport compiled and run with
``--xla_backend_optimization_level=0`` (the test suite's default selection, ``tests/conftest.py``), with and
without the compile option it asks for (``tofjax.compile_cache.FUSION_EMITTERS``).

Each measurement runs in a fresh Python process (``--worker``) with the test suite's ``$XLA_FLAGS`` (the elemental
emitters for the rest, level 0, LLVM's expensive passes off), no persistent cache, the two variants alternating
``--rounds`` times (the order flipped every round). Per process, float64 (as the tests), the built-in
``touch-three-line`` scene, next-event estimation: the transport's compile seconds and run seconds at 2,000 and at
20,000 photons per sensor (two programs: the batch size differs). All data **simulated**.

Where the backend does not optimise, the fusion emitters make the transport no faster and its compile about twice
as slow, so :data:`tofjax.compile_cache.FUSION_EMITTERS` is empty there.

    python experiments/emitters_unoptimised.py --rounds 3 --out docs/results/emitters_unoptimised.json
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

ROOT = Path(__file__).resolve().parents[1]
TEST_FLAGS = ("--xla_cpu_use_fusion_emitters=false --xla_backend_optimization_level=0 "
              "--xla_llvm_disable_expensive_passes=true")
PHOTONS = (2_000, 20_000)


def worker(variant: str) -> dict:
    sys.path.insert(0, str(ROOT))
    import jax

    jax.config.update("jax_enable_x64", True)
    import tofjax.compile_cache as cc

    if variant == "fusion":  # what the transport asked for before: the option whatever the level
        cc.FUSION_EMITTERS = dict(cc._FUSION_ON)
    elif dict(cc.FUSION_EMITTERS):
        raise SystemExit("FUSION_EMITTERS is not empty at level 0")
    from tofjax.mc import MCOptions, run_mc
    from tofjax.scene import load_scene

    scene = load_scene("touch-three-line")
    out = {}
    for n in PHOTONS:
        r = run_mc(scene, MCOptions(photons=n, seed=0))
        out[f"compile_s_{n}"] = r.compile_seconds
        out[f"run_s_{n}"] = r.seconds
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=3, help="alternations of the two variants (default 3)")
    ap.add_argument("--out", help="JSON file to write")
    ap.add_argument("--overwrite", action="store_true")
    ap.add_argument("--worker", choices=("fusion", "none"), help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        print(json.dumps(worker(a.worker)))
        return 0
    if a.rounds < 1:
        ap.error("--rounds must be >= 1")
    if not a.out:
        ap.error("--out is required")
    sys.path.insert(0, str(ROOT))
    from tofjax.outputs import OutputError, atomic_write_text, check_output

    try:
        path = check_output(Path(a.out), overwrite=a.overwrite)
    except OutputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    env = {**os.environ, "XLA_FLAGS": TEST_FLAGS, "TOFJAX_COMPILATION_CACHE": "0", "TOFJAX_PROGRAM_STORE": "0",
           "JAX_ENABLE_COMPILATION_CACHE": "false"}
    runs: dict[str, list[dict]] = {"fusion": [], "none": []}
    for r in range(a.rounds):
        for v in ("fusion", "none") if r % 2 == 0 else ("none", "fusion"):
            p = subprocess.run([sys.executable, __file__, "--worker", v], env=env, capture_output=True, text=True,
                               check=False)
            if p.returncode != 0:
                print(f"error: worker {v} failed:\n{p.stderr[-2000:]}", file=sys.stderr)
                return 1
            runs[v].append(json.loads(p.stdout.strip().splitlines()[-1]))
            print(v, runs[v][-1], flush=True)
    keys = list(runs["none"][0])
    med = {v: {k: statistics.median(x[k] for x in rs) for k in keys} for v, rs in runs.items()}
    result = {
        "study": "the Monte Carlo's transport at --xla_backend_optimization_level=0 with and without the fusion "
                 "emitters' compile option (fresh process each, alternating)",
        "data": "simulated (touch-three-line, next-event estimation, float64)",
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs ({platform.platform()}), CPU only",
        "xla_flags": TEST_FLAGS, "rounds": a.rounds, "runs": runs, "median": med,
        "ratio_fusion_over_none": {k: med["fusion"][k] / med["none"][k] for k in keys},
    }
    atomic_write_text(path, json.dumps(result, indent=1))
    print(json.dumps(result["median"], indent=1))
    print(json.dumps(result["ratio_fusion_over_none"], indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
