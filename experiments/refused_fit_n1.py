"""A refused calibration and the timing estimate of n1: which n1 does it keep? (issues 13 and 14)

Where a calibration is refused for its chi-square (the model does not describe the capture), amplitude errors can pull
n1, and the calibration may refit with n1 held at the timing estimate (``fit.calibrate._hold_n1_at_timing``). This
study calibrates the 64x Monte Carlo baseline of ``experiments/eval_mc_data.py`` (its 64 cached runs, 10 frames, seed 0;
reduced chi-square about 5.5, refused) at each ``--quadratures`` value, each in a process of its own, and reports the
timing estimate, every start's fit (steps, result, reduced chi-square, n1) and whether n1 was held, with the result's
reduced chi-square and n1 and mu_s + mu_a errors. Run it on two checkouts to compare their rules side by side
(``--label``). All data **simulated**; 2-4 minutes per quadrature on the 2-core VM.

    python experiments/refused_fit_n1.py --out docs/results/refused_fit_n1.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path


def calibrate_one(quadrature: int) -> dict:
    """The eval's 64x Monte Carlo calibration at ``quadrature`` time nodes per bin (in this process)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import eval_mc_data as ev

    scene, expected, _ = ev.calibration_baseline(exposure=64.0)
    cap = ev._capture(scene, expected, 10, 0, "simulated (monte_carlo)")
    fig, res = ev.calibrate_capture(scene, cap, None, "guided", quadrature=quadrature)  # the eval's figures
    return {"quadrature": quadrature, "result": fig["result"], "steps_of_the_kept_fit": fig["steps"],
            "seconds_with_compile": fig["seconds"], "reduced_chi2": fig["reduced_chi2_photon_noise"],
            "n1_rel_error": fig["n1_rel_error"], "mu_t_rel_error": fig["mu_t_rel_error"],
            "n1_held_at_timing": "n1" not in res.free, "stages": fig["stages"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="JSON file to write")
    ap.add_argument("--quadratures", default="2,4", help="time nodes per bin to calibrate at (comma-separated)")
    ap.add_argument("--label", default="", help="what this checkout is (kept in the JSON)")
    ap.add_argument("--overwrite", action="store_true")
    ap.add_argument("--one", type=int, help=argparse.SUPPRESS)  # one quadrature in this process; JSON to stdout
    args = ap.parse_args(argv)
    if args.one is not None:
        import jax

        jax.config.update("jax_enable_x64", True)
        print(json.dumps(calibrate_one(args.one)))
        return 0
    out_path = Path(args.out)
    if out_path.exists() and not args.overwrite:
        print(f"error: {out_path} exists (--overwrite to replace it)", file=sys.stderr)
        return 2
    try:
        quads = [int(q) for q in args.quadratures.split(",")]
    except ValueError:
        quads = []
    if not quads or any(not 1 <= q <= 16 for q in quads):
        print(f"error: --quadratures: expected integers in 1..16 separated by commas, got {args.quadratures!r}",
              file=sys.stderr)
        return 2
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).resolve().parent).stdout.strip()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import eval_mc_data as ev

    out = ev.study_header("a refused calibration's n1 against the timing estimate",
                          "simulated (tofjax's Monte Carlo; 64 runs of 25,000 packets per sensor, 64x, 10 frames)")
    out.update({"label": args.label, "commit": commit, "calibrations": []})
    for q in quads:
        row = ev.run_in_own_process(__file__, ["--out", os.devnull, "--one", str(q)])
        out["calibrations"].append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "stages"}), flush=True)
    ev.write_study(out, out_path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
