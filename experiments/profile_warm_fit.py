"""Where a warm ``Calibrator.fit`` spends its time (issue 13: warm fit <= 50 ms).

Simulates one default-scene baseline (seed 1000, as ``bench_fit.py``), compiles the calibration,
times ``--repeats`` warm fits (median), then runs ``--profiled`` more under cProfile and writes,
per named stage of :func:`tofjax.fit.calibrate.calibrate` (the start's timing and envelope, the
fits, the slow-tail score test, the result's assembly), its cumulative seconds per fit. On an
accelerator jitted calls return before the device is done, so a stage's time lands where its
result is first read on the host (the stage itself, since each stage reads its result). All data
**simulated**.

    python experiments/profile_warm_fit.py --out docs/results/profile_warm_fit_cpu.json [--pulse-tails auto]
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import os
import platform
import pstats
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: (label, module file suffix, function name) of the stages reported
STAGES = (
    ("calibrate (all)", "fit/calibrate.py", "calibrate"),
    ("starts (timing, envelope)", "fit/calibrate.py", "_starts"),
    ("start: timing", "fit/_start.py", "timing_start"),
    ("start: envelope", "fit/_start.py", "envelope_candidates"),
    ("fits from the starts (run, read, assemble)", "fit/calibrate.py", "_fit_starts"),
    ("fits: run_fit (dispatch; on a CPU the run)", "fit/calibrate.py", "run_fit"),
    ("slow-tail score test", "fit/calibrate.py", "_tail_test"),
    ("result assembly", "fit/calibrate.py", "_assemble"),
    ("n1 held at timing (refit)", "fit/calibrate.py", "_hold_n1_at_timing"),
)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="JSON file to write")
    ap.add_argument("--scene", default="optoskin")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--profiled", type=int, default=5)
    ap.add_argument("--pulse-tails", choices=("1", "2", "auto"), default="auto")
    a = ap.parse_args(argv)
    if a.repeats < 1 or a.profiled < 1 or a.frames < 1:
        ap.error("--repeats, --profiled and --frames must be >= 1")
    sys.path.insert(0, str(ROOT))
    os.environ.setdefault("TOFJAX_PROGRAM_STORE", "0")
    import jax

    from tofjax import enable_x64

    from tofjax.compile_cache import use_fast_cpu_compiler  # noqa: E402
    use_fast_cpu_compiler()  # the CLI's CPU compiler (before JAX's backend starts)
    enable_x64()
    from tofjax.fit import Calibrator, FitConfig
    from tofjax.outputs import atomic_write_text
    from tofjax.scene import load_scene
    from tofjax.simulate import simulate

    scene = load_scene(a.scene)
    cap = simulate(scene, a.frames, seed=1000)
    tails = a.pulse_tails if a.pulse_tails == "auto" else int(a.pulse_tails)
    cal = Calibrator(scene, FitConfig(pulse_tails=tails))
    t = time.perf_counter()
    res = cal.fit(cap)
    first = time.perf_counter() - t
    print(f"first fit (compiles) {first:.1f} s, {res.steps} steps, {res.result}", flush=True)
    times = []
    for _ in range(a.repeats):
        t = time.perf_counter()
        cal.fit(cap)
        times.append(time.perf_counter() - t)
    print(f"warm fit median {statistics.median(times) * 1e3:.1f} ms (min {min(times) * 1e3:.1f})", flush=True)
    prof = cProfile.Profile()
    prof.enable()
    for _ in range(a.profiled):
        cal.fit(cap)
    prof.disable()
    st = pstats.Stats(prof)
    stages = {}
    for label, suffix, name in STAGES:
        cum = sum(v[3] for (f, _, fn), v in st.stats.items() if fn == name and f.replace("\\", "/").endswith(suffix))
        stages[label] = cum / a.profiled
    buf = io.StringIO()
    pstats.Stats(prof, stream=buf).sort_stats("cumulative").print_stats(40)
    out = {
        "what": "warm Calibrator.fit: median wall time and a cProfile breakdown per stage (issue 13: warm fit <= 50 ms)",
        "simulated": True, "scene": a.scene, "frames": a.frames, "pulse_tails": a.pulse_tails,
        "machine": f"{platform.node()} {platform.machine()}, {os.cpu_count()} cores; backend {jax.default_backend()} "
                   f"({jax.devices()[0].device_kind}); jax {jax.__version__}",
        "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
        "steps": res.steps, "result": res.result, "chosen_pulse_tails": getattr(res, "pulse_tails", None),
        "first_fit_s": first, "warm_fit_s": statistics.median(times), "warm_fit_all_s": times,
        "profiled_fits": a.profiled, "stage_s_per_fit": stages,
        "profile_top_cumulative": buf.getvalue().splitlines()[:70],
    }
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(Path(a.out), json.dumps(out, indent=1) + "\n")
    for k, v in stages.items():
        print(f"  {k:32s} {v * 1e3:8.1f} ms per fit", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
