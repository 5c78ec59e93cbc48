"""Two checkouts side by side on what the CLI's compile costs: cold calibration (compile + first fit),
warm fit, time per step, the model's value-and-gradient compile and call, and the answer.

Each tree (``--base``: a checkout of the commit before, e.g. ``git archive REV | tar -x -C /tmp/base``;
and this worktree) runs ``experiments/cpu_opt_level.py``'s worker (the measurements of
``experiments/cpu_emitters.py``: float64, the default scene's simulated 100-frame baseline of seed
1000) in fresh processes with the CLI's XLA flags (elemental CPU emitters, XLA's default level), no
program store and no compilation cache (cold), alternating base / this tree ``--rounds`` times with
the order rotated. Medians, and the per-round ratios this tree / base. All data **simulated**.

    python experiments/tree_compare.py --base /tmp/base --label "before (REV)" --out docs/results/NAME.json
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
sys.path.insert(0, str(ROOT / "experiments"))

from cpu_opt_level import MEASURES, VARIANTS, describe, run_worker  # noqa: E402  (the CLI's flags, the worker and its measures)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--base", required=True, help="a checkout of the tree before the change")
    ap.add_argument("--label", default="before", help="what the base is (written to the JSON)")
    ap.add_argument("--out", required=True, help="JSON file to write")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--warm", type=int, default=5, help="warm fits per process (median)")
    a = ap.parse_args(argv)
    base = Path(a.base)
    if not (base / "experiments" / "cpu_opt_level.py").is_file():
        ap.error(f"--base {base}: not a tofjax checkout with experiments/cpu_opt_level.py")
    if a.rounds < 1 or a.warm < 1:
        ap.error("--rounds and --warm must be >= 1")
    trees = {"before": base, "after": ROOT}
    runs = {k: [] for k in trees}
    for r in range(a.rounds):
        for k in (("before", "after") if r % 2 == 0 else ("after", "before")):
            rec = run_worker(k, VARIANTS["default"], a.warm, trees[k])
            runs[k].append(rec)
            print(describe(r, k, rec), flush=True)
    med = {k: {m: statistics.median(x[m] for x in runs[k]) for m in MEASURES} for k in trees}
    ratios = {m: [x[m] / y[m] for x, y in zip(runs["after"], runs["before"])] for m in MEASURES}
    sys.path.insert(0, str(ROOT))
    import jax

    from tofjax.outputs import atomic_write_text

    result = {
        "what": "two checkouts side by side with the CLI's XLA flags: cold calibration (compile + first fit), warm fit and "
                "its time per step, model value-and-grad compile and call; fresh process each, alternating",
        "simulated": True, "scene": "default", "frames": 100, "seed": 1000, "xla_flags": VARIANTS["default"],
        "before": a.label, "machine": f"{platform.node()} {platform.machine()}, {os.cpu_count()} cores; jax {jax.__version__}",
        "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()), "rounds": a.rounds, "warm_fits": a.warm,
        "median": med, "ratio_after_over_before_per_round": ratios,
        "ratio_median": {m: statistics.median(x) for m, x in ratios.items()},
        "n1_max_abs_difference": max(abs(x["n1"] - y["n1"]) for x, y in zip(runs["after"], runs["before"])),
        "runs": runs,
    }
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(Path(a.out), json.dumps(result, indent=1) + "\n")
    for m in MEASURES:
        print(f"{m:20s} before {med['before'][m]:.4g}  after {med['after'][m]:.4g}  ratio {result['ratio_median'][m]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
