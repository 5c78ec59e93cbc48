"""Monte Carlo speed: packet-events per second, against the old implementation side by side.

The machine is shared, so absolute rates move with the load: each case runs the current
kernel and the reference implementation (``--old``: a copy of an older ``transport.py``,
default the one before the vectorised queue, saved by git) alternately, ``--repeats`` times,
and reports medians and the median of the per-repeat ratios.

    python experiments/bench_mc.py --out out/bench_mc.json [--old /tmp/old_transport.py]
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
from pathlib import Path

ROOT = Path(__file__).parents[1]
#: the commit before the fixes and the queue (issue 14): the old kernel, 5.8e4 events/s quoted there
OLD_COMMIT = "3b0b73c"


def _load_old(path: str | None):
    """The old ``transport`` module, imported as ``tofjax.mc._old_transport`` (same package, relative imports)."""
    if path is None:
        src = subprocess.run(["git", "show", f"{OLD_COMMIT}:tofjax/mc/transport.py"], cwd=ROOT, check=True,
                             capture_output=True, text=True).stdout
        path = str(Path(os.environ.get("TMPDIR", "/tmp")) / "tofjax_old_transport.py")
        Path(path).write_text(src)
    spec = importlib.util.spec_from_file_location("tofjax.mc._old_transport", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def _scene_cases():
    from tofjax.scene import load_scene

    return {"optoskin (nee)": (load_scene("optoskin"), {}), "optoskin (analog)": (load_scene("optoskin"), {"nee": False})}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--photons", type=int, default=2_000, help="photons per sensor of the scenes")
    ap.add_argument("--slab-photons", type=int, default=100_000, help="photons per slab run")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--old", help="path of the old transport.py (default: git show OLD_COMMIT)")
    ap.add_argument("--out", default="out/bench_mc.json")
    ap.add_argument("--cpu-devices", type=int, default=os.cpu_count(),
                    help="host CPU devices (one per core; the photons are sharded over them; default: all cores)")
    a = ap.parse_args(argv)
    if "jax" not in sys.modules and a.cpu_devices > 1:
        # before JAX starts: each core a device, so both implementations shard their packets over all cores
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={a.cpu_devices}").strip()
    import jax

    from tofjax.mc import MCOptions, run_mc
    from tofjax.mc.slab import SlabOptions, run_slab

    old = _load_old(a.old)
    rows = []
    for name, (scene, kw) in _scene_cases().items():
        new_r, old_r = [], []
        for _ in range(a.repeats):
            r = run_mc(scene, MCOptions(photons=a.photons, **kw))
            new_r.append(r.events_per_second)
            r = old.run_mc(scene, old.MCOptions(photons=a.photons, **kw))
            old_r.append(r.events_per_second)
        rows.append(_row(name, new_r, old_r))
        print(rows[-1], flush=True)
    # the slab (van de Hulst's): the old kernel has no slab mode; no ratio
    for name, o in {"slab, van de Hulst": SlabOptions(n=1.0, thickness_m=2e-4, mu_s_per_m=9000, mu_a_per_m=1000, g=0.75),
                    "slab, n=1.4 g=0.9 a=0.99 tau=10": SlabOptions(n=1.4, thickness_m=1e-3, mu_s_per_m=9900, mu_a_per_m=100, g=0.9)}.items():
        run_slab(SlabOptions(**{**o.__dict__, "photons": a.slab_photons}))  # compile
        rates = [run_slab(SlabOptions(**{**o.__dict__, "photons": a.slab_photons})).events_per_second for _ in range(a.repeats)]
        rows.append(_row(name, rates, None))
        print(rows[-1], flush=True)
    out = {
        "benchmark": "monte carlo packet-events per second",
        "machine": {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
                    "cpu_count": os.cpu_count(), "jax": jax.__version__, "backend": jax.default_backend(),
                    "devices": jax.device_count(),
                    "load_average_at_end": os.getloadavg()},
        "note": "shared machine: absolute rates depend on the load; ratios are measured side by side",
        "old": f"tofjax/mc/transport.py at {OLD_COMMIT}" if a.old is None else a.old,
        "photons": a.photons, "slab_photons": a.slab_photons, "repeats": a.repeats, "rows": rows,
    }
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {a.out}")
    return 0


def _row(name, new_rates, old_rates):
    row = {"case": name, "events_per_s": statistics.median(new_rates), "events_per_s_best": max(new_rates),
           "events_per_s_all": new_rates}
    if old_rates:
        row["old_events_per_s"] = statistics.median(old_rates)
        row["old_events_per_s_best"] = max(old_rates)
        row["old_events_per_s_all"] = old_rates
        row["speedup"] = statistics.median([n / o for n, o in zip(new_rates, old_rates)])
    return row


if __name__ == "__main__":
    raise SystemExit(main())
