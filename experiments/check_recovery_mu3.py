"""Check: the mu_s = 3 /m corner of the recovery grid (configs/studies/recovery_mu3.toml), one
fit at a time (``Calibrator.fit``) instead of one vmapped call, so that it runs in parts of
under 10 minutes on the shared 2-core VM (the vmapped program alone took longer than that to
compile at load 16-22). Same baselines as ``experiments/study_recovery.py`` (``simulate_item``),
same default fit config. Writes ``recovery_mu3_single.json`` after every point. **Simulated**.

    python experiments/check_recovery_mu3.py --out out/rec_mu3 [--points 0 1 2] [--overwrite]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import tofjax
from tofjax.config import from_dict, load_toml
from tofjax.fit.calibrate import Calibrator
from tofjax.outputs import atomic_write_text, check_output
from tofjax.scene import load_scene
from tofjax.study_cli import RecoveryStudy, recovery_point, simulate_item


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default="configs/studies/recovery_mu3.toml")
    ap.add_argument("--out", default="out/rec_mu3")
    ap.add_argument("--points", type=int, nargs="+", help="only these grid points (indices into the config's items)")
    ap.add_argument("--overwrite", action="store_true")
    args = ap.parse_args(argv)
    tofjax.enable_x64()
    config = from_dict(RecoveryStudy, load_toml(args.config))
    path = check_output(Path(args.out) / "recovery_mu3_single.json", overwrite=args.overwrite)
    nominal = load_scene(config.scene)
    cal = Calibrator(nominal)
    items = config.items()
    keep = [i for i in range(len(items)) if args.points is None or i in args.points]
    rows = []
    for i in keep:
        t = time.perf_counter()
        res = cal.fit(simulate_item(config, nominal, items[i]))
        fit = {p: float(res.values[p]) for p in ("n1", "mu_s_per_m", "mu_a_per_m")}
        fit |= {"converged": res.converged, "result": res.result, "reduced_chi2": res.reduced_chi2,
                "crosstalk_width_s": float(res.params.crosstalk_width_s), "seconds": time.perf_counter() - t}
        row = recovery_point(items[i][2], [fit]) | {"item": i}
        rows.append(row)
        print(f"point {i} truth {row['truth']}: {res.result} n1 bias {row['bias']['n1']:+.2e} mu_t bias {row['bias']['mu_t']:+.4f} "
              f"chi2 {res.reduced_chi2:.3f} ({fit['seconds']:.0f} s)", flush=True)
        atomic_write_text(path, json.dumps({
            "study": "parameter recovery, mu_s = 3 /m corner, one fit at a time",
            "data": "simulated (tofjax.simulate)",
            "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, CPU only, shared with other agents (loaded)",
            "load_average": list(os.getloadavg()),
            "config": vars(config) if not hasattr(config, "__dataclass_fields__") else {k: getattr(config, k) for k in config.__dataclass_fields__},
            "points": rows,
        }, indent=2))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
