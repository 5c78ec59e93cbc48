"""Study: recovery of n1, mu_s and mu_a from simulated baselines over a grid of truths.

For every (n1, mu_s, mu_a) of the config's grid and every replicate, a baseline is
simulated with those true values and fitted with the nominal scene as start and prior
centre, all baselines through :meth:`Calibrator.fit_many` (one vmapped call on an accelerator, one fit
after the other on a CPU; a fit
that fails or ends on a bound is then refitted alone with restarts). Writes ``recovery.json`` (per grid point: bias and
spread of n1, mu_s, mu_a and mu_t = mu_s + mu_a, convergence, reduced chi-square) and
``recovery.png`` (fitted against true).

    python experiments/study_recovery.py --config configs/studies/recovery.toml --out out/recovery
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

import tofjax
from tofjax.config import from_dict, load_toml
from tofjax.fit.calibrate import Calibrator
from tofjax.outputs import atomic_write_text, save_figure
from tofjax.scene import load_scene
from tofjax.study_cli import RecoveryStudy, recovery_point, simulate_item


# the grid's keys (configs/studies/recovery.toml), validated: the same dataclass `tofjax study` runs
RecoveryConfig = RecoveryStudy


def run(config: RecoveryConfig, out: Path, progress: bool = True) -> dict:
    nominal = load_scene(config.scene)
    calibrator = Calibrator(nominal)
    items = config.items()
    t0 = time.perf_counter()
    caps = [simulate_item(config, nominal, item) for item in items]
    t_fit = time.perf_counter()
    results = calibrator.fit_many(caps)
    fit_seconds = time.perf_counter() - t_fit
    reps = config.replicates
    rows = []
    for k in range(len(items) // reps):
        fits = []
        for res in results[k * reps : (k + 1) * reps]:
            v = {p: float(res.values[p]) for p in ("n1", "mu_s_per_m", "mu_a_per_m")}
            fits.append({**v, "converged": res.converged, "result": res.result, "reduced_chi2": res.reduced_chi2})
        rows.append(recovery_point(items[k * reps][2], fits))
    result = {
        "study": "parameter recovery",
        "data": "simulated",
        "config": dataclasses.asdict(config),
        "seconds": time.perf_counter() - t0,
        "fit_seconds_batched": fit_seconds,
        "points": rows,
    }
    atomic_write_text(out / "recovery.json", json.dumps(result, indent=2))
    _plot(rows, out / "recovery.png")
    return result


def _plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(11, 3.6))
    for ax, p in zip(axes, ("n1", "mu_s_per_m", "mu_a_per_m")):
        t = np.array([r["truth"][p] for r in rows for _ in r["fits"]])
        f = np.array([fit[p] for r in rows for fit in r["fits"]])
        ax.plot(t, f, "o", ms=4, alpha=0.6)
        lim = [min(t.min(), f.min()), max(t.max(), f.max())]
        ax.plot(lim, lim, "k--", lw=0.8)
        ax.set_xlabel(f"true {p}")
        ax.set_ylabel(f"fitted {p}")
    fig.suptitle("calibration recovery (simulated baselines)")
    fig.tight_layout()
    save_figure(fig, path, dpi=100)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default="configs/studies/recovery.toml")
    ap.add_argument("--out", default="out/recovery")
    args = ap.parse_args(argv)
    tofjax.enable_x64()
    config = from_dict(RecoveryConfig, load_toml(args.config))
    result = run(config, Path(args.out))
    for r in result["points"]:
        t = r["truth"]
        print(
            f"n1 {t['n1']:.2f} mu_s {t['mu_s_per_m']:.2f} mu_a {t['mu_a_per_m']:.2f}: bias n1 {r['bias']['n1']:+.2e}, "
            f"mu_t {r['bias']['mu_t']:+.3f} (spread {r['spread']['mu_t']:.3f}), converged {r['converged']}/{len(r['fits'])}"
        )
    print(f"wrote {args.out}/recovery.json and recovery.png ({result['seconds']:.0f} s)")


if __name__ == "__main__":
    main()
