"""Is the two-tail pulse the cause of the straggler fits? The default scene states no slow tail
(``pulse_slow_weight = 0``), so its **simulated** baselines lie on the singular set of the default
two-tail fit (weight 0 with any slow time constant, or the slow tail equal to the fast one with
any weight). This runs ``Calibrator(scene, FitConfig(pulse_tails=N)).fit`` (the whole calibration,
its own start) on the given seeds and records steps, result, warm time and the estimates.

    TOFJAX_PROGRAM_STORE=0 python experiments/straggler_tails.py --tails 1 --out docs/results/straggler_tails_1.json
    TOFJAX_PROGRAM_STORE=0 python experiments/straggler_tails.py --tails 2 --out docs/results/straggler_tails_2.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tails", type=int, choices=[1, 2], required=True)
    p.add_argument("--seeds", type=int, nargs="*", default=[2000, 2011, 2014, 2031, 2033, 2036, 2001, 2004])
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)
    os.environ.setdefault("TOFJAX_PROGRAM_STORE", "0")
    import jax

    jax.config.update("jax_enable_x64", True)
    from tofjax.fit.calibrate import Calibrator, FitConfig
    from tofjax.scene import load_scene
    from tofjax.simulate import simulate

    scene = load_scene("optoskin")
    cal = Calibrator(scene, FitConfig(pulse_tails=a.tails))
    rows = []
    for s in a.seeds:
        cap = simulate(scene, a.frames, seed=s)
        t = time.perf_counter()
        r = cal.fit(cap)
        dt = time.perf_counter() - t
        p_ = r.params
        row = {"seed": s, "steps": int(r.steps), "result": r.result, "converged": bool(r.converged), "fit_s": dt,
               "n1": float(p_.n1), "n1_stderr": float(r.stderr["n1"]), "mu_t": float(p_.mu_s_per_m + p_.mu_a_per_m),
               "reduced_chi2": float(r.reduced_chi2),
               "pulse": {k: float(getattr(p_, k)) for k in ("pulse_tail_s", "pulse_slow_tail_s", "pulse_slow_weight")}}
        rows.append(row)
        print(f"[straggler_tails] tails {a.tails} seed {s}: {row['steps']} steps {row['result']} {dt:.2f} s n1 {row['n1']:.6f}",
              file=sys.stderr, flush=True)
    out = {"what": f"Calibrator.fit with pulse_tails = {a.tails} on the default optoskin scene (which states no slow tail)",
           "data": f"simulated: tofjax.simulate.simulate(load_scene('optoskin'), {a.frames}, seed=s), own model",
           "command": "TOFJAX_PROGRAM_STORE=0 python experiments/straggler_tails.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "machine": f"{platform.node()} ({os.cpu_count()} CPU cores, shared); load average at the end {os.getloadavg()}",
           "note": "fit_s includes the first call's compile for the first seed", "fits": rows}
    path = Path(a.out) if Path(a.out).is_absolute() else ROOT / a.out
    path.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
