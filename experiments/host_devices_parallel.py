"""Do forced host devices run at the same time? (why `bench_distributed.py` found no speed-up from 1 x 8 devices
on 16 idle cores, `docs/results/distributed_16core.json`).

A latency-bound program (a ``fori_loop`` of small elementwise steps on a 64-vector: one thread's work, as a
fit's solver loop is) is dispatched (a) once on device 0, (b) once on each of two forced host devices
(``--xla_force_host_platform_device_count=2``) without waiting in between, (c) twice on device 0, and (d) as
two separate processes at once, each on its one device. If the two devices ran at the same time, (b) would take
about (a)'s time; if they run one after the other, about (c)'s. (d) shows what the machine's cores give when
the work is in two processes. Medians of ``--repeats``; the JSON holds every time.

    python experiments/host_devices_parallel.py --out docs/results/host_devices_parallel.json
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


def _program(steps: int):
    import jax
    import jax.numpy as jnp

    @jax.jit
    def work(x):
        def body(i, x):
            return jnp.sin(x) * 0.999 + 0.001 * jnp.cos(x[::-1])

        return jax.lax.fori_loop(0, steps, body, x)

    return jax, jnp, work


def worker(steps: int, repeats: int) -> dict:
    """One process with two forced host devices: the times of (a), (b), (c)."""
    jax, jnp, work = _program(steps)
    d = jax.devices()
    x0, x1 = jax.device_put(jnp.ones((64,)), d[0]), jax.device_put(jnp.ones((64,)), d[1])
    for x in (x0, x1):
        work(x).block_until_ready()  # compile for each device
    out = {"one": [], "two_devices": [], "twice_one_device": [], "dispatch_returned_s": []}
    for _ in range(repeats):
        t = time.perf_counter()
        work(x0).block_until_ready()
        out["one"].append(time.perf_counter() - t)
        t = time.perf_counter()
        a = work(x0)
        out["dispatch_returned_s"].append(time.perf_counter() - t)
        b = work(x1)
        a.block_until_ready(), b.block_until_ready()
        out["two_devices"].append(time.perf_counter() - t)
        t = time.perf_counter()
        a, b = work(x0), work(x0)
        a.block_until_ready(), b.block_until_ready()
        out["twice_one_device"].append(time.perf_counter() - t)
    out["jax"] = jax.__version__
    return out


def single(steps: int, repeats: int) -> list:
    """One process, one device: the time of one run, ``repeats`` times (for (d))."""
    _, jnp, work = _program(steps)
    x = jnp.ones((64,))
    work(x).block_until_ready()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        work(x).block_until_ready()
        times.append(time.perf_counter() - t)
    return times


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", help="JSON file to write")
    ap.add_argument("--steps", type=int, default=200_000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--worker", choices=["two", "single"], help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker == "two":
        os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=2"
        print(json.dumps(worker(a.steps, a.repeats)))
        return 0
    if a.worker == "single":
        print(json.dumps(single(a.steps, a.repeats)))
        return 0
    if not a.out:
        ap.error("--out is required")
    sys.path.insert(0, str(ROOT))
    from tofjax.outputs import atomic_write_text, check_output

    check_output(a.out, overwrite=True)
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"} | {"JAX_PLATFORMS": "cpu"}
    cmd = [sys.executable, __file__, "--steps", str(a.steps), "--repeats", str(a.repeats)]
    load0 = os.getloadavg()[0]
    two = json.loads(subprocess.run(cmd + ["--worker", "two"], env=env, capture_output=True, text=True, check=True).stdout)
    alone = json.loads(subprocess.run(cmd + ["--worker", "single"], env=env, capture_output=True, text=True, check=True).stdout)
    procs = [subprocess.Popen(cmd + ["--worker", "single"], env=env, stdout=subprocess.PIPE, text=True) for _ in range(2)]
    pair = [json.loads(p.communicate()[0]) for p in procs]  # their timed runs overlap (same work, same start)
    med = {k: statistics.median(v) for k, v in two.items() if isinstance(v, list)}
    rep = {
        "what": "do forced host devices run at the same time? a latency-bound fori_loop on one device, on two at once, "
                "twice on one, and in two processes at once",
        "machine": f"{platform.machine()}, {os.cpu_count()} cores; load average {load0:.1f} at the start, "
                   f"{os.getloadavg()[0]:.1f} at the end",
        "jax": two["jax"], "steps": a.steps, "repeats": a.repeats,
        "in_one_process": two, "medians_s": med,
        "two_devices_speedup": 2 * med["one"] / med["two_devices"],
        "two_processes": {"alone_s": alone, "each_of_two_at_once_s": pair,
                          "slowdown_at_once": statistics.median(pair[0] + pair[1]) / statistics.median(alone)},
    }
    atomic_write_text(a.out, json.dumps(rep, indent=1))
    print(f"one device {med['one']:.3f} s; two devices at once {med['two_devices']:.3f} s "
          f"(speed-up {rep['two_devices_speedup']:.2f}x, 2.0 = parallel); twice on one device {med['twice_one_device']:.3f} s; "
          f"two processes at once: each {rep['two_processes']['slowdown_at_once']:.2f}x its time alone (1.0 = parallel)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
