"""Monte Carlo speed: packet-events per second, the current kernel against the old one side by side.

A **packet-event** is one scattering, edge, contact or boundary event of one packet: one
iteration of one live lane of the transport loop (``MCResult.events``: the sum over steps of
the live lanes). Face bounces folded into a free flight are not events; next-event scores are
work done *per* event (4 aperture pieces x 8 elevation nodes by default), not events. The
definition is the same in the old and the new kernel (the same counter), so the rates compare.

The machine is shared, so absolute rates move with the load: each case runs the current kernel
and the old one (``tofjax/mc/transport.py`` and ``slab.py`` of ``--old-commit``, default main at
1a31083, before the second round of speed work; 71e0f30 is main before any; read with
``git show`` and imported in this process) alternately, ``--repeats`` times, and reports medians
and the median of the per-repeat ratios, with the load average before and after. Compilation is
excluded (``MCResult.seconds``); the first run of each program is discarded.

By default only the headline case (optoskin, next-event estimation, float32: issue 14's target of
1e6 packet-events/s), the same with six contacts (touch-six) and the accuracy check run (about 2
minutes on the loaded VM); ``--all`` adds float64, the
analog walk and two slabs. The accuracy check: the detected fractions of old and new with the same
seed (relative L2; when both use the same random stream it is float rounding) against the
seed-to-seed spread, and the ledgers; with ``--all`` also float32 against float64. All data
simulated.

    python experiments/bench_mc.py --out docs/mc-bench.json --overwrite          # headline, ~2 min
    python experiments/bench_mc.py --all --out docs/mc-bench.json --overwrite    # every case
    python experiments/bench_mc.py --ops --cpu-devices 1 --out docs/results/mc-ops.json --overwrite  # single operations
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).parents[1]
#: main before this round of speed work (issue 14, item 5); "71e0f30" is main before any speed work
OLD_COMMIT = "1a31083"


def _load_old(commit: str):
    """The old ``transport`` and ``slab`` modules, imported as ``tofjax.mc._old_transport`` and
    ``tofjax.mc._old_slab`` (same package, so their relative imports resolve)."""
    tmp = Path(tempfile.mkdtemp(prefix="tofjax_old_mc_"))
    mods = []
    for name in ("transport", "slab"):
        src = subprocess.run(["git", "show", f"{commit}:tofjax/mc/{name}.py"], cwd=ROOT, check=True,
                             capture_output=True, text=True).stdout
        src = src.replace("from .transport import", "from ._old_transport import")
        path = tmp / f"_old_{name}.py"
        path.write_text(src)
        spec = importlib.util.spec_from_file_location(f"tofjax.mc._old_{name}", path)
        mod = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = mod
        spec.loader.exec_module(mod)
        mods.append(mod)
    return mods


def _l2(a, b):
    import numpy as np

    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / np.linalg.norm(np.asarray(b)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--photons", type=int, default=10_000, help="photons per sensor of the scenes")
    ap.add_argument("--slab-photons", type=int, default=50_000, help="photons per slab run")
    ap.add_argument("--ops", action="store_true", help="only time single float32 operations on this CPU (ns per element) and write those")
    ap.add_argument("--all", action="store_true", help="also float64, the analog walk and two slabs (default: the headline case only)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--old-commit", default=OLD_COMMIT, help="git commit of the old kernel")
    ap.add_argument("--out", default="docs/mc-bench.json")
    ap.add_argument("--overwrite", action="store_true")
    ap.add_argument("--cpu-devices", type=int, default=os.cpu_count(),
                    help="host CPU devices (one per core; the photons are sharded over them; default: all cores)")
    a = ap.parse_args(argv)
    if "jax" not in sys.modules and a.cpu_devices > 1:
        # before JAX starts: each core a device, so both implementations shard their packets over all cores
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={a.cpu_devices}").strip()
    import jax

    from tofjax import enable_x64
    from tofjax.outputs import atomic_write_text, check_output

    out_path = check_output(a.out, overwrite=a.overwrite)
    if a.ops:
        out = {"benchmark": "float32 elementwise operations on the CPU backend, ns per element (one device, 2**16 "
                            "elements in [0, 1) (cos and sin of 6.28 times that), 200 loop iterations, medians of 5 interleaved rounds, "
                            "wall time; the kernel's reason to avoid the slow ones)",
               "machine": {"description": "the project's 2-core shared x86-64 VM, loaded by other sessions' jobs",
                           "load_average": os.getloadavg(), "jax": jax.__version__},
               "data": "simulated (random inputs)", "ns_per_element": _time_ops()}
        atomic_write_text(out_path, json.dumps(out, indent=1) + "\n", overwrite=a.overwrite)
        print(out["ns_per_element"], f"wrote {out_path}")
        return 0
    from tofjax.compile_cache import use_fast_cpu_compiler  # noqa: E402
    use_fast_cpu_compiler()  # the CLI's CPU compiler (before JAX's backend starts)
    enable_x64()  # for the float64 cases (every case names its dtype)
    from tofjax.mc import MCOptions, run_mc
    from tofjax.mc.slab import SlabOptions, run_slab
    from tofjax.scene import load_scene

    load_start = os.getloadavg()
    old, old_slab = _load_old(a.old_commit)
    scenes = {"optoskin": load_scene("optoskin"), "touch-six": load_scene("touch-six")}
    headline = "optoskin, next-event estimation (default), float32"
    cases = {headline: ("optoskin", dict()),
             "touch-six (six contacts), next-event estimation, float32": ("touch-six", dict())}
    if a.all:
        cases.update({"optoskin, next-event estimation, float64": ("optoskin", dict(dtype="float64")),
                      "optoskin, analog (nee = False), float32": ("optoskin", dict(nee=False))})
    rows = []
    for name, (scene_name, kw) in cases.items():
        scene = scenes[scene_name]
        run_mc(scene, MCOptions(photons=a.photons, **kw))  # compile (and warm) both
        old.run_mc(scene, old.MCOptions(photons=a.photons, **kw))
        new_r, old_r = [], []
        for _ in range(a.repeats):
            new_r.append(run_mc(scene, MCOptions(photons=a.photons, **kw)).events_per_second)
            old_r.append(old.run_mc(scene, old.MCOptions(photons=a.photons, **kw)).events_per_second)
        rows.append(_row(name, new_r, old_r, photons_per_sensor=a.photons))
        print(rows[-1], flush=True)
    slabs = {"slab, van de Hulst (3.7 events per photon)": dict(n=1.0, thickness_m=2e-4, mu_s_per_m=9000, mu_a_per_m=1000, g=0.75),
             "slab, n=1.4 g=0.9 albedo 0.99 tau=10": dict(n=1.4, thickness_m=1e-3, mu_s_per_m=9900, mu_a_per_m=100, g=0.9)}
    for name, kw in (slabs.items() if a.all else ()):
        run_slab(SlabOptions(photons=a.slab_photons, **kw))
        old_slab.run_slab(old_slab.SlabOptions(photons=a.slab_photons, **kw))
        new_r, old_r = [], []
        for _ in range(a.repeats):
            new_r.append(run_slab(SlabOptions(photons=a.slab_photons, **kw)).events_per_second)
            old_r.append(old_slab.run_slab(old_slab.SlabOptions(photons=a.slab_photons, **kw)).events_per_second)
        rows.append(_row(name + ", float32", new_r, old_r, photons=a.slab_photons))
        print(rows[-1], flush=True)

    # accuracy: old against new with the same seed, against the seed-to-seed spread (and with --all,
    # float32 against float64: same seed, same random numbers)
    accuracy = {"note": "relative L2 over all (sensor, zone, bin) of the detected fraction, "
                        f"{a.photons} photons per sensor, next-event estimation: old and new with the same seed "
                        "(the same random stream: float rounding) against the seed-to-seed spread"}
    for scene_name, scene in scenes.items():
        dts = ("float32", "float64") if a.all and scene_name == "optoskin" else ("float32",)
        f = {(impl, dt, seed): m.run_mc(scene, m.MCOptions(photons=a.photons, seed=seed, dtype=dt))
             for impl, m in (("new", sys.modules["tofjax.mc.transport"]), ("old", old))
             for dt in dts for seed in (0, 1)}
        dt = "float32"
        acc = {
            "dtype": dt,
            "old_vs_new_same_seed": _l2(f["new", dt, 0].fraction, f["old", dt, 0].fraction),
            "new_seed0_vs_seed1": _l2(f["new", dt, 1].fraction, f["new", dt, 0].fraction),
            "old_seed0_vs_seed1": _l2(f["old", dt, 1].fraction, f["old", dt, 0].fraction),
            "old_vs_new_mean_of_two_seeds": _l2(
                (f["new", dt, 0].fraction + f["new", dt, 1].fraction) / 2,
                (f["old", dt, 0].fraction + f["old", dt, 1].fraction) / 2),
            "ledger_new_seed0": f["new", dt, 0].ledger,
            "ledger_old_seed0": f["old", dt, 0].ledger,
        }
        if "float64" in dts:
            acc["new_float32_vs_float64_same_seed"] = _l2(f["new", "float32", 0].fraction, f["new", "float64", 0].fraction)
        accuracy[scene_name] = acc
    print(accuracy, flush=True)
    out = {
        "benchmark": "monte carlo packet-events per second, current kernel and the old one side by side",
        "packet_event": "one scattering, edge, contact or boundary event of one packet (one loop iteration of "
                        "one live lane; MCResult.events); identical definition and counter in old and new",
        "machine": {"description": "the project's 2-core shared x86-64 VM, CPU backend, loaded by other "
                                   "sessions' jobs while measured (absolute rates depend on the load; ratios "
                                   "are measured side by side in one process)",
                    "platform": platform.platform(), "processor": platform.processor() or platform.machine(),
                    "cpu_count": os.cpu_count(), "jax": jax.__version__, "backend": jax.default_backend(),
                    "devices": jax.device_count(), "load_average_at_start": load_start,
                    "load_average_at_end": os.getloadavg()},
        "old": f"tofjax/mc/transport.py and slab.py at {a.old_commit}, "
               "read with git show and run alternately with the new kernel in this process",
        "target": "issue 14: >= 1e6 packet-events/s with next-event estimation, float32, on the 2-core CPU",
        "headline": {"case": headline, "events_per_s": rows[0]["events_per_s"],
                     "old_events_per_s": rows[0]["old_events_per_s"],
                     "speedup_median_of_pairs": rows[0]["speedup_median_of_pairs"],
                     "target_met_here": rows[0]["events_per_s"] >= 1e6},
        "data": "simulated",
        "photons_per_sensor": a.photons, "slab_photons": a.slab_photons, "repeats": a.repeats,
        "rows": rows, "accuracy": accuracy,
    }
    atomic_write_text(out_path, json.dumps(out, indent=1) + "\n", overwrite=a.overwrite)
    h = out["headline"]
    print(f"next-event estimation, float32: {h['events_per_s']:.3g} packet-events/s (old {a.old_commit}: "
          f"{h['old_events_per_s']:.3g}; ratio {h['speedup_median_of_pairs']:.2f}); load average "
          f"{load_start[0]:.1f} -> {os.getloadavg()[0]:.1f}")
    print(f"wrote {out_path}")
    return 0


def _time_ops() -> dict:
    import time

    import jax
    import jax.numpy as jnp
    import numpy as np

    from tofjax.mc.transport import _cos_sin_turn, _expm1

    x = jnp.asarray(np.random.default_rng(0).random(1 << 16), jnp.float32)
    ops = {"cos": lambda v: jnp.cos(6.28 * v), "sin": lambda v: jnp.sin(6.28 * v), "exp": jnp.exp, "log": jnp.log,
           "log1p": jnp.log1p, "expm1": jnp.expm1, "sqrt": jnp.sqrt, "multiply": lambda v: v * 1.5,
           "power (float exponent)": lambda v: v ** (3.0 * v), "exp(k log R)": lambda v: jnp.exp(3.0 * v * jnp.log(v)),
           "kernel _cos_sin_turn (cos + sin)": lambda v: sum(_cos_sin_turn(v)), "kernel _expm1": lambda v: _expm1(-v)}
    fns = {name: jax.jit(lambda v, op=op: jax.lax.fori_loop(
        0, 200, lambda i, acc: acc + op(v + i.astype(jnp.float32) * 1e-6), jnp.zeros(v.shape, jnp.float32)))
        for name, op in ops.items()}
    times = {name: [] for name in ops}
    for rnd in range(6):  # interleaved rounds, the first discarded (compilation); medians
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn(x).block_until_ready()
            if rnd:
                times[name].append((time.perf_counter() - t0) / 200 / x.size * 1e9)
    return {name: statistics.median(t) for name, t in times.items()}


def _row(name, new_rates, old_rates, **extra):
    return {"case": name, **extra,
            "events_per_s": statistics.median(new_rates), "events_per_s_all": new_rates,
            "old_events_per_s": statistics.median(old_rates), "old_events_per_s_all": old_rates,
            "speedup_median_of_pairs": statistics.median([n / o for n, o in zip(new_rates, old_rates)])}


if __name__ == "__main__":
    raise SystemExit(main())
