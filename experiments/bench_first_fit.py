"""Benchmark: time to the first calibration in a new process, with the persistent compilation cache
cold, warm and turned off (issue 16, item 3).

Every ``tofjax`` process compiles its fit afresh unless the persistent compilation cache
(:mod:`tofjax.compile_cache`) already holds the programs. This runs ``tofjax calibrate`` on the
same simulated baseline as separate processes:

* ``off``: ``TOFJAX_COMPILATION_CACHE=0`` (what every run cost before the cache);
* ``cold``: an empty cache folder (the first run on a machine: compiles and writes entries);
* ``warm``: the same folder again (every later run on that machine): the compiled program from
  the XLA cache and the traced program from tofjax's program store
  (:func:`tofjax.compile_cache.call_stored`);
* ``warm_xla_only``: the program store off (``TOFJAX_PROGRAM_STORE=0``) in a second folder
  that one store-off run filled first: what the XLA cache alone gives; the process traces the
  fit again (the traced and the stored program are different XLA programs, so each needs its own
  entries).

Each is repeated ``--repeats`` times (cold uses a fresh folder each time) and the medians are
reported, with the warm/off ratio measured side by side in one run. The times are whole
processes (imports, reading the capture, the fit, writing the JSON), since that is what a user
waits for.

Writes ``first_fit.json`` to ``--out``. Its fast check in the test suite is
``tests/test_compile_cache.py::test_second_process_reads_the_cache`` (two processes, one
program): the benchmark itself compiles a calibration several times and belongs outside the
suite's budget.

    python experiments/bench_first_fit.py --out out/bench [--scene optoskin] [--frames 20] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _run(cmd: list[str], cache: str, store: str = "1") -> float:
    env = dict(os.environ, TOFJAX_COMPILATION_CACHE=cache, TOFJAX_PROGRAM_STORE=store)
    t0 = time.perf_counter()
    done = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({done.returncode}):\n{done.stderr}")
    return wall


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True)
    p.add_argument("--scene", default="optoskin")
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--repeats", type=int, default=3)
    a = p.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    tofjax = [sys.executable, "-m", "tofjax.cli"]
    with tempfile.TemporaryDirectory() as tmp:
        cap = Path(tmp) / "baseline.h5"
        _run(tofjax + ["simulate", a.scene, "--frames", str(a.frames), "--out", str(cap)], "0")
        fit = tofjax + ["calibrate", str(cap), "--out", str(Path(tmp) / "cal.json"), "--overwrite"]
        times: dict[str, list[float]] = {"off": [], "cold": [], "warm": [], "warm_xla_only": []}
        for r in range(a.repeats):
            folder = Path(tmp) / f"cache{r}"
            times["off"].append(_run(fit, "0"))
            times["cold"].append(_run(fit, str(folder)))
            times["warm"].append(_run(fit, str(folder)))
            xla_only = Path(tmp) / f"xla{r}"
            _run(fit, str(xla_only), store="0")
            times["warm_xla_only"].append(_run(fit, str(xla_only), store="0"))
            shutil.rmtree(xla_only, ignore_errors=True)
            entries = sum(1 for _ in folder.rglob("*") if _.is_file())
            shutil.rmtree(folder, ignore_errors=True)
            print(f"repeat {r}: off {times['off'][-1]:.1f} s, cold {times['cold'][-1]:.1f} s, "
                  f"warm {times['warm'][-1]:.1f} s, warm without the program store {times['warm_xla_only'][-1]:.1f} s "
                  f"({entries} cache files)", flush=True)
    med = {k: statistics.median(v) for k, v in times.items()}
    report = {
        "what": "wall time of a whole `tofjax calibrate` process on a simulated baseline",
        "scene": a.scene,
        "frames": a.frames,
        "repeats": a.repeats,
        "seconds": times,
        "median_s": med,
        "warm_over_off": med["warm"] / med["off"],
        "warm_over_warm_xla_only": med["warm"] / med["warm_xla_only"],
        "load_average_1min": os.getloadavg()[0],
        "cold_over_off": med["cold"] / med["off"],
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "python": sys.version.split()[0]},
    }
    from tofjax.outputs import atomic_write_text

    atomic_write_text(out / "first_fit.json", json.dumps(report, indent=2))
    print(f"median: off {med['off']:.1f} s, cold {med['cold']:.1f} s, warm {med['warm']:.1f} s, "
          f"warm without the program store {med['warm_xla_only']:.1f} s "
          f"(warm/off {report['warm_over_off']:.2f}); wrote {out / 'first_fit.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
