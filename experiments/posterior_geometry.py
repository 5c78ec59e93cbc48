"""Why NUTS mixes slowly on the calibration posterior: where its draws lie against the point fit.

Simulates the reduced OptoSkin baseline of ``bench_posterior.py --small 3 3 96`` (100 frames,
seed 1), fits it, samples the posterior with NUTS (slow pulse tail held at the fit; the
default nuisance prior), then reports, on that posterior's own coordinates:

- per coordinate: the draws' mean minus the fit, in Laplace standard errors, and the draws'
  standard deviation over the Laplace one;
- the eigenvalues of the draws' covariance in coordinates whitened by the Laplace covariance
  (all 1 if the Laplace approximation were the posterior);
- the log-density along the straight line from the fit (t = 0) through the draws' mean
  (t = 1): a second maximum and the valley between them mean two modes (or a curved ridge).

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


def run(out: Path, chains: int = 4, warmup: int = 300, draws: int = 500) -> dict:
    from bench_posterior import small_scene_of  # noqa: PLC0415 (the benchmark's reduced scene)

    from tofjax.fit.calibrate import Calibrator, FitConfig
    from tofjax.fit.nuts import NutsOptions, sample_nuts
    from tofjax.fit.posterior import log_density
    from tofjax.simulate import simulate

    scene, label = small_scene_of("optoskin", (3, 3, 96))
    cap = simulate(scene, 100, seed=1)
    cal = Calibrator(scene, FitConfig())
    fit = cal.fit(cap)
    opts = NutsOptions(chains=chains, warmup=warmup, draws=draws, pilot=False)  # bench_posterior's program, one run
    ld = log_density(cal, cap, fit, opts.nuisance_width, opts.hold)
    r = sample_nuts(cal, cap, fit, opts, density=ld)
    x = r.chains_unconstrained.reshape(-1, ld.flat0.size)
    sd = np.sqrt(np.diag(ld.laplace_cov))
    mean = x.mean(0)
    L = np.linalg.cholesky(ld.laplace_cov)
    Li = np.linalg.inv(L)
    eig = np.linalg.eigvalsh(Li @ np.cov(x.T) @ Li.T)
    t = np.linspace(-0.2, 1.4, 33)
    lp = ld.batch(ld.flat0[None] + t[:, None] * (mean - ld.flat0)[None])
    inner = (t > 0) & (t < 1)
    result = {
        "study": "geometry of the calibration posterior (NUTS draws against the point fit's Laplace approximation)",
        "data": f"simulated {label}, 100 frames (seed 1)",
        "machine": f"{platform.machine()} CPU, {os.cpu_count()} cores shared with other jobs "
        f"(load average at the end {os.getloadavg()[0]:.1f})",
        "nuts": {"chains": chains, "warmup": warmup, "draws": draws, "pilot": opts.pilot, "held_at_fit": list(opts.hold),
                 "divergences": r.divergences, "rhat_max": r.diagnostics["rhat_max"], "ess_bulk": r.diagnostics["ess_bulk"]},
        "coordinates": list(ld.coords),
        "draws_mean_minus_fit_in_laplace_sd": dict(zip(ld.coords, ((mean - ld.flat0) / sd).tolist())),
        "draws_sd_over_laplace_sd": dict(zip(ld.coords, (x.std(0) / sd).tolist())),
        "whitened_covariance_eigenvalues": eig.tolist(),
        "line_from_fit_to_draws_mean": {"t": t.tolist(), "log_density": lp.tolist()},
        "log_density_at_fit": float(lp[np.argmin(np.abs(t))]),
        "log_density_max_on_line": float(lp.max()),
        "t_of_max": float(t[np.argmax(lp)]),
        "log_density_min_between": float(lp[inner].min()),
    }
    atomic_write_text(out / "posterior_geometry.json", json.dumps(result, indent=1))
    return result


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/posterior_geometry")
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)
    tofjax.enable_x64()
    from tofjax.compile_cache import enable_compilation_cache

    enable_compilation_cache()
    out = Path(a.out)
    check_output(out / "posterior_geometry.json", overwrite=a.overwrite)
    out.mkdir(parents=True, exist_ok=True)
    r = run(out)
    print(json.dumps({k: v for k, v in r.items() if k != "line_from_fit_to_draws_mean"}, indent=1))


if __name__ == "__main__":
    main()
