"""The calibration's Levenberg-Marquardt with and without NL2SOL's structured secant term
(``FitConfig.secant``, on by default).

On data the model did not make, the residuals at the optimum are not noise alone, and their
own curvature (``sum r_i H_i``, which the Gauss-Newton matrix ``J^T J`` leaves out) is as large
as ``J^T J``'s along the poorly determined directions: the default solver then overshoots along
them at every step, and the iterates zigzag (consecutive steps antiparallel, cosine -0.999)
toward the optimum for 75-131 steps on the independent simulator's default-scene baselines.
``MarquardtLM(secant=True)`` (``FitConfig.secant``) adds the secant estimate of that term
(Dennis, Gay and Welsch 1981), where it predicted the last step better than ``J^T J`` alone.
"plain" in the record is ``secant = false``.

This study fits the same baselines with both solvers, side by side (each baseline with one
solver, then the other, each fit twice and timed the second time, warm), and records per fit
the steps, result, n1 and mu_t errors, reduced chi-square and seconds:

- the default scene (OptoSkin, 6 sensors x 7 zones, 100 frames), 2 own baselines and 3 from
  ``tests/indep_sim.py``;
- the independent-calibration study's grid (``study_calib_independent.py``: 3 sensors, 7 zones,
  128 bins, 60 frames; n1 1.3 / 1.45 / 1.6 by mu_s + mu_a 0.05 / 0.5 / 2 / 4 /m, albedo 0.8),
  own and independent.

    python experiments/solver_secant.py --out docs/results/solver_secant.json [--quick]

Simulated data; CPU. ``--quick``: one own and one independent baseline of a 2-sensor, 3-zone
scene (the fast test's size).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

import tofjax
from tofjax.fit import Calibrator, FitConfig
from tofjax.outputs import OutputError, atomic_write_text, check_output
from tofjax.scene import default_scene, load_scene
from tofjax.simulate import simulate

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from indep_sim import CONVERGED, IndepRig  # noqa: E402
from indep_sim import simulate as simulate_independent  # noqa: E402
from study_calib_independent import FULL, QUICK, _scene, truth_scene  # noqa: E402

SOLVERS = ("plain", "secant")  # MarquardtLM without the secant term, and with it (the default since 2026-11-29)


def _fit(cal: Calibrator, cap) -> tuple[object, float]:
    cal.fit(cap)  # the first call compiles (once per solver and scene shape)
    t = time.perf_counter()
    res = cal.fit(cap)
    return res, time.perf_counter() - t


def _row(res, seconds, n1, mu_t) -> dict:
    steps = [int(s["steps"]) for s in res.stages if "steps" in s]
    f_n1, f_mu = float(res.params.n1), float(res.params.mu_s_per_m + res.params.mu_a_per_m)
    return {"result": res.result, "converged": bool(res.converged), "steps": int(sum(steps)), "steps_per_start": steps,
            "n1": f_n1, "mu_t_per_m": f_mu, "reduced_chi2": float(res.reduced_chi2), "seconds": seconds,
            "n1_rel_error": f_n1 / n1 - 1, "mu_t_rel_error": f_mu / mu_t - 1}


def _baselines(quick: bool):
    """``(set, name, scene, capture, truth n1, truth mu_t)`` for every baseline (``quick``: the
    independent-calibration study's quick scene, 2 sensors x 3 zones, one own and one independent
    baseline)."""
    if quick:
        p = QUICK
        nominal = _scene(load_scene("optoskin"), p["sensors"], p["zones"], p["bins"])
        n1, mu_t = p["n1"][0], p["mu_t"][0]
        truth = truth_scene(nominal, n1, mu_t)
        yield "quick", "own", nominal, simulate(truth, p["frames"], seed=100), n1, mu_t
        rig = IndepRig.from_scene(truth, seed=200)
        yield "quick", "independent", nominal, simulate_independent(rig, contacts=np.zeros((0, 3)), frames=p["frames"], seed=300), n1, mu_t
        return
    scene = default_scene()
    wg = scene.waveguide
    n1, mu = wg.n1, wg.mu_s_per_m + wg.mu_a_per_m
    yield "default_scene", "own 1000", scene, simulate(scene, 100, seed=1000), n1, mu
    yield "default_scene", "own 1001", scene, simulate(scene, 100, seed=1001), n1, mu
    for s in (0, 1, 2):
        rig = IndepRig.from_scene(scene, seed=s)
        yield "default_scene", f"independent {s}", scene, simulate_independent(rig, frames=100, seed=100 + s), n1, mu
    p = FULL
    nominal = _scene(load_scene("optoskin"), p["sensors"], p["zones"], p["bins"])
    for k, (n1, mu_t) in enumerate(itertools.product(p["n1"], p["mu_t"])):
        truth = truth_scene(nominal, n1, mu_t)
        yield "grid", f"own n1 {n1} mu_t {mu_t}", nominal, simulate(truth, p["frames"], seed=100 + k), n1, mu_t
        rig = IndepRig.from_scene(truth, seed=200 + k, options=CONVERGED)
        cap = simulate_independent(rig, contacts=np.zeros((0, 3)), frames=p["frames"], seed=300 + k)
        yield "grid", f"independent n1 {n1} mu_t {mu_t}", nominal, cap, n1, mu_t


def _summary(rows: list[dict]) -> dict:
    out = {}
    for sv in SOLVERS:
        steps = np.array([r[sv]["steps"] for r in rows])
        secs = np.array([r[sv]["seconds"] for r in rows])
        out[sv] = {"fits": len(rows), "converged": int(sum(r[sv]["converged"] for r in rows)),
                   "steps_median": float(np.median(steps)), "steps_total": int(steps.sum()), "steps_max": int(steps.max()),
                   "seconds_median": float(np.median(secs)), "seconds_total": float(secs.sum())}
    ratio = np.array([r["secant"]["seconds"] / r["plain"]["seconds"] for r in rows])
    sratio = np.array([r["secant"]["steps"] / max(r["plain"]["steps"], 1) for r in rows])
    dchi = np.array([r["secant"]["reduced_chi2"] - r["plain"]["reduced_chi2"] for r in rows])
    dn1 = np.array([abs(r["secant"]["n1"] / r["plain"]["n1"] - 1) for r in rows])
    out["paired"] = {"seconds_ratio_median": float(np.median(ratio)), "steps_ratio_median": float(np.median(sratio)),
                     "reduced_chi2_difference_min_max": [float(dchi.min()), float(dchi.max())],
                     "n1_relative_difference_max": float(dn1.max())}
    return out


def run(out: Path, quick: bool = False, overwrite: bool = False, progress: bool = True) -> dict:
    path = check_output(out, overwrite=overwrite)
    cals = {}
    rows = []
    for group, name, scene, cap, n1, mu_t in _baselines(quick):
        row = {"set": group, "baseline": name}
        for sv in SOLVERS:
            key = (sv, id(scene))
            if key not in cals:
                cals[key] = Calibrator(scene, FitConfig(secant=sv == "secant"))
            res, sec = _fit(cals[key], cap)
            row[sv] = _row(res, sec, n1, mu_t)
        rows.append(row)
        if progress:
            d, s = row["plain"], row["secant"]
            print(f"{name:34s} steps {d['steps']:4d} -> {s['steps']:4d}  {d['seconds']:6.3f} -> {s['seconds']:6.3f} s  "
                  f"chi2 {d['reduced_chi2']:.5f} -> {s['reduced_chi2']:.5f}  {d['result']} / {s['result']}", flush=True)
    result = {
        "what": "calibration fits with MarquardtLM's Gauss-Newton model alone (secant=False, plain) and with the structured secant term (secant=True), side by side",
        "data": "simulated (own: tofjax.simulate; independent: tests/indep_sim.py)",
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs ({platform.platform()}), CPU only, shared (loaded)",
        "load_average": list(os.getloadavg()),
        "tofjax": tofjax.__version__,
        "summary": {g: _summary([r for r in rows if r["set"] == g]) for g in sorted({r["set"] for r in rows})} | {"all": _summary(rows)},
        "fits": rows,
    }
    atomic_write_text(path, json.dumps(result, indent=2))
    return result


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("out/solver_secant.json"))
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--overwrite", action="store_true")
    args = ap.parse_args(argv)
    try:
        check_output(args.out, overwrite=args.overwrite)
    except OutputError as e:
        ap.error(str(e))
    tofjax.enable_x64()
    res = run(args.out, quick=args.quick, overwrite=args.overwrite)
    print(json.dumps(res["summary"], indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
