"""Why some calibration fits of the default scene take 100-200 steps (the "stragglers" of a
vmapped batch), measured on **simulated** 100-frame OptoSkin baselines.

For each seed (``tofjax.simulate.simulate(load_scene("optoskin"), frames, seed=s)``, the GPU batch's
seeds 2000-2099) and each solver variant, the fit runs from one fixed start (the envelope start of
seed 1000's capture, as ``bench_fit.py --batch`` does), warm, then a tight reference refit from its
end point (``MarquardtLM(rtol=atol=1e-12)``, ``loss_tol = 0``, up to ``--reference-steps`` steps).
Reported per fit: steps, result, warm time, what the loss still fell in the last half of the steps,
the share of rejected steps, and the distance of n1, mu_s + mu_a and the worst free parameter from
the reference in the fit's Laplace standard errors.

``--diagnose SEED``: at the default fit's end point of that seed, the spectrum of the scaled
``J^T J`` (Marquardt's scaling) with the two softest directions, and the Gauss-Newton / damped
steps' predicted against actual loss decrease along the step (is the quadratic model wrong at the
step's scale, i.e. a curved valley?), with and without the softest direction projected out; and
the physical path of the valley's parameters (start, step 20, end).

    TOFJAX_PROGRAM_STORE=0 python experiments/straggler_fits.py --out docs/results/straggler_fits.json
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

ROOT = Path(__file__).resolve().parents[1]
SLOW = [2000, 2011, 2014, 2031, 2033, 2036]  # 100-200 steps in a first pass over seeds 2000-2039 (default solver)
TYPICAL = [2001, 2004, 2017, 2026]
VALLEY = ["pulse_tail_s", "pulse_slow_tail_s", "pulse_slow_weight", "end_reflectance", "interface_backscatter_per_m",
          "mu_s_per_m", "mu_a_per_m", "gain", "n1"]


def _progress(msg):
    print(f"[straggler {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="*", default=SLOW + TYPICAL)
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--variants", nargs="*", default=["default", "trials"], choices=["default", "trials", "geodesic"])
    p.add_argument("--reference-steps", type=int, default=400)
    p.add_argument("--diagnose", type=int, default=2000, help="seed whose end point is diagnosed (-1: none)")
    p.add_argument("--slow-tail", type=float, default=0.0,
                   help="simulate with a slow pulse tail of this weight (time constant 4x the fast one); 0: the scene's one tail")
    p.add_argument("--out", default="docs/results/straggler_fits.json")
    a = p.parse_args(argv)
    os.environ.setdefault("TOFJAX_PROGRAM_STORE", "0")

    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.flatten_util
    import numpy as np

    from tofjax.fit._laplace import laplace_covariance
    from tofjax.fit._start import envelope_candidates, timing_start
    from tofjax.fit.calibrate import Calibrator, _anchor, _data, _result_name, fit_problem
    from tofjax.fit.solve import MarquardtLM
    from tofjax.scene import load_scene
    from tofjax.simulate import simulate

    scene = load_scene("optoskin")
    cal = Calibrator(scene)
    pb, cfg = cal.problem, cal.config
    solver, objective = cfg.make_solver(), cfg.make_objective()
    base = cal.base_params()
    dtype = pb.model.geometry.ray_length.dtype
    variants = {"default": solver, "trials": dataclasses.replace(solver, lambda_trials=(1e-3, 1e-2, 1e-1, 1.0, 10.0)),
                "geodesic": dataclasses.replace(solver, geodesic=True)}
    tight = MarquardtLM(rtol=1e-12, atol=1e-12)
    c0 = simulate(scene, a.frames, seed=1000)
    d0, s0 = _data(c0, dtype)
    st, found = timing_start(pb, np.asarray(d0), a.frames, scene, base)
    start = envelope_candidates(pb, st, d0, s0, 1)[0]
    anchor = _anchor(st, found, cfg, dtype)
    kw = dict(max_steps=cfg.max_steps, loss_tol=cfg.loss_tol, gn_first=cfg.gn_first)

    def phys(sol):
        return {k: np.asarray(sol.linear[k] if k in sol.linear else getattr(sol.params, k), np.float64) for k in pb.free}

    fits, ends = [], {}
    sim_kw = {}
    if a.slow_tail > 0:
        from tofjax.model import ModelOptions, Params

        truth = Params.from_scene(scene, dtype)
        sim_kw = {"options": ModelOptions(pulse_tails=2), "params": truth.replace(pulse_slow_weight=np.asarray(a.slow_tail, dtype))}
    for s in a.seeds:
        d, g = _data(simulate(scene, a.frames, seed=s, **sim_kw), dtype)
        for name in a.variants:
            sv = variants[name]
            jax.block_until_ready(fit_problem(pb, objective, sv, start, d, g, base, anchor, with_cov=True, **kw).steps)
            t = time.perf_counter()
            sol = jax.device_get(fit_problem(pb, objective, sv, start, d, g, base, anchor, with_cov=True, **kw))
            dt = time.perf_counter() - t
            ref = jax.device_get(fit_problem(pb, objective, tight, sol.params, d, g, base, anchor, max_steps=a.reference_steps,
                                             loss_tol=0.0, gn_first=0, with_cov=False))
            v, vr = phys(sol), phys(ref)
            cov, labels, se, _, _ = laplace_covariance(pb, v, sol.hessian, sol.dphys)
            i_s, i_a = labels.index("mu_s_per_m"), labels.index("mu_a_per_m")
            mut_se = float(np.sqrt(cov[i_s, i_s] + cov[i_a, i_a] + 2 * cov[i_s, i_a]))
            dev = {k: float(np.max(np.abs(v[k] - vr[k]) / np.maximum(se[k], 1e-300))) for k in pb.free}
            steps = int(sol.steps)
            h = np.asarray(sol.history)[: steps + 1]
            dh = -np.diff(h)
            half = steps // 2
            row = {
                "seed": s, "variant": name, "steps": steps, "result": _result_name(sol.result), "warm_fit_s": dt,
                "chi2_over_2": float(0.5 * sol.chi2), "reference_chi2_over_2": float(0.5 * ref.chi2),
                "reference_steps": int(ref.steps), "reference_hit_limit": int(ref.steps) >= a.reference_steps,
                "loss_fall_last_half": float(h[half] - h[-1]), "rejected_share": float(np.mean(dh <= 0)) if steps else 0.0,
                "n1": float(v["n1"]), "mu_t": float(v["mu_s_per_m"] + v["mu_a_per_m"]),
                "n1_sd_from_reference": float(abs(v["n1"] - vr["n1"]) / se["n1"]),
                "mu_t_sd_from_reference": abs(float(v["mu_s_per_m"] + v["mu_a_per_m"] - vr["mu_s_per_m"] - vr["mu_a_per_m"])) / mut_se,
                "worst_parameter": max(dev, key=dev.get), "worst_sd_from_reference": max(dev.values()),
                "end_values": {k: float(np.mean(v[k])) if k in v else float(np.mean(np.asarray(getattr(sol.params, k)))) for k in VALLEY},
            }
            fits.append(row)
            if name == "default":
                ends[s] = sol
            _progress(f"seed {s} {name}: {steps} steps {row['result']} {dt:.2f} s, n1 {row['n1_sd_from_reference']:.3f} sd, "
                      f"mu_t {row['mu_t_sd_from_reference']:.3f} sd, worst {row['worst_parameter']} {row['worst_sd_from_reference']:.2f} sd "
                      f"(reference {row['reference_steps']} steps)")

    summary = {}
    for name in a.variants:
        rows = [f for f in fits if f["variant"] == name]
        st_ = [f["steps"] for f in rows]
        summary[name] = {
            "steps_mean": float(np.mean(st_)), "steps_max": int(max(st_)), "at_limit": sum(x >= cfg.max_steps for x in st_),
            "reported_converged": sum(f["result"] == "successful" for f in rows),
            "warm_fit_s_total": float(sum(f["warm_fit_s"] for f in rows)),
            "max_n1_sd": max(f["n1_sd_from_reference"] for f in rows), "max_mu_t_sd": max(f["mu_t_sd_from_reference"] for f in rows),
            "converged_but_over_0.1_sd_n1_or_mu_t": [f["seed"] for f in rows if f["result"] == "successful"
                                                    and max(f["n1_sd_from_reference"], f["mu_t_sd_from_reference"]) > 0.1],
        }
    out = {
        "what": "straggler calibration fits of the default optoskin scene: steps, accuracy against a tight reference, diagnosis",
        "data": f"simulated: tofjax.simulate.simulate(load_scene('optoskin'), {a.frames}, seed=s), own model"
                + (f", with a slow pulse tail of weight {a.slow_tail} (4x the fast time constant)" if a.slow_tail > 0 else ""),
        "command": "TOFJAX_PROGRAM_STORE=0 python experiments/straggler_fits.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "machine": f"{platform.node()} ({os.cpu_count()} CPU cores, shared); load average at the end {os.getloadavg()}",
        "start": "one fixed start for every seed: the envelope start of seed 1000's capture (as bench_fit.py --batch)",
        "config": {"loss_tol": cfg.loss_tol, "max_steps": cfg.max_steps, "reference_steps": a.reference_steps},
        "summary": summary, "fits": fits,
    }
    if a.diagnose in ends:
        out["diagnosis"] = diagnose(pb, ends[a.diagnose], a, scene, base, start, anchor, dtype)
    path = ROOT / a.out if not Path(a.out).is_absolute() else Path(a.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1) + "\n")
    _progress(f"wrote {path}")
    return 0


def diagnose(pb, sol, a, scene, base, start, anchor, dtype) -> dict:
    """The scaled spectrum and the quadratic model's validity at ``sol``'s end point."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from tofjax.fit.calibrate import _data
    from tofjax.simulate import simulate

    d, g = _data(simulate(scene, a.frames, seed=a.diagnose), dtype)
    p0, _, _, _ = pb.profile(start, d, g)
    u0 = pb.pack_jax(p0, pb.nonlinear)
    prior = pb.pack_jax(base, pb.nonlinear)
    prior["n1_anchor"] = anchor
    f0, unravel = jax.flatten_util.ravel_pytree(u0)
    names = sorted(u0)
    args = (p0, d, g, prior)
    res = jax.jit(lambda f: pb.residuals(unravel(f), args))
    jac = jax.jit(jax.jacfwd(lambda f: pb.residuals(unravel(f), args)))
    y = jax.flatten_util.ravel_pytree(pb.pack_jax(sol.params, pb.nonlinear))[0]
    r, J = res(y), jac(y)
    L0 = 0.5 * float(r @ r)
    A, gr = np.asarray(J.T @ J), np.asarray(J.T @ r)
    dd = np.sqrt(np.diag(A))
    w, V = np.linalg.eigh(A / np.outer(dd, dd))

    def top(vec):
        return {names[k]: round(float(vec[k]), 3) for k in np.argsort(-np.abs(vec))[:5]}

    steps = []
    for drop in (0, 1):
        P = np.eye(len(w)) - V[:, :drop] @ V[:, :drop].T
        for lam in (0.0, 1e-5, 1e-4, 3e-4):
            vs = -P @ np.linalg.solve(P @ (A / np.outer(dd, dd)) @ P + lam * np.eye(len(w)) + (np.eye(len(w)) - P), P @ (gr / dd))
            v = vs / dd
            pred = float(-(gr @ v + 0.5 * v @ A @ v))
            ts = (0.1, 0.3, 1.0)
            steps.append({"softest_directions_removed": drop, "relative_damping": lam, "largest_coordinate": names[int(np.argmax(np.abs(v)))],
                          "largest_change": float(np.max(np.abs(v))), "predicted_decrease": pred,
                          "actual_decrease_at_fraction": {str(t): L0 - 0.5 * float(jnp.sum(res(y + t * jnp.asarray(v)) ** 2)) for t in ts}})
    return {"seed": a.diagnose, "coordinates": names, "chi2_over_2": L0,
            "scaled_jtj_eigenvalues": w.tolist(), "softest_direction": top(V[:, 0]), "second_softest_direction": top(V[:, 1]),
            "gauss_newton_left": float(0.5 * (gr / dd) @ np.linalg.solve(A / np.outer(dd, dd) + 1e-12 * np.eye(len(w)), gr / dd)),
            "steps_at_end_point": steps,
            "end_values": {k: float(np.mean(np.asarray(sol.linear[k] if k in sol.linear else getattr(sol.params, k)))) for k in VALLEY},
            "scene_values": {k: float(np.mean(np.asarray(getattr(base, k)))) for k in VALLEY}}


if __name__ == "__main__":
    sys.exit(main())
