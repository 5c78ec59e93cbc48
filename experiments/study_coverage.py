"""Study: coverage of the calibration's 95% intervals (Laplace and posterior).

Simulates ``replicates`` baselines of one (small) scene with known parameters, fits each,
and counts how often the Laplace 95% interval of n1, mu_s, mu_a and mu_s + mu_a contains
the truth; for the first ``posterior_replicates`` it also samples the posterior and counts
the same for its 95% intervals. ``sampler = "nuts"`` (default: ``chains`` x (``warmup`` +
``draws``), compiled once for every replicate) or ``"emcee"`` (``walkers``, up to
``max_steps`` or 50 autocorrelation times). The posterior is
:func:`tofjax.fit.posterior.log_density` with the nuisance prior of width
``nuisance_width`` (centred on the truth here: the scene's values are the prior's centre).
A well-calibrated interval covers 95% of the time; each coverage p over R replicates is
reported with its binomial standard error sqrt(p (1 - p) / R), and the nominal one,
sqrt(0.95 x 0.05 / R) (2.2% at R = 100).

All point fits run first, then the posteriors; ``coverage.json`` is rewritten after the fits
and after every posterior, so a long run that is stopped still leaves its counts; ``coverage.md`` and ``coverage.png`` come at the end.

    python experiments/study_coverage.py --config configs/studies/coverage.toml --out out/coverage
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

import tofjax
from tofjax.config import ConfigError, from_dict, load_toml
from tofjax.fit.calibrate import Calibrator
from tofjax.outputs import atomic_write_text, save_figure
from tofjax.scene import SensorModel, load_scene
from tofjax.simulate import simulate

QUANTITIES = ("n1", "mu_s_per_m", "mu_a_per_m", "mu_t")


@dataclass(frozen=True)
class CoverageConfig:
    scene: str = "optoskin"
    sensors: int = 3
    zones: int = 3
    bins: int = 96
    frames: int = 40
    replicates: int = 100
    posterior_replicates: int = 100
    walkers: int = 32
    max_steps: int = 2500
    seed: int = 20000
    sampler: str = "nuts"
    chains: int = 2
    warmup: int = 200
    draws: int = 300
    nuisance_width: float = 0.3
    pilot: bool = False
    target_accept: float = 0.8
    gain_prior: str = "log-uniform"

    def __post_init__(self):
        if self.sampler not in ("nuts", "emcee"):
            raise ConfigError(f"sampler: must be nuts or emcee, got {self.sampler!r}")


def small_scene(config: CoverageConfig):
    scene = load_scene(config.scene)
    sm = scene.sensor
    small = SensorModel(
        bin_width_s=sm.bin_width_s, n_bins=config.bins, zones=config.zones, fov_deg=sm.fov_deg * config.zones / sm.zones
    )
    return scene.replace(sensor=small, sensors=scene.sensors[: config.sensors])


def laplace_intervals(res) -> dict[str, tuple[float, float]]:
    """The fit's 95% intervals; mu_t's from the covariance, symmetric in log(mu_t)."""
    out = {k: (float(res.interval95[k][0]), float(res.interval95[k][1])) for k in QUANTITIES[:3]}
    i, j = res.labels.index("mu_s_per_m"), res.labels.index("mu_a_per_m")
    c = res.covariance
    mu_t = float(res.values["mu_s_per_m"] + res.values["mu_a_per_m"])
    sd = math.sqrt(max(c[i, i] + c[j, j] + 2 * c[i, j], 0.0)) / mu_t
    out["mu_t"] = (mu_t * math.exp(-1.96 * sd), mu_t * math.exp(1.96 * sd))
    return out


def posterior_intervals(post) -> dict[str, tuple[float, float]]:
    s = post.samples
    cols = {k: s[:, post.names.index(k)] for k in QUANTITIES[:3]}
    cols["mu_t"] = cols["mu_s_per_m"] + cols["mu_a_per_m"]
    return {k: tuple(float(x) for x in np.percentile(v, [2.5, 97.5])) for k, v in cols.items()}


def _summary(rows, key) -> dict:
    used = [r for r in rows if r.get(key)]
    n = len(used)
    if not n:
        return {"replicates": 0}
    cover = {q: sum(r[key][q]["covers"] for r in used) for q in QUANTITIES}
    p = {q: cover[q] / n for q in QUANTITIES}
    return {
        "replicates": n,
        "coverage": p,
        "coverage_stderr": {q: math.sqrt(max(p[q] * (1 - p[q]), 0.25 / n) / n) for q in QUANTITIES},
        "within_90_98": {q: 0.90 <= p[q] <= 0.98 for q in QUANTITIES},
        "binomial_stderr": math.sqrt(0.95 * 0.05 / n),
        "median_width": {q: float(np.median([r[key][q]["width"] for r in used])) for q in QUANTITIES},
    }


def comparison(rows) -> dict:
    """Per quantity, Laplace against posterior coverage: each p +- its binomial standard error
    over its own replicates, whether it is within the 90-98% target, and whether it matches the
    nominal 95% (within 1.96 nominal binomial errors, sqrt(0.95 x 0.05 / R)); on the replicates
    with both intervals, how many only the Laplace one covers and how many only the posterior's
    (the paired, McNemar, view of their difference)."""
    out = {}
    both = [r for r in rows if r.get("laplace") and r.get("posterior")]
    for q in QUANTITIES:
        e = {}
        for key in ("laplace", "posterior"):
            used = [r for r in rows if r.get(key)]
            n = len(used)
            if not n:
                continue
            p = sum(r[key][q]["covers"] for r in used) / n
            nominal_se = math.sqrt(0.95 * 0.05 / n)
            e[key] = {
                "replicates": n,
                "coverage": p,
                "stderr": math.sqrt(max(p * (1 - p), 0.25 / n) / n),
                "within_90_98": 0.90 <= p <= 0.98,
                "matches_nominal_95": abs(p - 0.95) <= 1.96 * nominal_se,
                "z_vs_nominal": (p - 0.95) / nominal_se,
                # the interval's width as a standard deviation of log(quantity): ln(hi / lo) / (2 x 1.96)
                "median_sd_log": _median([math.log(r[key][q]["interval"][1] / r[key][q]["interval"][0]) / 3.92
                                          for r in used if r[key][q]["interval"][0] > 0]),
            }
        e["paired_replicates"] = len(both)
        e["only_laplace_covers"] = sum(1 for r in both if r["laplace"][q]["covers"] and not r["posterior"][q]["covers"])
        e["only_posterior_covers"] = sum(1 for r in both if r["posterior"][q]["covers"] and not r["laplace"][q]["covers"])
        out[q] = e
    return out


def _finite(xs) -> np.ndarray:
    a = np.asarray(xs, np.float64)
    return a[np.isfinite(a)]


def _median(xs) -> float:
    a = _finite(xs)
    return float(np.median(a)) if a.size else float("nan")


def sampler_stats(rows) -> dict:
    """ESS, R-hat, divergences and time of the NUTS posteriors (each replicate's ``posterior_seconds``:
    finding the mode, warm-up and draws, compiling excluded)."""
    post = [r for r in rows if "posterior_ess_min" in r]
    if not post:
        return {"posteriors": 0}
    ess = np.array([r["posterior_ess_min"] for r in post])
    rhat = np.array([r["posterior_rhat_max"] for r in post])
    div = np.array([r["posterior_divergences"] for r in post])
    sec = np.array([r.get("posterior_seconds", np.nan) for r in post])
    pct = (10, 25, 50, 75, 90)
    return {
        "posteriors": len(post),
        "ess_min_percentiles_10_25_50_75_90": [float(x) for x in np.percentile(ess, pct)],
        "ess_min_at_least_200": int(np.sum(ess >= 200)),
        **{f"ess_{q}_median": _median([r.get("posterior_ess_n1_mu", {}).get(q, np.nan) for r in post])
           for q in QUANTITIES[:3]},
        "rhat_max_percentiles_10_25_50_75_90": [float(x) for x in np.percentile(rhat, pct)],
        "rhat_max_at_most_1_01": int(np.sum(rhat <= 1.01)),
        "replicates_with_divergences": int(np.sum(div > 0)),
        "divergences_total": int(div.sum()),
        "divergences_median": float(np.median(div)),
        "divergences_max": int(div.max()),
        "seconds_per_posterior_median": _median(sec),
        "seconds_per_posterior_percentiles_10_90": [float(x) for x in np.percentile(_finite(sec), (10, 90))]
        if _finite(sec).size
        else None,
    }


def run(config: CoverageConfig, out: Path, progress: bool = True) -> dict:
    from tofjax.fit.nuts import NutsOptions, sample_nuts
    from tofjax.fit.posterior import PosteriorOptions, sample_posterior

    scene = small_scene(config)
    truth = {k: float(getattr(scene.waveguide, k)) for k in QUANTITIES[:3]}
    truth["mu_t"] = truth["mu_s_per_m"] + truth["mu_a_per_m"]
    cal = Calibrator(scene)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    t0 = time.perf_counter()
    fit_s = post_s = 0.0

    def result(final: bool) -> dict:
        return {
            "study": "interval coverage",
            "data": "simulated",
            "machine": f"{os.cpu_count()} CPUs shared with other jobs (load average now {os.getloadavg()[0]:.1f})",
            "config": dataclasses.asdict(config),
            "scene": f"{config.sensors} sensors x {config.zones} zones x {config.bins} bins of {config.scene}, "
            f"{config.frames} frames per baseline",
            "truth": truth,
            "finished": final,
            "seconds": time.perf_counter() - t0,
            "seconds_fits": fit_s,
            "seconds_posteriors": post_s,
            "laplace": _summary(rows, "laplace"),
            "posterior": _summary(rows, "posterior"),
            "comparison": comparison(rows),
            "sampler_stats": sampler_stats(rows),
            "seconds_per_posterior": post_s / max(sum(1 for r in rows if r.get("posterior")), 1),
            "posterior_replicates_with_divergences": sum(1 for r in rows if r.get("posterior_divergences")),
            "posterior_ess_min_median": float(np.median([r["posterior_ess_min"] for r in rows if "posterior_ess_min" in r]))
            if any("posterior_ess_min" in r for r in rows)
            else float("nan"),
            "posterior_reached_50_tau": sum(1 for r in rows if r.get("posterior_converged")),
            "posterior_rhat_max_median": float(np.median([r["posterior_rhat_max"] for r in rows if "posterior_rhat_max" in r]))
            if any("posterior_rhat_max" in r for r in rows)
            else float("nan"),
            "posterior_tau_median": float(np.median([r["posterior_tau_max"] for r in rows if "posterior_tau_max" in r]))
            if any("posterior_tau_max" in r for r in rows)
            else float("nan"),
            "replicates_run": rows,
        }

    # all the point fits first (fit_many: one vmapped call on an accelerator, a loop on a CPU); then the posteriors
    # (expensive) of the first ones
    caps = {}
    captures = [simulate(scene, config.frames, seed=config.seed + k) for k in range(config.replicates)]
    t = time.perf_counter()
    fits = cal.fit_many(captures)
    fit_s += time.perf_counter() - t
    for k, (cap, res) in enumerate(zip(captures, fits)):
        row = {"seed": config.seed + k, "converged": res.converged, "result": res.result, "reduced_chi2": res.reduced_chi2}
        row["laplace"] = {
            q: {"interval": list(iv), "covers": bool(iv[0] <= truth[q] <= iv[1]), "width": iv[1] - iv[0]}
            for q, iv in laplace_intervals(res).items()
        }
        rows.append(row)
        if k < config.posterior_replicates and res.converged:
            caps[k] = (cap, res)
    atomic_write_text(out / "coverage.json", json.dumps(result(False), indent=1))
    for k, (cap, res) in tqdm(caps.items(), desc="posteriors", disable=not progress):
        t = time.perf_counter()
        if config.sampler == "nuts":
            opts = NutsOptions(chains=config.chains, warmup=config.warmup, draws=config.draws, seed=config.seed + k,
                               nuisance_width=config.nuisance_width, pilot=config.pilot, target_accept=config.target_accept,
                               gain_prior=config.gain_prior)
            post = sample_nuts(cal, cap, res, opts)
        else:
            post = sample_posterior(cal, cap, res, PosteriorOptions(
                walkers=config.walkers, max_steps=config.max_steps, seed=config.seed + k, progress=False, nuisance_width=config.nuisance_width,
                gain_prior=config.gain_prior))
        post_s += time.perf_counter() - t
        row = rows[k]
        row["posterior"] = {
            q: {"interval": list(iv), "covers": bool(iv[0] <= truth[q] <= iv[1]), "width": iv[1] - iv[0]}
            for q, iv in posterior_intervals(post).items()
        }
        if config.sampler == "nuts":
            d = post.diagnostics
            row["posterior_rhat_max"] = d["rhat_max"]
            row["posterior_ess_min"] = d["ess_min"]
            row["posterior_ess_n1_mu"] = {q: min(d["ess_bulk"][q], d["ess_tail"][q]) for q in QUANTITIES[:3]}
            row["posterior_divergences"] = post.divergences
            row["posterior_seconds"] = post.wall_s
        else:
            row["posterior_converged"] = post.converged
            row["posterior_steps"] = post.steps
            row["posterior_tau_max"] = float(np.nanmax(post.tau))
        atomic_write_text(out / "coverage.json", json.dumps(result(False), indent=1))
    r = result(True)
    atomic_write_text(out / "coverage.json", json.dumps(r, indent=1))
    atomic_write_text(out / "coverage.md", markdown(r))
    plot(r, out / "coverage.png")
    return r


def merge(parts: list[dict]) -> dict:
    """One result from runs of the same settings side by side, each from its own ``seed`` (the
    runs may overlap: a replicate seed is one simulated capture, counted once)."""
    by_seed: dict = {}
    for r in parts:  # a seed in two parts is the same simulated capture: keep one row, with a posterior if either has
        for row in r["replicates_run"]:
            if row["seed"] not in by_seed or (row.get("posterior") and not by_seed[row["seed"]].get("posterior")):
                by_seed[row["seed"]] = row
    rows = [by_seed[k] for k in sorted(by_seed)]
    keys = ("sensors", "zones", "bins", "frames", "sampler", "chains", "warmup", "draws", "nuisance_width", "pilot", "target_accept",
            "gain_prior")
    for r in parts[1:]:
        if any(r["config"].get(k) != parts[0]["config"].get(k) for k in keys):
            raise ValueError("merge: the parts differ in their settings")
    out = dict(parts[0])
    post = [r for r in rows if "posterior_rhat_max" in r]
    n_post = max(len(post), 1)
    out.update(
        finished=all(r["finished"] for r in parts),
        parts=[{"seed": r["config"]["seed"], "replicates": r["config"]["replicates"], "finished": r["finished"],
                "posteriors": r["posterior"]["replicates"], "seconds": r["seconds"]} for r in parts],
        seconds=max(r["seconds"] for r in parts),
        seconds_fits=sum(r["seconds_fits"] for r in parts),
        seconds_posteriors=sum(r["seconds_posteriors"] for r in parts),
        laplace=_summary(rows, "laplace"),
        posterior=_summary(rows, "posterior"),
        comparison=comparison(rows),
        sampler_stats=sampler_stats(rows),
        seconds_per_posterior=sum(r["seconds_posteriors"] for r in parts) / n_post,
        posterior_replicates_with_divergences=sum(1 for r in post if r.get("posterior_divergences")),
        posterior_ess_min_median=float(np.median([r["posterior_ess_min"] for r in post])) if post else float("nan"),
        posterior_rhat_max_median=float(np.median([r["posterior_rhat_max"] for r in post])) if post else float("nan"),
        replicates_run=rows,
    )
    return out


def markdown(r: dict) -> str:
    c = r["config"]
    lines = [
        f"# Interval coverage ({r['data']}: {r['scene']})",
        "",
        f"{r['laplace']['replicates']} replicates with a Laplace interval, {r['posterior']['replicates']} with a "
        + (
            f"NUTS posterior ({c['chains']} chains x ({c['warmup']} warm-up + {c['draws']} draws)"
            + (", after a pilot run of the same length" if c.get("pilot") else "")
            + f", slow pulse tail held at the fit, nuisance prior width "
            f"{c['nuisance_width']}; median of the largest R-hat {r['posterior_rhat_max_median']:.3f}, of the smallest "
            f"ESS {r['posterior_ess_min_median']:.0f}; divergences in {r['posterior_replicates_with_divergences']} replicates"
            if c["sampler"] == "nuts"
            else f"emcee posterior ({c['walkers']} walkers, up to {c['max_steps']} steps or 50 tau; "
            f"{r['posterior_reached_50_tau']} reached 50 tau; median tau {r['posterior_tau_median']:.0f} steps"
        )
        + f"; {r['seconds_per_posterior']:.1f} s per posterior). Target: 95% nominal, 90-98% accepted. "
        f"Run time {r['seconds']:.0f} s (fits {r['seconds_fits']:.0f} s, posteriors {r['seconds_posteriors']:.0f} s). "
        "Each coverage +- its binomial standard error.",
        "",
        "| interval | n1 | mu_s | mu_a | mu_s + mu_a | nominal binomial stderr |",
        "|---|---|---|---|---|---|",
    ]
    for key in ("laplace", "posterior"):
        s = r[key]
        if s["replicates"]:
            lines.append(
                f"| {key} ({s['replicates']}) | "
                + " | ".join(f"{100 * s['coverage'][q]:.0f} +- {100 * s['coverage_stderr'][q]:.0f}%" for q in QUANTITIES)
                + f" | {100 * s['binomial_stderr']:.1f}% |"
            )
    comp = r.get("comparison")
    if comp:
        lines += [
            "",
            "| quantity | Laplace | posterior | only Laplace covers | only posterior covers |",
            "|---|---|---|---|---|",
        ]

        def cell(e):
            if not e:
                return "-"
            tags = ("in 90-98%" if e["within_90_98"] else "outside 90-98%") + (
                ", matches 95%" if e["matches_nominal_95"] else ", not 95%")
            return f"{100 * e['coverage']:.1f} +- {100 * e['stderr']:.1f}% ({tags})"

        for q in QUANTITIES:
            e = comp[q]
            lines.append(f"| {q} | {cell(e.get('laplace'))} | {cell(e.get('posterior'))} | {e['only_laplace_covers']} | "
                         f"{e['only_posterior_covers']} |")
        lines.append("")
        lines.append("'matches 95%': within 1.96 nominal binomial errors of 0.95.")
    return "\n".join(lines) + "\n"


def plot(r: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = r["replicates_run"]
    fig, axes = plt.subplots(1, len(QUANTITIES), figsize=(13, 4.2))
    for ax, q in zip(axes, QUANTITIES):
        for key, colour, dx in (("laplace", "C0", -0.15), ("posterior", "C1", 0.15)):
            used = [(i, row[key][q]["interval"], row[key][q]["covers"]) for i, row in enumerate(rows) if row.get(key)]
            for i, (lo, hi), ok in used:
                ax.plot([i + dx, i + dx], [lo, hi], color=colour if ok else "red", lw=0.8)
        ax.axhline(r["truth"][q], color="k", lw=0.8)
        cov = {k: r[k]["coverage"][q] for k in ("laplace", "posterior") if r[k]["replicates"]}
        ax.set_title(q + "\n" + ", ".join(f"{k} {100 * v:.0f}%" for k, v in cov.items()), fontsize=9)
        ax.set_xlabel("replicate")
        if q in ("mu_s_per_m", "mu_a_per_m"):
            ax.set_yscale("log")
    fig.suptitle("95% intervals against the truth (simulated; blue Laplace, orange posterior, red: missed)", fontsize=10)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default="configs/studies/coverage.toml")
    ap.add_argument("--out", default="out/coverage")
    ap.add_argument("--merge", nargs="+", metavar="JSON", help="merge these coverage.json (runs on different seeds) into --out")
    ap.add_argument("--note", default=None, help="with --merge: a note stored in the merged coverage.json")
    args = ap.parse_args(argv)
    if args.merge:
        r = merge([json.loads(Path(p).read_text()) for p in args.merge])
        if args.note:
            r = {"note": args.note, **r}
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out / "coverage.json", json.dumps(r, indent=1))
        atomic_write_text(out / "coverage.md", markdown(r))
        plot(r, out / "coverage.png")
        print(markdown(r))
        return
    tofjax.enable_x64()
    from tofjax.compile_cache import enable_compilation_cache

    enable_compilation_cache()  # the user cache: a rerun skips compiling the model, the fit and NUTS
    config = from_dict(CoverageConfig, load_toml(args.config), where=args.config)
    r = run(config, Path(args.out))
    print(markdown(r))


if __name__ == "__main__":
    main()
