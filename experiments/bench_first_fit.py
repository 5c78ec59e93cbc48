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

``--trees main=/work/main,branch=.`` runs the same processes for several source trees (each on
``PYTHONPATH``, interleaved within every repeat so that they share the machine's load) and
reports each tree's medians and their ratios. ``--profile`` also runs every tree's warm process
under ``experiments/_first_fit_probe.py`` (``--repeats`` times) and writes
``first_fit_profile.json`` (``<--json>_profile.json``): the median seconds of each stage (interpreter start, the imports of
jax, equinox, optimistix and tofjax, reading the capture, the timing and envelope starts, loading
the stored programs, the joint fit, the Laplace covariance, writing the JSON) and JAX's own
compile events. ``--modes`` picks among off, cold, warm and warm_xla_only (default all).

``--compare REF`` is the side-by-side comparison in one option: ``--trees base=REF,this=<this
tree> --modes warm``. Without ``cold`` among the modes every tree fills its own fresh cache folder
once (a cold run, not counted) and its warm runs then reuse it, the trees alternating run by run;
with ``cold`` every repeat starts from a fresh folder as before. Besides the wall time, every run's
CPU time (user + system of the child process) is recorded: on a machine shared with other work it
is the steadier of the two.

With ``--compare`` (or ``--trees`` without cold runs) the JSON also lists every stored executable
of each tree's filled folder with its size and the time (wall and CPU) one fresh process takes
to read it (``stored_executables``). The JSON also holds each tree's estimates from its last run (n1, mu_t, reduced chi-square, steps,
n1's standard error) and, with several trees, their relative differences from the first tree's.

Writes ``first_fit.json`` (or ``--json NAME``) to ``--out``. Its fast check in the test suite is
``tests/test_compile_cache.py::test_second_process_reads_the_cache`` (two processes, one
program): the benchmark itself compiles a calibration several times and belongs outside the
suite's budget.

    python experiments/bench_first_fit.py --out out/bench [--scene optoskin] [--frames 20] [--repeats 3]
        [--trees main=/work/main,branch=.] [--modes cold,warm] [--profile]
    # idle side-by-side comparison with another checkout (e.g. git worktree add /tmp/base b224fd3):
    python experiments/bench_first_fit.py --out out/bench --compare /tmp/base --repeats 7
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


ROOT = Path(__file__).resolve().parents[1]
PROBE = Path(__file__).resolve().parent / "_first_fit_probe.py"
MODES = ("off", "cold", "warm", "warm_xla_only")


CPU: list[float] = []  # CPU seconds (user + system) of the last child run by _run


def _run(cmd: list[str], cache: str, store: str = "1", tree: Path = ROOT) -> float:
    """Wall seconds of one child process (its CPU seconds are appended to ``CPU``)."""
    import resource

    env = dict(os.environ, TOFJAX_COMPILATION_CACHE=cache, TOFJAX_PROGRAM_STORE=store, PYTHONPATH=str(tree))
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    # from a neutral folder: ``python -m`` puts the working directory first on sys.path, so run
    # from inside a checkout it would import that checkout's tofjax whatever PYTHONPATH says
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=tempfile.gettempdir())
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    CPU.append((r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime))
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({done.returncode}):\n{done.stderr}")
    return wall


def _stages(probe: dict) -> dict[str, float]:
    """Seconds per stage of one probed process (calls of the same stage summed)."""
    out: dict[str, float] = {"interpreter start": probe["interpreter_start_s"]}
    for mod, secs in probe["imports_s"]:
        out[f"import {mod}"] = secs
    for name, t0, t1, _ in probe["events"]:
        out[name] = out.get(name, 0.0) + (t1 - t0)
    for name, (n, secs) in probe["jax_events_s"].items():
        out[f"jax: {name.rsplit('/', 1)[-1]} ({n} events)"] = secs
    out["probe total (after interpreter start)"] = probe["probe_total_s"]
    return out


_READ = """
import glob, json, os, pickle, sys, time
import jax
jax.config.update("jax_enable_x64", True)
from jax.experimental import serialize_executable
from jax._src.lax import linalg
linalg.initialize_lapack()
out = []
for f in sorted(glob.glob(os.path.join(sys.argv[1], "*.xla")), key=os.path.getsize):
    payload, in_tree, out_tree, _ = pickle.loads(open(f, "rb").read())
    c, t = time.process_time(), time.perf_counter()
    serialize_executable.deserialize_and_load(payload, in_tree, out_tree)
    out.append({"bytes": os.path.getsize(f), "read_s": time.perf_counter() - t, "read_cpu_s": time.process_time() - c})
print(json.dumps(out))
"""


def _read_executables(folder: Path) -> list[dict]:
    """Size and load time (wall and CPU) of every stored executable in ``folder``, each read in
    one fresh process (what a warm process pays to read them, without running them)."""
    done = subprocess.run([sys.executable, "-c", _READ, str(folder / "programs")], capture_output=True, text=True)
    return json.loads(done.stdout.strip().splitlines()[-1]) if done.returncode == 0 else []


def _estimates(path: Path) -> dict:
    """n1, mu_t and the reduced chi-square of a calibration JSON (the trees' results compared)."""
    d = json.loads(path.read_text())
    p = d["parameters"]

    def v(k):
        return p[k]["value"] if isinstance(p[k], dict) else p[k]

    return {"n1": v("n1"), "mu_t_per_m": v("mu_s_per_m") + v("mu_a_per_m"), "reduced_chi2": d["reduced_chi2"],
            "steps": d["steps"], "stderr_n1": p["n1"].get("stderr") if isinstance(p["n1"], dict) else None}


def _git(tree: Path) -> str:
    done = subprocess.run(["git", "-C", str(tree), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run(["git", "-C", str(tree), "status", "--porcelain", "--", "tofjax"], capture_output=True, text=True)
    return done.stdout.strip() + ("+uncommitted" if dirty.stdout.strip() else "")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True)
    p.add_argument("--scene", default="optoskin")
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--trees", default=f"this={ROOT}", help="label=path,... source trees to compare (default: this one)")
    p.add_argument("--modes", default=",".join(MODES), help=f"among {', '.join(MODES)}")
    p.add_argument("--profile", action="store_true", help="also profile each tree's warm process stage by stage")
    p.add_argument("--compare", metavar="REF", help="another checkout: --trees base=REF,this=<this tree> --modes warm")
    p.add_argument("--json", default="first_fit.json", help="name of the JSON written to --out")
    a = p.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    if a.compare:
        a.trees = f"base={a.compare},this={ROOT}"
        if a.modes == ",".join(MODES):
            a.modes = "warm"
    trees = {k: Path(v).resolve() for k, v in (t.split("=", 1) for t in a.trees.split(","))}
    modes = [m for m in a.modes.split(",") if m]
    if set(modes) - set(MODES):
        raise SystemExit(f"--modes: unknown {sorted(set(modes) - set(MODES))}")
    tofjax = [sys.executable, "-m", "tofjax.cli"]
    times = {t: {m: [] for m in modes} for t in trees}
    cpu = {t: {m: [] for m in modes} for t in trees}
    loads: list[float] = []
    profiles: dict[str, list[dict]] = {t: [] for t in trees}
    # without cold runs to time, each tree's folder is filled once and kept for every repeat
    keep = "cold" not in modes
    with tempfile.TemporaryDirectory() as tmp:
        cap = Path(tmp) / "baseline.h5"
        _run(tofjax + ["simulate", a.scene, "--frames", str(a.frames), "--out", str(cap)], "0")
        fit_args = ["calibrate", str(cap), "--out", str(Path(tmp) / "cal.json"), "--overwrite"]
        fit = tofjax + fit_args
        results: dict[str, dict] = {}
        executables: dict[str, list] = {}
        if keep and ("warm" in modes or a.profile):
            for label, tree in trees.items():
                fill = _run(fit, str(Path(tmp) / f"cache-{label}"), tree=tree)
                print(f"{label}: cache filled by a cold run ({fill:.1f} s, not counted)", flush=True)
                executables[label] = _read_executables(Path(tmp) / f"cache-{label}")
        for r in range(a.repeats):
            for label, tree in trees.items():
                folder = Path(tmp) / (f"cache-{label}" if keep else f"cache-{label}-{r}")
                t = times[label]
                if "off" in modes:
                    t["off"].append(_run(fit, "0", tree=tree))
                    cpu[label]["off"].append(CPU[-1])
                if not keep and ("cold" in modes or "warm" in modes or a.profile):
                    cold = _run(fit, str(folder), tree=tree)
                    if "cold" in modes:
                        t["cold"].append(cold)
                        cpu[label]["cold"].append(CPU[-1])
                if "warm" in modes:
                    t["warm"].append(_run(fit, str(folder), tree=tree))
                    cpu[label]["warm"].append(CPU[-1])
                if a.profile:
                    probe = Path(tmp) / "probe.json"
                    _run([sys.executable, str(PROBE), str(probe)] + fit_args, str(folder), tree=tree)
                    profiles[label].append(_stages(json.loads(probe.read_text())))
                if "warm_xla_only" in modes:
                    xla_only = Path(tmp) / f"xla-{label}-{r}"
                    _run(fit, str(xla_only), store="0", tree=tree)
                    t["warm_xla_only"].append(_run(fit, str(xla_only), store="0", tree=tree))
                    cpu[label]["warm_xla_only"].append(CPU[-1])
                    shutil.rmtree(xla_only, ignore_errors=True)
                results[label] = _estimates(Path(tmp) / "cal.json")
                entries = sum(1 for _ in folder.rglob("*") if _.is_file())
                if not keep:
                    shutil.rmtree(folder, ignore_errors=True)
                loads.append(os.getloadavg()[0])
                print(f"repeat {r} {label}: " + ", ".join(f"{m} {v[-1]:.2f} s" for m, v in t.items() if v)
                      + f" ({entries} cache files), load {loads[-1]:.1f}", flush=True)
    med = {lab: {m: statistics.median(v) for m, v in t.items() if v} for lab, t in times.items()}
    med_cpu = {lab: {m: statistics.median(v) for m, v in t.items() if v} for lab, t in cpu.items()}
    machine = {"platform": platform.platform(), "cpus": os.cpu_count(), "python": sys.version.split()[0],
               "what": "the shared 2-core CPU VM, loaded by other sessions (see load_average_1min)",
               "PYTHONDONTWRITEBYTECODE": os.environ.get("PYTHONDONTWRITEBYTECODE", "")}
    report = {
        "what": "wall time of a whole `tofjax calibrate` process on a simulated baseline",
        "data": "simulated (tofjax simulate)",
        "scene": a.scene,
        "frames": a.frames,
        "repeats": a.repeats,
        "trees": {lab: {"path": str(tree), "commit": _git(tree)} for lab, tree in trees.items()},
        "seconds": times,
        "median_s": med,
        "cpu_seconds": cpu,
        "median_cpu_s": med_cpu,
        "load_average_1min": os.getloadavg()[0],
        "load_average_1min_per_run": loads,
        "command": " ".join([Path(sys.argv[0]).name] + (sys.argv[1:] if argv is None else list(argv))),
        "machine": machine,
    }
    for lab, m in med.items():
        if "warm" in m and "off" in m:
            report.setdefault("warm_over_off", {})[lab] = m["warm"] / m["off"]
        if "warm" in m and "warm_xla_only" in m:
            report.setdefault("warm_over_warm_xla_only", {})[lab] = m["warm"] / m["warm_xla_only"]
        if "cold" in m and "off" in m:
            report.setdefault("cold_over_off", {})[lab] = m["cold"] / m["off"]
    labels = list(trees)
    if len(labels) > 1:
        ref = labels[0]
        report["ratio_to_" + ref] = {
            lab: {m: med[lab][m] / med[ref][m] for m in med[lab] if m in med[ref]} for lab in labels[1:]
        }
        report["cpu_ratio_to_" + ref] = {
            lab: {m: med_cpu[lab][m] / med_cpu[ref][m] for m in med_cpu[lab] if m in med_cpu[ref]} for lab in labels[1:]
        }
        # the same ratio run by run (the trees alternate, so each pair shared the machine's load)
        report["paired_ratio_median_to_" + ref] = {
            lab: {m: statistics.median(x / y for x, y in zip(times[lab][m], times[ref][m]))
                  for m in times[lab] if times[lab][m] and times[ref].get(m)} for lab in labels[1:]
        }
    if executables:
        report["stored_executables"] = executables  # per tree: bytes, read_s, read_cpu_s of each (one process)
    if results:
        report["estimates"] = results
        if len(labels) > 1:
            ref = results[labels[0]]
            report["estimates_relative_difference_to_" + labels[0]] = {
                lab: {k: abs(r[k] - ref[k]) / abs(ref[k]) for k in ("n1", "mu_t_per_m", "reduced_chi2", "stderr_n1")
                      if r.get(k) is not None and ref.get(k)} for lab, r in results.items() if lab != labels[0]
            }
    if len(labels) == 1:  # the layout of earlier runs: one tree, flat
        report["seconds"], report["median_s"] = times[labels[0]], med[labels[0]]
        report["cpu_seconds"], report["median_cpu_s"] = cpu[labels[0]], med_cpu[labels[0]]
        for k in ("warm_over_off", "warm_over_warm_xla_only", "cold_over_off"):
            if k in report:
                report[k] = report[k][labels[0]]
    from tofjax.outputs import atomic_write_text

    atomic_write_text(out / a.json, json.dumps(report, indent=2))
    for lab, m in med.items():
        print(f"median {lab}: " + ", ".join(f"{k} {v:.2f} s (CPU {med_cpu[lab][k]:.2f} s)" for k, v in m.items()))
    for k in [k for k in report if k.startswith(("ratio_to_", "cpu_ratio_to_", "paired_ratio"))]:
        print(f"{k}: {report[k]}")
    if a.profile:
        stages = {}
        for lab, runs in profiles.items():
            names = list(dict.fromkeys(k for run in runs for k in run))
            stages[lab] = {k: statistics.median(run.get(k, 0.0) for run in runs) for k in names}
        prof = {
            "what": "stages of a warm `tofjax calibrate` process (median seconds over repeats), from "
                    "experiments/_first_fit_probe.py; nested stages are included in their parents "
                    "(the stored programs' load inside the timing, envelope and joint-fit stages)",
            "data": "simulated (tofjax simulate)",
            "scene": a.scene,
            "frames": a.frames,
            "repeats": a.repeats,
            "trees": report["trees"],
            "median_s": stages,
            "warm_process_median_s": {lab: med[lab].get("warm") for lab in med},
            "load_average_1min": os.getloadavg()[0],
            "machine": machine,
        }
        atomic_write_text(out / a.json.replace(".json", "_profile.json"), json.dumps(prof, indent=2))
        for lab, st in stages.items():
            print(f"profile {lab}: " + ", ".join(f"{k} {v:.2f}" for k, v in st.items()))
    print(f"wrote {out / a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
