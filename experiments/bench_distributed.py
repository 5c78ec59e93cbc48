"""Benchmark: a small batch of fits and a small Monte Carlo run on 1 process x 1 device,
1 process x 2 devices (forced host devices, ``jax_num_cpu_devices``) and 2 processes x 1
device (``jax.distributed`` on localhost, gloo), side by side in one run.

Every configuration runs in fresh processes (the device count is fixed when JAX starts); each
compiles once (untimed; a persistent compilation cache under ``--cache``), then times
``--repeats`` runs of the same work; the JSON reports medians and the ratio to 1 x 1. The fits
are :func:`tofjax.parallel.fit_many` over ``--fits`` simulated baselines (split into blocks
across processes, ``--chunk`` fits per device per compiled call, no restarts); the Monte Carlo
is :func:`tofjax.parallel.run_mc` with ``--photons`` packets per sensor. Also checks that the
fits and the MC tallies of every configuration equal those of 1 x 1.

    python experiments/bench_distributed.py --out docs/results/distributed.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _worker(a) -> None:
    from tofjax import parallel

    cluster = parallel.Cluster(a.processes, a.process_id, a.coordinator, a.devices)
    parallel.initialize(cluster, timeout_s=120)
    import jax

    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_compilation_cache_dir", a.cache)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    import numpy as np

    from tofjax.mc.transport import MCOptions
    from tofjax.scene import load_scene
    from tofjax.simulate import simulate

    scene = load_scene("optoskin")
    out: dict = {}
    if a.task == "fits":
        mine = parallel.split_items(a.fits, jax.process_index(), jax.process_count())
        caps = [simulate(scene, a.frames, seed=100 + i) for i in mine]

        def work():
            return parallel.fit_many(caps, scene=scene, chunk=a.chunk, restart_failures=False)

        summary = lambda res: [[float(r.params.n1), float(r.reduced_chi2), r.result] for r in res]  # noqa: E731
    else:
        opts = MCOptions(photons=a.photons, seed=1, batch=a.batch)

        def work():
            return parallel.run_mc(scene, opts)

        summary = lambda r: {"fraction_sum": float(np.sum(r.fraction)), "events": r.events, "ledger": r.ledger}  # noqa: E731
    t0 = time.perf_counter()
    res = work()  # compiles (or loads from the cache)
    out["first_s"] = time.perf_counter() - t0
    times = []
    for _ in range(a.repeats):
        parallel.allgather_json(0)  # start together
        t0 = time.perf_counter()
        res = work()
        parallel.allgather_json(0)  # the run is done when the slowest process is
        times.append(time.perf_counter() - t0)
    out["seconds"] = times
    out["result"] = parallel.gather_items(summary(res), mine, a.fits) if a.task == "fits" else summary(res)
    if jax.process_index() == 0:
        print("RESULT " + json.dumps(out), flush=True)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _run_config(a, task: str, processes: int, devices: int) -> dict:
    port = _free_port()
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("XLA_FLAGS", None)
    argv = [sys.executable, __file__, "--worker", task, "--processes", str(processes), "--devices", str(devices),
            "--coordinator", f"localhost:{port}", "--fits", str(a.fits), "--frames", str(a.frames),
            "--chunk", str(a.chunk), "--photons", str(a.photons), "--batch", str(a.batch),
            "--repeats", str(a.repeats), "--cache", a.cache]
    procs = [subprocess.Popen(argv + ["--process-id", str(k)], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True) for k in range(processes)]
    outs = [p.communicate() for p in procs]
    for p, (o, e) in zip(procs, outs):
        if p.returncode != 0:
            raise SystemExit(f"bench_distributed: {task} on {processes} x {devices} failed:\n{e[-2000:]}")
    line = [x for x in outs[0][0].splitlines() if x.startswith("RESULT ")][-1]
    r = json.loads(line[len("RESULT "):])
    r["median_s"] = statistics.median(r["seconds"])
    return r


def _same(task: str, a, b) -> bool:
    import numpy as np

    if task == "fits":
        return all(x[2] == y[2] and np.isclose(x[0], y[0], rtol=1e-9) and np.isclose(x[1], y[1], rtol=1e-9) for x, y in zip(a, b))
    return a["events"] == b["events"] and bool(np.isclose(a["fraction_sum"], b["fraction_sum"], rtol=1e-5))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="docs/results/distributed.json")
    ap.add_argument("--fits", type=int, default=4, help="baselines fitted (default 4)")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--chunk", type=int, default=2, help="fits per device per compiled call (default 2)")
    ap.add_argument("--photons", type=int, default=20_000, help="MC packets per sensor (default 2e4)")
    ap.add_argument("--batch", type=int, default=8192)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--tasks", default="fits,mc", help="fits, mc or both (a task left out keeps its old rows)")
    ap.add_argument("--cache", default=str(Path(tempfile.gettempdir()) / f"tofjax-bench-distributed-{os.getuid()}"))
    ap.add_argument("--configs", default="1x1,1x2,2x1",
                    help="PROCESSESxDEVICES, comma-separated, the first the reference (default 1x1,1x2,2x1)")
    ap.add_argument("--machine", help="the machine, in words, for the JSON (default: this 2-core shared VM)")
    ap.add_argument("--worker", choices=["fits", "mc"], help=argparse.SUPPRESS)
    ap.add_argument("--processes", type=int, default=1, help=argparse.SUPPRESS)
    ap.add_argument("--process-id", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--devices", type=int, default=1, help=argparse.SUPPRESS)
    ap.add_argument("--coordinator", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        a.task = a.worker
        return _worker(a)
    from tofjax.outputs import atomic_write_text, check_output

    try:
        configs = [tuple(int(x) for x in c.lower().split("x")) for c in a.configs.split(",")]
        if any(len(c) != 2 or min(c) < 1 for c in configs):
            raise ValueError
    except ValueError:
        ap.error(f"--configs: expected e.g. 1x1,1x2,2x1 (processes x devices, each >= 1), got {a.configs!r}")
    check_output(a.out, overwrite=True)
    t_start = time.perf_counter()
    old = json.loads(Path(a.out).read_text()) if Path(a.out).exists() else {}
    result: dict = {
        "benchmark": "studies on several devices and processes (tofjax.parallel)",
        "data": "simulated (fits: simulated optoskin baselines; Monte Carlo of optoskin)",
        "machine": (a.machine or "the 2-core shared CPU VM, loaded (other sessions running)")
                   + f"; load average at start {os.getloadavg()[0]:.1f}, {platform.processor() or platform.machine()}, "
                   f"{os.cpu_count()} cores",
        "load_average_at_start": os.getloadavg()[0],
        "settings": {k: getattr(a, k) for k in ("fits", "frames", "chunk", "photons", "batch", "repeats", "configs")},
        "note": "wall time of the timed runs after one untimed first run (compile), medians over repeats; "
                "on N cores, P processes x D devices cannot beat 1 x 1 by more than min(N, P D)",
    }
    for task in a.tasks.split(","):
        result.pop(task, None)
        rows = []
        base = None
        for p, d in configs:
            r = _run_config(a, task, p, d)
            base = base or r
            rows.append({
                "processes": p, "devices_per_process": d, "median_s": r["median_s"], "seconds": r["seconds"],
                "first_run_s": r["first_s"], "speedup_vs_1x1": base["median_s"] / r["median_s"],
                "equal_to_1x1": _same(task, base["result"], r["result"]),
            })
            result[task] = rows
            result["complete"] = False
            atomic_write_text(a.out, json.dumps(result, indent=1))  # a run cut short keeps what it measured
            print(f"{task}: {p} process(es) x {d} device(s): median {r['median_s']:.2f} s "
                  f"({base['median_s'] / r['median_s']:.2f}x of 1 x 1), equal to 1 x 1: {rows[-1]['equal_to_1x1']}",
                  flush=True)
        result[task] = rows
        result[f"{task}_settings"] = dict(result["settings"], load_average_at_start=result["load_average_at_start"])
    for task in ("fits", "mc"):  # a task not run this time keeps its rows from the last run
        if task not in result and task in old:
            result[task], result[f"{task}_settings"] = old[task], old.get(f"{task}_settings")
    result["bench_seconds"] = time.perf_counter() - t_start
    result["complete"] = True
    atomic_write_text(a.out, json.dumps(result, indent=1))
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
