"""Why a warm calibration takes 20-60 Levenberg-Marquardt steps: the amplitude near-gauge (issue 13).

With a gain per (sensor, zone) profiled out, the guide's light scales as a whole against the gains: the
interface backscatter ``ib``, the far-edge reflectance ``R`` and the volume backscatter (through ``mu_s``
at fixed ``mu_s + mu_a``) can all grow by one factor while every gain shrinks by it, and the histograms
hardly change. Only second-order effects of ``mu_s`` (and ``R``'s bound at 1) break that symmetry. The
fit's last tens of steps crawl along this nearly flat, curved valley (consecutive steps parallel), each
gaining a tenth of what the Gauss-Newton model says is left. This study measures the valley and the
solver levers tofjax has against it, on the default scene's baselines:

- the Laplace correlations of ``ib``, ``R``, ``mu_s`` and the zones' gains at the default fit's optimum, and
  each coordinate's data share of its Laplace variance (``CalibrationResult.data_share``);
- the default solver against three variants, side by side (round robin, each fit warm, median of
  ``--rounds``): geodesic acceleration (``FitConfig.geodesic``), three trial dampings per step
  (``MarquardtLM(lambda_trials=(1e-2, 1, 10))``), and ``ib`` held at the scene's value (the gauge
  removed; not a remedy: it holds a parameter), with steps, reduced chi-square, and how far each
  variant's end point lies from the default's in the default's Laplace standard errors.

``--monte-carlo``: also the contrast with the guided optics, on the Monte Carlo's baseline of
``eval_mc_data.py`` (64 runs, 1x exposure, 10 frames): there the multiple-scattering term ties mu_s's scale
and the gauge is broken; recorded are the data shares and the calibrated gains against the Monte Carlo's.

    python experiments/fit_valley.py --out docs/results/fit_valley.json [--quick] [--rounds 3] [--monte-carlo]

Simulated data (own: ``tofjax.simulate``; independent: ``tests/indep_sim.py``); CPU. ``--quick``: one own
and one independent baseline of a 2-sensor, 3-zone scene, one round (the fast test's size).
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
from tofjax.fit import Calibrator, FitConfig, calibrate
from tofjax.fit.solve import MarquardtLM
from tofjax.outputs import OutputError, atomic_write_text, check_output

sys.path.insert(0, str(Path(__file__).resolve().parent))
from solver_secant import _baselines, _row  # noqa: E402

VARIANTS = ("default", "geodesic", "trials", "ib_held")
SHIFTED = ("n1", "mu_s_per_m", "mu_a_per_m", "end_reflectance")


def _fitters(scene, variants):
    """``{variant: fit(capture) -> CalibrationResult}`` for ``variants`` (the default among them), each with its
    own compiled fit."""
    cfg = FitConfig()
    configs = {"default": cfg, "geodesic": dataclasses.replace(cfg, geodesic=True),
               "ib_held": dataclasses.replace(cfg, free=tuple(k for k in cfg.free if k != "interface_backscatter_per_m"))}
    base = Calibrator(scene, cfg)
    fits = {v: (base if v == "default" else Calibrator(scene, configs[v])).fit for v in variants if v in configs}
    if "trials" in variants:
        trials = MarquardtLM(rtol=cfg.rtol, atol=cfg.atol, lambda_trials=(1e-2, 1.0, 10.0), secant=cfg.secant)
        fits["trials"] = lambda cap: calibrate(cap, base.config, scene=scene, solver=trials, problem=base.problem)
    return fits


def _correlations(res) -> dict:
    """The Laplace correlations of the amplitude near-gauge at ``res``'s optimum."""
    cov = np.asarray(res.covariance)
    idx = {k: i for i, k in enumerate(res.labels)}
    sd = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    corr = cov / sd[:, None] / sd[None, :]

    def c(a, b):
        return float(corr[idx[a], idx[b]])

    ib = "interface_backscatter_per_m"
    i_s, i_a = idx["mu_s_per_m"], idx["mu_a_per_m"]
    gains = [k for k in res.labels if k.startswith("gain[")]
    return {"ib_R": c(ib, "end_reflectance"), "ib_mu_s": c(ib, "mu_s_per_m"), "R_mu_s": c("end_reflectance", "mu_s_per_m"),
            "ib_gain_median": float(np.median([c(ib, g) for g in gains])) if gains else None,
            "relative_stderr": {k: float(res.stderr[k]) / abs(float(getattr(res.params, k)))
                                for k in (ib, "end_reflectance", "mu_s_per_m", "mu_a_per_m")},
            "mu_t_relative_stderr": float(np.sqrt(cov[i_s, i_s] + cov[i_a, i_a] + 2 * cov[i_s, i_a]))
                                    / float(res.params.mu_s_per_m + res.params.mu_a_per_m)}


def monte_carlo_contrast(exposure: float = 1.0, frames: int = 10) -> dict:
    """The guided optics' calibration of ``eval_mc_data.py``'s Monte Carlo baseline: data shares and gains."""
    import eval_mc_data as E

    scene, expected, _ = E.calibration_baseline(exposure=exposure)
    cap = E._capture(scene, expected, frames, 0, "simulated (monte carlo)")
    res = Calibrator(scene, FitConfig(optics="guided")).fit(cap)
    truth = exposure * np.asarray(scene.gains(), float)
    return {"data": f"tofjax.mc, 64 runs of 25,000 packets per sensor, {exposure:g}x exposure, {frames} frames",
            "optics": "guided", "result": res.result, "reduced_chi2": float(res.reduced_chi2),
            "data_share": dict(res.data_share),
            "gain_over_truth_per_sensor": (np.asarray(res.values["gain"]).mean(-1) / truth).tolist(),
            "correlations": _correlations(res)}


def run(out: Path, quick: bool = False, rounds: int = 3, overwrite: bool = False, progress: bool = True,
        variants: tuple[str, ...] = VARIANTS, monte_carlo: bool = False) -> dict:
    path = check_output(out, overwrite=overwrite)
    variants = ("default",) + tuple(v for v in variants if v != "default")
    fitters: dict = {}
    rows = []
    for group, name, scene, cap, n1, mu_t in _baselines(quick):
        if group == "grid":
            break
        if id(scene) not in fitters:
            fitters[id(scene)] = _fitters(scene, variants)
        fits = fitters[id(scene)]
        results, seconds = {}, {v: [] for v in variants}
        for v in variants:
            results[v] = fits[v](cap)  # the first call compiles
        for _ in range(rounds):
            for v in variants:  # round robin: the machine's load moves every variant alike
                t = time.perf_counter()
                results[v] = fits[v](cap)
                seconds[v].append(time.perf_counter() - t)
        ref = results["default"]
        row = {"set": group, "baseline": name, "correlations": _correlations(ref), "data_share": dict(ref.data_share)}
        for v in variants:
            r = results[v]
            row[v] = _row(r, float(np.median(seconds[v])), n1, mu_t) | {
                "shift_in_stderr": {k: (float(getattr(r.params, k)) - float(getattr(ref.params, k))) / float(ref.stderr[k])
                                    for k in SHIFTED},
                "chi2_minus_default": float(np.sum(np.asarray(r.residuals) ** 2) - np.sum(np.asarray(ref.residuals) ** 2)),
                "gain_data_share": r.data_share.get("gain"),
                "gain_over_default": float(np.median(np.asarray(r.values["gain"]) / np.asarray(ref.values["gain"]))),
                # tofjax's own data are made with the scene's gains (one per sensor): the fitted ones against them
                "gain_over_truth": float(np.median(np.asarray(r.values["gain"]) / np.asarray(scene.gains(), float)[:, None]))
                if name.startswith("own") else None}
        rows.append(row)
        if progress:
            cr = row["correlations"]
            print(f"{name:18s} corr ib-R {cr['ib_R']:+.3f} ib-mu_s {cr['ib_mu_s']:+.3f}  " +
                  "  ".join(f"{v} {row[v]['steps']:3d} steps {row[v]['seconds']:.3f} s" for v in variants), flush=True)
    summary = {}
    for v in variants:
        steps = [r[v]["steps"] for r in rows]
        ratio = [r[v]["seconds"] / r["default"]["seconds"] for r in rows]
        shift = [max(abs(x) for x in r[v]["shift_in_stderr"].values()) for r in rows]
        summary[v] = {"steps": steps, "steps_total": int(sum(steps)), "seconds_ratio_to_default_median": float(np.median(ratio)),
                      "max_shift_in_stderr": float(max(shift)), "converged": int(sum(r[v]["converged"] for r in rows))}
    result = {
        "what": "the calibration's amplitude near-gauge (interface backscatter, edge reflectance and mu_s against the zones' gains) "
                "and the solver variants against it, side by side on the default scene's baselines",
        "data": "simulated (own: tofjax.simulate; independent: tests/indep_sim.py)",
        "rounds": rounds,
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs ({platform.platform()}), CPU only, shared (loaded)",
        "load_average": list(os.getloadavg()),
        "tofjax": tofjax.__version__,
        "summary": summary,
        "fits": rows,
    }
    if monte_carlo:
        result["monte_carlo"] = monte_carlo_contrast()
        if progress:
            mc = result["monte_carlo"]
            print("Monte Carlo, guided optics: data shares", {k: round(v, 3) for k, v in mc["data_share"].items()},
                  "gains / truth", np.round(mc["gain_over_truth_per_sensor"], 3), flush=True)
    atomic_write_text(path, json.dumps(result, indent=2))
    return result


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("out/fit_valley.json"))
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--rounds", type=int, default=None, help="timed warm fits per variant and baseline (default 3; 1 with --quick)")
    ap.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated, of {', '.join(VARIANTS)} (default: all)")
    ap.add_argument("--monte-carlo", action="store_true", help="also the guided optics on the Monte Carlo's baseline (minutes)")
    ap.add_argument("--overwrite", action="store_true")
    args = ap.parse_args(argv)
    variants = tuple(v.strip() for v in args.variants.split(",") if v.strip())
    bad = [v for v in variants if v not in VARIANTS]
    if bad or not variants:
        ap.error(f"--variants: unknown {', '.join(bad) or '(none given)'}; choose from {', '.join(VARIANTS)}")
    rounds = args.rounds if args.rounds is not None else (1 if args.quick else 3)
    if rounds < 1:
        ap.error("--rounds must be >= 1")
    try:
        check_output(args.out, overwrite=args.overwrite)
    except OutputError as e:
        ap.error(str(e))
    tofjax.use_fast_cpu_compiler()
    tofjax.enable_x64()
    res = run(args.out, quick=args.quick, rounds=rounds, overwrite=args.overwrite, variants=variants, monte_carlo=args.monte_carlo)
    print(json.dumps(res["summary"], indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
