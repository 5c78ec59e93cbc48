"""Benchmark: the Monte Carlo on an accelerator (issue 14 item 5: "report GPU figures where a GPU
machine is available").

Runs :func:`tofjax.mc.run_mc` (next-event estimation, the default) on JAX's default backend, which is
the GPU where one is found, over a ladder of photon counts and lane batches (a GPU needs many more
packets in flight than the CPU's default ``MCOptions.batch``), and reports **packet-events per
second** (the same counter as ``experiments/bench_mc.py``: one loop iteration of one live lane,
``MCResult.events``; compilation excluded, ``MCResult.seconds``). Each row: one untimed run
(compile and warm), then ``--repeats`` timed runs; the median. Also the energy ledger of one run
(conservation: emitted = detected + absorbed + escaped + ...), so a fast but wrong kernel shows.

The CPU figure in the README comes from the 2-core VM (another machine): compare rates across
machines as what they are, not as a speed-up of one code path. All data **simulated**.

    python experiments/bench_gpu.py --out out/gpu/mc_gpu.json
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

#: (scene, photons per sensor, lane batch, dtype)
LADDER = (
    ("optoskin", 100_000, 32_768, "float32"),
    ("optoskin", 1_000_000, 32_768, "float32"),
    ("optoskin", 1_000_000, 262_144, "float32"),
    ("optoskin", 4_000_000, 1_048_576, "float32"),
    ("touch-six", 1_000_000, 262_144, "float32"),
    ("optoskin", 1_000_000, 262_144, "float64"),
)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="JSON file to write")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--max-seconds", type=float, default=240.0, help="stop adding rows after this much wall time")
    ap.add_argument("--quick", action="store_true", help="small photon counts only (a smoke test on a CPU)")
    a = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    import jax

    from tofjax import enable_x64

    enable_x64()  # the float64 row; every row names its dtype
    from tofjax.mc import MCOptions, run_mc
    from tofjax.outputs import atomic_write_text
    from tofjax.scene import load_scene

    t0 = time.perf_counter()
    ladder = [(s, p // 100, min(b, 8192), d) for s, p, b, d in LADDER[:2]] if a.quick else LADDER
    out = {
        "benchmark": "monte carlo packet-events per second on JAX's default backend (next-event estimation)",
        "data": "simulated",
        "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(), "python": sys.version.split()[0],
                    "jax": jax.__version__, "backend": jax.default_backend(),
                    "devices": [str(d) for d in jax.devices()],
                    "device_kind": jax.devices()[0].device_kind},
        "repeats": a.repeats,
        "rows": [],
    }
    path = Path(a.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    for scene_name, photons, batch, dtype in ladder:
        if time.perf_counter() - t0 > a.max_seconds:
            out["stopped_early"] = f"--max-seconds {a.max_seconds} reached before {scene_name} {photons} {batch} {dtype}"
            break
        scene = load_scene(scene_name)
        opts = MCOptions(photons=photons, batch=batch, dtype=dtype)
        first = run_mc(scene, opts)
        rates, secs = [], []
        for _ in range(a.repeats):
            r = run_mc(scene, opts)
            rates.append(r.events_per_second)
            secs.append(r.seconds)
        row = {"scene": scene_name, "photons_per_sensor": photons, "batch": batch, "dtype": dtype,
               "devices": first.devices, "events_per_run": first.events,
               "events_per_s_median": statistics.median(rates), "events_per_s": rates,
               "seconds_median": statistics.median(secs), "compile_seconds_first_run": first.compile_seconds,
               "ledger_first_run": first.ledger}
        out["rows"].append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "ledger_first_run"}), flush=True)
        atomic_write_text(path, json.dumps(out, indent=1) + "\n", overwrite=True)
    out["seconds"] = time.perf_counter() - t0
    best = max(out["rows"], key=lambda r: r["events_per_s_median"]) if out["rows"] else None
    out["best"] = best and {k: best[k] for k in ("scene", "photons_per_sensor", "batch", "dtype", "events_per_s_median")}
    atomic_write_text(path, json.dumps(out, indent=1) + "\n", overwrite=True)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
