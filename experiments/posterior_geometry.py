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


def run(out: Path, small=None) -> dict:
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
        "study": "geometry of the calibration posterior along its ridge: the parts of the log-density",
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
    atomic_write_text(out / "posterior_geometry.json", json.dumps(result, indent=1))
    return result


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--small", type=int, nargs=3, metavar=("SENSORS", "ZONES", "BINS"), help="a reduced scene (e.g. 3 3 96)")
    ap.add_argument("--out", default="out/posterior_geometry")
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)
    tofjax.enable_x64()
    from tofjax.compile_cache import enable_compilation_cache

    enable_compilation_cache()
    out = Path(a.out)
    check_output(out / "posterior_geometry.json", overwrite=a.overwrite)
    out.mkdir(parents=True, exist_ok=True)
    r = run(out, a.small)
    print(json.dumps({k: r[k] for k in ("data", "zones", "slope_nats_per_sd", "relative_to_fit")}, indent=1))


if __name__ == "__main__":
    main()
