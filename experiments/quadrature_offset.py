"""The noise-free mu_t offset of tofjax's default quadrature alone: tofjax's own simulator at
quadrature 8 (its time discretisation converged), fitted with quadrature 2 (the default) and 4,
at mu_s + mu_a = 0.05 /m (``--mu-t``), n1 1.3 / 1.45 / 1.6 (the "own at quadrature 8" rows of
``study_mu_low.py --offset``, without the independent rigs, which that option builds too).

    PYTHONPATH=$PWD python experiments/quadrature_offset.py --out docs/results/quadrature_offset.json --label after
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

import tofjax
from tofjax.fit import Calibrator, FitConfig
from tofjax.outputs import atomic_write_text, check_output
from tofjax.scene import load_scene

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from study_calib_independent import ALBEDO, FULL, _scene, truth_scene  # noqa: E402
from study_mu_low import MU_T, _fit_row, _noise_free  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="out/quadrature_offset.json")
    ap.add_argument("--label", default="", help="which model version (e.g. before / after the node-spread fix)")
    ap.add_argument("--n1", type=float, nargs="+", default=[1.3, 1.45, 1.6])
    ap.add_argument("--fit-quadrature", type=int, nargs="+", default=[2, 4])
    ap.add_argument("--frames", type=int, default=960)
    ap.add_argument("--mu-t", type=float, default=MU_T, help="true mu_s + mu_a (/m)")
    ap.add_argument("--overwrite", action="store_true")
    args = ap.parse_args(argv)
    tofjax.enable_x64()
    from tofjax.model import ModelOptions
    from tofjax.simulate import expected_counts

    path = check_output(Path(args.out), overwrite=args.overwrite)
    t0 = time.perf_counter()
    nominal = _scene(load_scene("optoskin"), FULL["sensors"], FULL["zones"], FULL["bins"])
    cals = {q: Calibrator(nominal, dataclasses.replace(FitConfig(), quadrature=q)) for q in args.fit_quadrature}
    rows = {}
    for n1 in args.n1:
        truth = truth_scene(nominal, n1, args.mu_t)
        lam = np.asarray(expected_counts(truth, ModelOptions(quadrature=8)))
        cap = _noise_free(lam, truth, args.frames, "simulated (tofjax expected counts at quadrature 8), noise-free")
        rows[str(n1)] = {}
        for q, cal in cals.items():
            r = _fit_row(cal, cap, n1, args.mu_t)
            rows[str(n1)][f"fit quadrature {q}"] = r
            print(f"{args.label} n1 {n1} fit q{q}: mu_t {100 * r['mu_t_rel_error']:+.2f}% n1 {100 * r['n1_rel_error']:+.4f}% "
                  f"chi2 {r['reduced_chi2']:.4f} {r['seconds']:.1f}s", flush=True)
    res = {
        "study": "noise-free mu_t offset of the fit's quadrature alone: tofjax's own simulator at quadrature 8 fitted at quadrature 2 and 4",
        "label": args.label,
        "data": "simulated (tofjax expected counts at quadrature 8, noise-free, weighted as frames_weighting frames)",
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs ({platform.platform()}), CPU only, shared with other agents (loaded)",
        "load_average": list(os.getloadavg()),
        "truth": {"mu_t_per_m": args.mu_t, "albedo": ALBEDO, "frames_weighting": args.frames},
        "by_n1": rows,
        "seconds": time.perf_counter() - t0,
    }
    atomic_write_text(path, json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
