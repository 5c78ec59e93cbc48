"""NUTS variants side by side on the default 100-frame baseline: coordinates and settings.

Each variant is a JSON object of :class:`tofjax.fit.nuts.NutsOptions` fields, plus ``label``,
``fractions`` (the coordinates sampled as log p, :data:`tofjax.fit.posterior.LOG_FRACTIONS`;
default albedo and end reflectance) and ``steep`` (:data:`tofjax.fit.posterior.STEEP`). One fit,
one log-density per variant, one NUTS run each; a row per variant (divergences, gradients, min
ESS, R-hat, ESS per gradient, step sizes, tree depth, per-parameter ESS, the load average) is
appended to ``--out`` (JSON lines) as it finishes. The per-gradient figures do not depend on
the load (the seeds are fixed); the seconds do. Several copies may run at once (the 2-core
shared VM: each copy pays its own fit and compilation). ``--fit-cache`` keeps the point fit
(pickle) for the next copy.

    python experiments/nuts_variants.py --out out/posterior_variants.jsonl '{"label":"shear","shear":true}'
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import time
from pathlib import Path

import numpy as np

import tofjax


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("variants", nargs="+", help="JSON objects: NutsOptions fields, label, fractions, steep")
    ap.add_argument("--out", default="out/posterior_variants.jsonl")
    ap.add_argument("--fit-cache", default="out/posterior_variants_fit.pkl")
    a = ap.parse_args(argv)
    tofjax.enable_x64()
    from tofjax.compile_cache import enable_compilation_cache

    enable_compilation_cache()
    import tofjax.fit.nuts as nm
    import tofjax.fit.posterior as post
    from tofjax.fit.calibrate import Calibrator, FitConfig
    from tofjax.scene import load_scene
    from tofjax.simulate import simulate

    scene = load_scene("optoskin")
    cap = simulate(scene, 100, seed=1)
    cal = Calibrator(scene, FitConfig())
    try:
        with open(a.fit_cache, "rb") as f:
            fit = pickle.load(f)
    except (OSError, pickle.UnpicklingError, EOFError):
        fit = cal.fit(cap)
        Path(a.fit_cache).parent.mkdir(parents=True, exist_ok=True)
        with open(a.fit_cache, "wb") as f:
            pickle.dump(fit, f)
    for spec in a.variants:
        kw = json.loads(spec)
        label = kw.pop("label", spec)
        fractions = tuple(kw.pop("fractions", ("albedo", "end_reflectance")))
        steep = float(kw.pop("steep", 30.0))
        post.LOG_FRACTIONS, post.STEEP, nm.STEEP = fractions, steep, steep
        nm._COMPILED.clear()
        o = nm.NutsOptions(**kw)
        ld = post.log_density(cal, cap, fit, o.nuisance_width, o.hold, o.gain_prior)
        t = time.perf_counter()
        r = nm.sample_nuts(cal, cap, fit, o, density=ld)
        s = r.summary()
        row = dict(label=label, options=kw, fractions=fractions, steep=steep, divergences=r.divergences,
                   gradient_evaluations=r.gradient_evaluations,
                   warmup_gradient_evaluations=r.warmup_gradient_evaluations, ess_min=s["ess_min"], rhat_max=s["rhat_max"],
                   ess_min_per_gradient=s["ess_min"] / r.gradient_evaluations, wall_s=r.wall_s, compile_s=r.compile_s,
                   total_s=time.perf_counter() - t, step_size=r.step_size.tolist(), mean_tree_depth=r.mean_tree_depth,
                   mean_accept=r.mean_accept, ess_bulk=s["ess_bulk"], ess_tail=s["ess_tail"],
                   ridge_tail_alpha=r.start_info.get("ridge_tail_alpha"), load_average=os.getloadavg()[0])
        # the posterior's shape against the Laplace approximation at the fit (the samplers' coordinates):
        # the eigenvalues of the draws' covariance whitened by the Laplace covariance, and the
        # widest and narrowest directions' loadings (which coordinates the sampler finds off)
        w = post._to_sampler_np(r.chains_unconstrained.reshape(-1, ld.flat0.size), ld.idx)
        L = np.linalg.cholesky(ld.laplace_cov)
        ev, vec = np.linalg.eigh(np.linalg.solve(L, np.linalg.solve(L, np.cov(w.T)).T))
        row["draws_over_laplace_variance"] = ev.tolist()
        sd = np.sqrt(np.diag(ld.laplace_cov))
        for name, j in (("widest_direction", -1), ("narrowest_direction", 0)):  # in Laplace sd of each coordinate
            d = L @ vec[:, j] / sd
            row[name] = {k: round(float(v), 3) for k, v in zip(ld.coords, d / np.abs(d).max())}
        print(json.dumps(row), flush=True)
        with open(a.out, "a") as f:
            f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
