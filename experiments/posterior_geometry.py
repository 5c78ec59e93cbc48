"""Why the calibration posterior had its bulk away from the point fit: the gain prior's volume term.

Simulates the default OptoSkin baseline (or ``--small S Z B``, the reduced scene of
``bench_posterior.py``; 100 frames, seed 1), fits it, builds the posterior's log-density
(:func:`tofjax.fit.posterior.log_density`: slow pulse tail held at the fit, the default
nuisance prior) and walks from the fit along the Laplace covariance's widest direction (the
ridge where albedo, end reflectance and interface backscatter trade against the zone gains),
``t`` in Laplace standard errors. At each point it splits the log-density into its parts:

- ``profile``: ``-chi2/2`` at the profiled linear parameters (the point fit's objective);
- ``half_logdet``: ``-1/2 log det(A^T W A)``, the Gaussian volume of the linear parameters;
- ``log_gain``: ``-sum log g*`` over the profiled zone gains, the log-uniform gain prior's term;
- ``prior``: the fit's weak prior and the nuisance prior;

and the totals with the flat gain prior (``profile + half_logdet + prior``, the log-density
before issue 16's rework) and with the log-uniform one (``+ log_gain``, the default now). A
volume term that changes along the ridge moves the posterior's mass away from the fit.

Writes ``posterior_geometry.json`` in ``--out``. Simulated data.

    python experiments/posterior_geometry.py --out out/posterior_geometry
"""

from __future__ import annotations

import argparse
import json
import os
import platform
from pathlib import Path

import numpy as np

import tofjax
from tofjax.outputs import atomic_write_text, check_output


def run(out: Path, small=None, nuts_draws: int = 400) -> dict:
    import jax
    import jax.numpy as jnp
    from bench_posterior import small_scene_of  # noqa: PLC0415 (the benchmark's scenes)

    from tofjax.fit.calibrate import Calibrator, FitConfig
    from tofjax.fit.posterior import log_density
    from tofjax.simulate import simulate

    scene, label = small_scene_of("optoskin", small)
    cap = simulate(scene, 100, seed=1)
    cal = Calibrator(scene, FitConfig())
    fit = cal.fit(cap)
    ld = log_density(cal, cap, fit)
    pb = cal.problem
    base, data, sigma, prior, widths, held, _ = ld.args

    _, unravel = jax.flatten_util.ravel_pytree(ld.template)

    @jax.jit
    def parts(flat):
        u = {**held, **unravel(flat)}
        _, m, logdet, lin = pb.profile(pb.unpack(u, base), data, sigma)
        pr = jnp.sum(pb.prior_residuals(u, prior) ** 2) + sum(jnp.sum(((u[k] - prior[k]) / w) ** 2) for k, w in widths.items())
        return jnp.stack([-0.5 * jnp.sum(((m - data) / sigma) ** 2), -0.5 * logdet, -jnp.sum(jnp.log(lin["gain"])),
                          -0.5 * pr, jnp.mean(lin["gain"])])

    w, V = np.linalg.eigh(ld.laplace_cov)
    v = V[:, -1] * np.sqrt(w[-1])
    v = v * np.sign(v[list(ld.coords).index("albedo")]) if "albedo" in ld.coords else v
    t = np.linspace(-2.0, 2.0, 17)
    rows = np.array([np.asarray(parts(jnp.asarray(ld.to_fit(ld.flat0 + ti * v)))) for ti in t])
    rows[:, :4] -= rows[np.argmin(np.abs(t)), :4]  # relative to the fit
    flat = rows[:, 0] + rows[:, 1] + rows[:, 3]
    logu = flat + rows[:, 2]

    def slope(y):  # nats per Laplace standard error, fitted over |t| <= 1
        k = np.abs(t) <= 1 + 1e-9
        return float(np.polyfit(t[k], y[k], 1)[0])

    result = {
        "study": "geometry of the calibration posterior along its ridge: the parts of the log-density; "
        "the light-entry width's wall and what holding it at the fit changes (light_entry_width)",
        "data": f"simulated {label}, 100 frames (seed 1)",
        "machine": f"{platform.machine()} CPU, {os.cpu_count()} cores shared with other jobs "
        f"(load average at the end {os.getloadavg()[0]:.1f})",
        "zones": int(np.prod(np.shape(fit.params.crosstalk_counts))),
        "coordinates": list(ld.coords),
        "direction_per_laplace_sd": dict(zip(ld.coords, v.tolist())),
        "t_laplace_sd": t.tolist(),
        "relative_to_fit": {"profile": rows[:, 0].tolist(), "half_logdet": rows[:, 1].tolist(), "log_gain": rows[:, 2].tolist(),
                            "prior": rows[:, 3].tolist(), "total_flat_gain_prior": flat.tolist(),
                            "total_log_uniform_gain_prior": logu.tolist()},
        "mean_zone_gain": rows[:, 4].tolist(),
        "slope_nats_per_sd": {"half_logdet": slope(rows[:, 1]), "log_gain": slope(rows[:, 2]),
                              "volume_flat": slope(rows[:, 1]), "volume_log_uniform": slope(rows[:, 1] + rows[:, 2])},
    }
    if "crosstalk_width_s" in pb.nonlinear:
        result["light_entry_width"] = light_entry_width(cal, cap, fit, nuts_draws)
    atomic_write_text(out / "posterior_geometry.json", json.dumps(result, indent=1))
    return result


def light_entry_width(cal, cap, fit, nuts_draws: int = 400) -> dict:
    """The light-entry width (``crosstalk_width_s``) sampled or held at the fit.

    With it sampled (``hold=HELD_SLOW_TAIL``): the log-density and its curvature along the
    width's coordinate (the sigmoid's logit ``u``) at the log-density's mode, the rest held
    there. With ``nuts_draws`` > 0, NUTS on both densities (4 chains x (250 warm-up +
    ``nuts_draws``), target acceptance 0.9, the same seed): divergences, step sizes, tree
    depth, gradients, ESS; the correlation of the width's draws with every other coordinate;
    the largest eigenvalue of the Hessian of ``-log p`` in the draws' metric (their
    covariance, about what the adaptation ends with) at 60 random draws, with the
    coordinate that dominates its eigenvector (a leapfrog step ``eps`` is unstable where
    ``eps sqrt(lambda) > 2``); and the physical posterior of both (median and sd)."""
    import jax
    import jax.numpy as jnp

    from tofjax.fit.nuts import NutsOptions, sample_nuts
    from tofjax.fit.posterior import HELD, HELD_SLOW_TAIL, log_density, posterior_mode

    free = log_density(cal, cap, fit, hold=HELD_SLOW_TAIL)
    i = free.coords.index("crosstalk_width_s")
    mode, cov, _ = posterior_mode(free)
    tr = cal.problem.transform("crosstalk_width_s")
    hess = jax.jit(jax.hessian(free.fn))
    rows = []
    for u in np.arange(-8.0, -1.99, 0.5):
        x = mode.copy()
        x[i] = u
        rows.append({"u": float(u), "width_ps": float(tr.lo + (tr.hi - tr.lo) / (1 + np.exp(-u))) * 1e12,
                     "log_density": float(free.fn(jnp.asarray(x))), "curvature": -float(hess(jnp.asarray(x))[i, i])})
    top = max(r["log_density"] for r in rows)
    for r in rows:
        r["log_density"] -= top
    out = {"fit_width_s": float(fit.params.crosstalk_width_s), "fit_u": float(free.flat0[i]), "mode_u": float(mode[i]),
           "laplace_sd_u_at_mode": float(np.sqrt(cov[i, i])),
           "prior": "the fit's weak prior: Gaussian of width 3 in u, centred at the scene's 0 (u = logit 0.005)",
           "scan_at_mode": rows}
    if nuts_draws <= 0:
        return out
    runs = {}
    for name, hold in (("sampled", HELD_SLOW_TAIL), ("held", HELD)):
        ld = free if name == "sampled" else log_density(cal, cap, fit, hold=hold)
        r = sample_nuts(cal, cap, fit, NutsOptions(chains=4, warmup=250, draws=nuts_draws, target_accept=0.9, hold=hold), density=ld)
        s = r.summary()
        ch = np.asarray(r.chains_unconstrained).reshape(-1, len(r.coords))
        row = {"hold": list(hold), "divergences": r.divergences, "step_size": s["step_size"], "mean_tree_depth": r.mean_tree_depth,
               "gradient_evaluations": r.gradient_evaluations, "ess_min": s["ess_min"], "rhat_max": s["rhat_max"],
               "ess_min_per_gradient": s["ess_min"] / r.gradient_evaluations, "wall_s_loaded": r.wall_s,
               "physical": {k: {"median": float(np.median(r.samples[:, j])), "sd": float(np.std(r.samples[:, j]))}
                            for j, k in enumerate(r.names)}}
        if name == "sampled":
            w = ch[:, i]
            row["width_u_percentiles_1_50_99"] = np.percentile(w, [1, 50, 99]).tolist()
            row["correlation_with_width_u"] = {k: float(np.corrcoef(w, ch[:, j])[0, 1]) for j, k in enumerate(r.coords) if j != i}
            flats = _to_sampler(free, ch)  # chains_unconstrained is in the fit's coordinates; the samplers' differ for the fractions
            S = np.cov(flats.T)
            ev, V = np.linalg.eigh(S)
            R = V * np.sqrt(ev)
            pick = np.random.default_rng(0).choice(len(flats), 60, replace=False)
            lam = []
            for j in pick:
                e, E = np.linalg.eigh(R.T @ -np.asarray(hess(jnp.asarray(flats[j]))) @ R)
                d = (R @ E[:, -1]) / np.sqrt(np.diag(S))
                lam.append((float(e[-1]), r.coords[int(np.argmax(np.abs(d)))], float(flats[j, i])))
            lam.sort(key=lambda t: -t[0])
            row["largest_curvature_in_draws_metric"] = {
                "percentiles_5_50_95_100": np.percentile([t[0] for t in lam], [5, 50, 95, 100]).tolist(),
                "top10": [{"lambda": t[0], "dominant_coordinate": t[1], "width_u": t[2]} for t in lam[:10]]}
        runs[name] = row
    out["nuts"] = runs
    return out


def _to_sampler(ld, fit_flat):
    from tofjax.fit.posterior import _to_sampler_np

    return _to_sampler_np(fit_flat, ld.idx)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--small", type=int, nargs=3, metavar=("SENSORS", "ZONES", "BINS"), help="a reduced scene (e.g. 3 3 96)")
    ap.add_argument("--nuts-draws", type=int, default=400,
                    help="draws per chain of the NUTS runs with the light-entry width sampled and held (0: none)")
    ap.add_argument("--out", default="out/posterior_geometry")
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)
    tofjax.enable_x64()
    from tofjax.compile_cache import enable_compilation_cache

    enable_compilation_cache()
    out = Path(a.out)
    check_output(out / "posterior_geometry.json", overwrite=a.overwrite)
    out.mkdir(parents=True, exist_ok=True)
    r = run(out, a.small, a.nuts_draws)
    print(json.dumps({k: r[k] for k in ("data", "zones", "slope_nats_per_sd", "relative_to_fit", "light_entry_width") if k in r}, indent=1))


if __name__ == "__main__":
    main()
