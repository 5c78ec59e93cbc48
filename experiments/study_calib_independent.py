"""Study: calibration on tofjax's own simulator and on an independent one, side by side.

For every true (n1, mu_t) of the grid a baseline is simulated twice: by ``tofjax.simulate``
("own") and by ``tests/indep_sim.py`` ("independent": NumPy, area sampling, a two-tail pulse,
an emission-time offset, per-zone gains, its own crosstalk and near field, an edge reflectance
that goes with the cosine of incidence, no multiple scattering). Both are calibrated from the
nominal scene (start and prior centre) with the same fit config. The independent baselines
are calibrated twice: from the nominal scene as it is (which states multiple scattering the
simulator does not make) and from the nominal scene stating ``multiple_scattering = 0`` (what
that simulator is documented to do: a user who knows their guide says so). Reported per column: convergence (``result == successful``), n1 and
mu_t = mu_s + mu_a errors, reduced chi-square, and the share within the targets (n1 within
1%, mu_t within 25%).

Then the batch speed-up: the same compiled fit run on ``batch`` captures as separate calls
and as one vmapped call (``tofjax.fit.fit_problem_batch``), from the same starts.

    python experiments/study_calib_independent.py --out out/calib_independent [--quick] [--overwrite]
        [--columns own,independent] [--n1 1.3 ...] [--mu-t 4 ...] [--no-batch] [--resolution converged|default]
    python experiments/study_calib_independent.py --merge out/a/calib_independent.json out/b/... --out out/all

The whole grid takes longer than one 10-minute command on the shared 2-core VM: run it in
parts (``--columns``, ``--n1``, ``--mu-t``, ``--no-batch``; each part writes its own JSON)
and ``--merge`` them (fits in grid order, summaries recomputed over the merged rows).

Writes ``calib_independent.json`` (copy it to ``docs/results/``). **Simulated** data.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import os
import platform
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import tofjax
from tofjax.fit import Calibrator, FitConfig, fit_problem, fit_problem_batch
from tofjax.outputs import atomic_write_text, check_output
from tofjax.fit._start import envelope_candidates, timing_start
from tofjax.fit.calibrate import _anchor, _data
from tofjax.scene import SensorModel, load_scene
from tofjax.simulate import simulate

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from indep_sim import CONVERGED, IndepOptions, IndepRig  # noqa: E402
from indep_sim import simulate as simulate_independent  # noqa: E402

FULL = {"sensors": 3, "zones": 7, "bins": 128, "frames": 60, "n1": (1.3, 1.45, 1.6), "mu_t": (0.05, 0.5, 2.0, 4.0), "batch": 30}
QUICK = {"sensors": 2, "zones": 3, "bins": 96, "frames": 30, "n1": (1.45,), "mu_t": (0.5,), "batch": 4}
ALBEDO = 0.8  # mu_s / mu_t of the truths
# The independent simulator's geometry resolution: "converged" (indep_sim.CONVERGED, where its
# expected counts stop changing: docs/results/mu_low_convergence.json; the default) or "default"
# (the fast fixture's, what this study used before: at mu_t = 0.05 /m its coarse sampling moved
# the fitted mu_t by 10-45 points from rig to rig)
RESOLUTIONS = {"converged": CONVERGED, "default": IndepOptions()}


def _scene(base, sensors, zones, bins):
    sm = base.sensor
    small = SensorModel(bin_width_s=sm.bin_width_s, n_bins=bins, zones=zones, fov_deg=sm.fov_deg * zones / sm.zones)
    return base.replace(sensor=small, sensors=base.sensors[:sensors])


def truth_scene(nominal, n1: float, mu_t: float):
    """``nominal`` with the truth's optics: n1 and mu_s + mu_a = ``mu_t`` at the studies' albedo (:data:`ALBEDO`)."""
    wg = dataclasses.replace(nominal.waveguide, n1=n1, mu_s_per_m=ALBEDO * mu_t, mu_a_per_m=(1 - ALBEDO) * mu_t)
    return nominal.replace(waveguide=wg)


def _mu_t_stderr(res):
    """Laplace standard error of mu_s + mu_a (None where the covariance does not hold both)."""
    try:
        i, j = res.labels.index("mu_s_per_m"), res.labels.index("mu_a_per_m")
        c = np.asarray(res.covariance)
        v = float(c[i, i] + c[j, j] + 2 * c[i, j])
        return float(np.sqrt(v)) if np.isfinite(v) and v >= 0 else None
    except (ValueError, TypeError, IndexError, AttributeError):
        return None


def _row(res, n1, mu_t, seconds):
    f_n1 = float(res.params.n1)
    f_mu = float(res.params.mu_s_per_m + res.params.mu_a_per_m)
    se = _mu_t_stderr(res)
    return {
        "result": res.result,
        "converged": bool(res.converged),
        "n1": f_n1,
        "mu_t_per_m": f_mu,
        "pulse": {k: float(getattr(res.params, k)) for k in ("pulse_sigma_s", "pulse_tail_s", "pulse_slow_weight", "pulse_slow_tail_s")},
        "emission_time_s": float(res.params.emission_time_s),
        "near_field_m": float(res.params.near_field_m),
        "near_field_shape": float(getattr(res.params, "near_field_shape", 2.0)),
        "n1_rel_error": f_n1 / n1 - 1,
        "mu_t_rel_error": f_mu / mu_t - 1,
        # Laplace standard error of mu_t (relative to the truth) and the error in its units
        "mu_t_stderr_rel": None if se is None else se / mu_t,
        "mu_t_error_in_stderr": None if not se else (f_mu - mu_t) / se,
        "crosstalk_width_s": float(res.params.crosstalk_width_s),
        "reduced_chi2": res.reduced_chi2,
        "worst_zone": (res.discrepancy.get("worst_zones") or [None])[0],
        "end_reflectance": float(res.params.end_reflectance),
        "end_incidence_power": float(res.params.end_incidence_power),
        "starts_fitted": sum(str(st.get("stage", "")).startswith("fit from start") for st in res.stages),
        "seconds": seconds,
    }


def _summary(rows):
    n = len(rows)
    n1e = np.abs([r["n1_rel_error"] for r in rows])
    mue = np.abs([r["mu_t_rel_error"] for r in rows])
    ok = [r["converged"] for r in rows]
    return {
        "fits": n,
        "converged": int(sum(ok)),
        "n1_within_1pct": int(np.sum(n1e <= 0.01)),
        "mu_t_within_25pct": int(np.sum(mue <= 0.25)),
        "all_targets": int(sum(o and a <= 0.01 and b <= 0.25 for o, a, b in zip(ok, n1e, mue))),
        "n1_rel_error_median": float(np.median(n1e)),
        "n1_rel_error_max": float(np.max(n1e)),
        "mu_t_rel_error_median": float(np.median(mue)),
        "mu_t_rel_error_max": float(np.max(mue)),
        "reduced_chi2_median": float(np.median([r["reduced_chi2"] for r in rows])),
        "reduced_chi2_max": float(np.max([r["reduced_chi2"] for r in rows])),
    }


def batch_speed(cal: Calibrator, truth, frames: int, batch: int, seed: int) -> dict:
    """The same compiled fit (no covariance) on ``batch`` captures: separate calls against one
    vmapped call, from the same starts."""
    cfg, problem = cal.config, cal.problem
    solver, objective = cfg.make_solver(), cfg.make_objective()
    base = cal.base_params()
    caps = [simulate(truth, frames, seed=seed + i) for i in range(batch)]
    starts, anchors, data, sigma = [], [], [], []
    for c in caps:
        d, g = _data(c, base.n1.dtype, cfg.model_error)
        s, found = timing_start(problem, np.asarray(d), c.n_frames, cal.scene, base)
        anchors.append(_anchor(s, found, cfg, base.n1.dtype))
        starts.append(envelope_candidates(problem, s, d, g, 1)[0])
        data.append(d)
        sigma.append(g)
    kw = dict(max_steps=cfg.max_steps, loss_tol=cfg.loss_tol, gn_first=cfg.gn_first, with_cov=False)

    def one(i):
        return fit_problem(problem, objective, solver, starts[i], data[i], sigma[i], base, anchors[i], **kw)

    stack = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *starts)
    D, G, A = jnp.stack(data), jnp.stack(sigma), jnp.stack(anchors)

    def many():
        return fit_problem_batch(problem, objective, solver, stack, D, G, base, A, **kw)

    t = time.perf_counter()
    jax.block_until_ready(one(0))
    compile_single = time.perf_counter() - t
    t = time.perf_counter()
    jax.block_until_ready(many())
    compile_batch = time.perf_counter() - t
    t = time.perf_counter()
    singles = [jax.block_until_ready(one(i)) for i in range(batch)]
    separate = time.perf_counter() - t
    t = time.perf_counter()
    out = jax.block_until_ready(many())
    batched = time.perf_counter() - t
    n1_single = np.array([float(s.params.n1) for s in singles])
    n1_batch = np.asarray(out.params.n1)
    return {
        "batch": batch,
        "separate_calls_s": separate,
        "one_vmapped_call_s": batched,
        "speedup": separate / batched,
        "warm_fit_s_per_fit_separate": separate / batch,
        "first_call_s_single (compile + 1 fit)": compile_single,
        "first_call_s_batch (compile + batch)": compile_batch,
        "max_n1_difference_batch_vs_single": float(np.max(np.abs(n1_single - n1_batch))),
        "successful_batch": int(np.sum(np.asarray(out.result._value) == 0)) if hasattr(out.result, "_value") else None,
    }


COLUMNS = ("own", "independent", "independent_scene_without_ms")


def run(out: Path, quick: bool = False, config: FitConfig = FitConfig(), progress: bool = True, overwrite: bool = False,
        columns=COLUMNS, n1s=None, mu_ts=None, batch: bool = True, resolution: str = "converged") -> dict:
    path = check_output(out / "calib_independent.json", overwrite=overwrite)
    p = dict(QUICK if quick else FULL)
    grid = list(itertools.product(p["n1"], p["mu_t"]))  # seeds follow the full grid's order
    keep = [(k, n1, mu_t) for k, (n1, mu_t) in enumerate(grid)
            if (n1s is None or n1 in n1s) and (mu_ts is None or mu_t in mu_ts)]
    nominal = _scene(load_scene("optoskin"), p["sensors"], p["zones"], p["bins"])
    cal = Calibrator(nominal, config)
    no_ms = nominal.replace(waveguide=dataclasses.replace(nominal.waveguide, multiple_scattering=0.0))
    cal_no_ms = Calibrator(no_ms, config)
    rows = {k: [] for k in columns}
    truths = []
    for k, n1, mu_t in keep:
        truth = truth_scene(nominal, n1, mu_t)
        truths.append({"n1": n1, "mu_t_per_m": mu_t, "albedo": ALBEDO, "grid_index": k})
        own = simulate(truth, p["frames"], seed=100 + k) if "own" in columns else None
        rig = IndepRig.from_scene(truth, seed=200 + k, options=RESOLUTIONS[resolution])
        ind = simulate_independent(rig, contacts=np.zeros((0, 3)), frames=p["frames"], seed=300 + k)
        todo = (("own", own, cal), ("independent", ind, cal), ("independent_scene_without_ms", ind, cal_no_ms))
        for name, cap, c in (t for t in todo if t[0] in columns):
            t = time.perf_counter()
            res = c.fit(cap)
            rows[name].append(_row(res, n1, mu_t, time.perf_counter() - t))
            if progress:
                r = rows[name][-1]
                print(
                    f"n1 {n1:.2f} mu_t {mu_t:5.2f} {name[:16]:16s}: {r['result']:22s} n1 err {100 * r['n1_rel_error']:+6.2f}% "
                    f"mu_t err {100 * r['mu_t_rel_error']:+7.1f}% chi2 {r['reduced_chi2']:7.2f} ({r['seconds']:.1f} s)",
                    flush=True,
                )
        # written after every truth: a part stopped by the 10-minute limit keeps what it fitted
        atomic_write_text(path, json.dumps(_result(config, p, truths, rows, columns, None, resolution), indent=2))
    speed = None
    if batch:
        wg = dataclasses.replace(nominal.waveguide, n1=1.45, mu_s_per_m=0.4, mu_a_per_m=0.1)
        speed = batch_speed(cal, nominal.replace(waveguide=wg), p["frames"], p["batch"], seed=5000)
    result = _result(config, p, truths, rows, columns, speed, resolution)
    atomic_write_text(path, json.dumps(result, indent=2))
    return result


def _result(config, p, truths, rows, columns, speed, resolution="converged") -> dict:
    return {
        "independent_resolution": {"name": resolution} | {k: getattr(RESOLUTIONS[resolution], k)
                                                           for k in ("range_step_m", "angles_per_zone", "end_rays", "fine")},
        "study": "calibration on own and independent simulated data",
        "data": "simulated (own: tofjax.simulate; independent: tests/indep_sim.py)",
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs ({platform.platform()}), CPU only, shared with other agents (loaded)",
        "load_average": list(os.getloadavg()),
        "scene": {k: p[k] for k in ("sensors", "zones", "bins", "frames")} | {"base": "optoskin", "albedo": ALBEDO},
        "fit_config": dataclasses.asdict(config),
        "truths": truths,
        **{k: {"summary": _summary(rows[k]), "fits": rows[k]} for k in columns if rows[k]},
        "batch_speed": speed,
    }


def merge(parts: list[Path], out: Path, overwrite: bool = False) -> dict:
    """One result from the JSONs of several parts of the grid: each column's fits in grid
    order (a truth fitted twice keeps the later part's), summaries recomputed; the parts'
    load averages and the first batch speed found are kept."""
    path = check_output(out / "calib_independent.json", overwrite=overwrite)
    loaded = [json.loads(Path(q).read_text()) for q in parts]
    cols: dict = {}
    for d in loaded:
        for c in COLUMNS:
            for t, r in zip(d["truths"], d.get(c, {}).get("fits", [])):
                cols.setdefault(c, {})[t["grid_index"]] = (t, r)
    truths = {}
    for c in cols.values():
        truths.update({i: t for i, (t, _) in c.items()})
    first = loaded[0]
    result = {k: first[k] for k in ("study", "data", "machine", "scene", "fit_config")}
    res = {json.dumps(d.get("independent_resolution")) for d in loaded}
    if len(res) > 1:
        raise SystemExit(f"--merge: the parts used different independent resolutions: {sorted(res)}")
    result["independent_resolution"] = first.get("independent_resolution")
    result["load_average"] = [d["load_average"] for d in loaded]
    result["parts"] = [str(q) for q in parts]
    result["truths"] = [truths[i] for i in sorted(truths)]
    for c in COLUMNS:
        if c in cols:
            idx = sorted(cols[c])
            fits = [cols[c][i][1] for i in idx]
            result[c] = {"summary": _summary(fits), "truth_index": idx, "fits": fits}
    result["batch_speed"] = next((d["batch_speed"] for d in loaded if d.get("batch_speed")), None)
    atomic_write_text(path, json.dumps(result, indent=2))
    return result


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/calib_independent")
    ap.add_argument("--quick", action="store_true", help="a tiny scene and one truth (what the test runs)")
    ap.add_argument("--model-error", type=float, default=FitConfig().model_error, help="FitConfig.model_error")
    ap.add_argument("--overwrite", action="store_true")
    ap.add_argument("--columns", default=",".join(COLUMNS), help=f"comma-separated subset of {', '.join(COLUMNS)}")
    ap.add_argument("--n1", type=float, nargs="+", help="only these true n1 of the grid")
    ap.add_argument("--mu-t", type=float, nargs="+", help="only these true mu_t of the grid")
    ap.add_argument("--geodesic", choices=("on", "off"), default="on" if FitConfig().geodesic else "off",
                    help="FitConfig.geodesic: the Marquardt solver's geodesic acceleration")
    ap.add_argument("--resolution", choices=tuple(RESOLUTIONS), default="converged",
                    help="the independent simulator's geometry resolution (converged: indep_sim.CONVERGED)")
    ap.add_argument("--no-batch", action="store_true", help="skip the batch speed-up measurement")
    ap.add_argument("--merge", nargs="+", type=Path, help="merge these parts' JSONs into --out instead of fitting")
    args = ap.parse_args(argv)
    if args.merge:
        r = merge(args.merge, Path(args.out), overwrite=args.overwrite)
    else:
        cols = tuple(c for c in args.columns.split(",") if c)
        bad = [c for c in cols if c not in COLUMNS]
        if bad:
            raise SystemExit(f"--columns: unknown column {bad[0]!r}; known: {', '.join(COLUMNS)}")
        tofjax.enable_x64()
        r = run(Path(args.out), args.quick, FitConfig(model_error=args.model_error, geodesic=args.geodesic == "on"), overwrite=args.overwrite,
                columns=cols, n1s=args.n1, mu_ts=args.mu_t, batch=not args.no_batch, resolution=args.resolution)
    for name in COLUMNS:
        if name in r:
            print(name, json.dumps(r[name]["summary"]))
    print("batch", json.dumps(r["batch_speed"]))
    print(f"wrote {args.out}/calib_independent.json")


if __name__ == "__main__":
    main()
