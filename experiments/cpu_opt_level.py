"""XLA's CPU backend optimisation level for the CLI's programs: XLA's default level against level 1 and level 0
(``--xla_backend_optimization_level``; level 0 with ``--xla_llvm_disable_expensive_passes=true``, what the default
test run compiles with, tests/conftest.py), all on the elemental emitters the CLI selects (:func:`tofjax.compile_cache.use_fast_cpu_compiler`).

Each measurement runs in a fresh Python process (``--worker``) with an explicit ``$XLA_FLAGS``, cold
(``TOFJAX_PROGRAM_STORE=0 TOFJAX_COMPILATION_CACHE=0``, no JAX persistent cache), the variants' order rotated
every round so a shared machine's swings fall on all alike. Per process, float64, the default scene, a
**simulated** 100-frame baseline (seed 1000), measured by ``experiments/cpu_emitters.py``'s
``calibration_and_model_timings``:

* ``calibration_cold_s``: ``Calibrator(scene).fit(capture)``, the first in the process (compilations and one fit);
* ``calibration_warm_s`` and ``steps``: the median of ``--warm`` more fits of the same capture, and the fit's steps.
  The fit's path depends on rounding (where a fit creeps along a ridge, the steps differ between levels: the demo's
  OptoSkin baseline takes 73-199), so ``warm_per_step_s`` is the comparable run-time figure;
* ``model_compile_s`` / ``model_warm_s``: ``jit(value_and_grad(sum(model(p)^2)))`` compiled and its median call;
* ``n1``, ``mu_t``, ``reduced_chi2``: the fit's answer.

Wall seconds, medians over the rounds, and per-round ratios against the default level.

    python experiments/cpu_opt_level.py --rounds 3 --out docs/results/cpu_opt_level.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ELEMENTAL = "--xla_cpu_use_fusion_emitters=false"
VARIANTS = {
    "default": ELEMENTAL,
    "level1": f"{ELEMENTAL} --xla_backend_optimization_level=1",
    "level0": f"{ELEMENTAL} --xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true",
}
MEASURES = ("calibration_cold_s", "calibration_warm_s", "warm_per_step_s", "model_compile_s", "model_warm_s")


def worker(warm: int) -> dict:
    import numpy as np

    from cpu_emitters import calibration_and_model_timings  # the same measurements, per variant

    _, _, _, res, cold, times, m_compile, m_warm = calibration_and_model_timings(warm)
    warm_s = statistics.median(times)
    return {
        "calibration_cold_s": cold, "calibration_warm_s": warm_s, "steps": int(res.steps),
        "warm_per_step_s": warm_s / max(int(res.steps), 1), "model_compile_s": m_compile, "model_warm_s": m_warm,
        "n1": float(res.params.n1), "mu_t": float(np.asarray(res.params.mu_s_per_m) + np.asarray(res.params.mu_a_per_m)),
        "reduced_chi2": float(res.reduced_chi2), "result": res.result, "xla_flags": os.environ.get("XLA_FLAGS", ""),
    }


def run_worker(label: str, xla_flags: str, warm: int, tree: Path = ROOT) -> dict:
    """One cold worker process (:func:`worker`) of ``tree``'s copy of this script, with ``xla_flags``, no program store and
    no compilation cache; its record with the 1-minute load at its start. ``label`` names it in a failure.
    ``experiments/tree_compare.py`` runs it for two checkouts."""
    env = dict(os.environ, XLA_FLAGS=xla_flags, TOFJAX_PROGRAM_STORE="0", TOFJAX_COMPILATION_CACHE="0",
               JAX_PLATFORMS="cpu", PYTHONPATH=str(tree))
    return fresh_record([str(tree / "experiments" / "cpu_opt_level.py"), "--worker", "--warm", str(warm)], env, tree, label)


def fresh_record(args: list, env: dict, cwd: Path, label: str, timeout: float | None = None) -> dict:
    """Run ``python args`` in a fresh process (``env``, in ``cwd``) and return the JSON record its last line of output
    prints, with the 1-minute load at its start. A failure, or a run past ``timeout`` seconds, stops with a message
    that names ``label``. ``experiments/model_compile_compare.py`` runs its workers through it too."""
    load = os.getloadavg()[0]
    try:
        out = subprocess.run([sys.executable, *args], env=env, capture_output=True, text=True, check=False, cwd=str(cwd),
                             timeout=timeout)
    except subprocess.TimeoutExpired:
        raise SystemExit(f"worker ({label}) did not finish in {timeout:.0f} s") from None
    if out.returncode != 0:
        print(out.stderr[-3000:], file=sys.stderr)
        raise SystemExit(f"worker ({label}) failed with exit code {out.returncode}")
    rec = json.loads(out.stdout.strip().splitlines()[-1])
    rec["load_1min"] = load
    return rec


def describe(r: int, label: str, rec: dict) -> str:
    """A worker's record as one progress line."""
    return (f"round {r + 1} {label:8s} cold {rec['calibration_cold_s']:6.2f} s  warm {rec['calibration_warm_s'] * 1e3:6.0f} ms "
            f"({rec['steps']} steps, {rec['warm_per_step_s'] * 1e3:5.1f} ms each)  model compile {rec['model_compile_s']:5.2f} s  "
            f"warm {rec['model_warm_s'] * 1e3:6.2f} ms  n1 {rec['n1']:.9f}  load {rec['load_1min']:.1f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", help="JSON file to write")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--warm", type=int, default=5, help="warm fits per process (median)")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        print(json.dumps(worker(a.warm)))
        return 0
    if not a.out:
        ap.error("--out is required")
    if a.rounds < 1 or a.warm < 1:
        ap.error("--rounds and --warm must be >= 1")
    names = list(VARIANTS)
    runs = {v: [] for v in names}
    for r in range(a.rounds):
        order = names[r % len(names):] + names[: r % len(names)]
        for v in order:
            rec = run_worker(v, VARIANTS[v], a.warm)
            runs[v].append(rec)
            print(describe(r, v, rec), flush=True)
    med = {v: {m: statistics.median(x[m] for x in runs[v]) for m in MEASURES} for v in names}
    ratios = {v: {m: [x[m] / d[m] for x, d in zip(runs[v], runs["default"])] for m in MEASURES} for v in names if v != "default"}
    spread = {v: {"n1_max_abs_difference": max(abs(x["n1"] - d["n1"]) for x, d in zip(runs[v], runs["default"])),
                  "mu_t_max_rel_difference": max(abs(x["mu_t"] - d["mu_t"]) / d["mu_t"] for x, d in zip(runs[v], runs["default"]))}
              for v in names if v != "default"}
    sys.path.insert(0, str(ROOT))
    import jax

    from tofjax.outputs import atomic_write_text

    result = {
        "what": "XLA CPU backend optimisation level (elemental emitters): cold calibration (compile + first fit), warm fit "
                "and its time per step, model value-and-grad compile and call; fresh process each",
        "simulated": True, "scene": "default", "frames": 100, "seed": 1000, "variants": VARIANTS,
        "machine": f"{platform.node()} {platform.machine()}, {os.cpu_count()} cores; jax {jax.__version__}",
        "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()), "rounds": a.rounds, "warm_fits": a.warm,
        "median": med, "ratio_over_default_per_round": ratios,
        "ratio_median": {v: {m: statistics.median(x) for m, x in r.items()} for v, r in ratios.items()},
        "answers_against_default": spread, "runs": runs,
    }
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(Path(a.out), json.dumps(result, indent=1) + "\n")
    for m in MEASURES:
        print(f"{m:20s} " + "  ".join(f"{v} {med[v][m]:.4g}" for v in names)
              + "  ratios " + "  ".join(f"{v} {result['ratio_median'][v][m]:.2f}" for v in ratios))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
