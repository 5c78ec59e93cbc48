"""Study: calibration speed against accuracy, and against scipy's least_squares.

1. Fit settings. On simulated baselines of one scene, every fit setting of the config
   (solver, tolerances, the loss stopping rule, the Gauss-Newton fast path, float32 /
   float64, quadrature) is compiled once (the compile time is recorded) and timed warm on
   the same captures: the whole fit (start, solve, covariance) and the solve alone. Its
   error is measured against a tight reference fit of each capture (in units of the
   reference's Laplace standard errors: the error the setting adds on top of the
   statistical one) and against the truth.
2. The usual tool. The same profiled residuals and JAX Jacobian go through
   ``scipy.optimize.least_squares`` from the same start as tofjax's default; the warm solve
   times are measured side by side, interleaved, on the same captures.
3. emcee steps against interval accuracy. One posterior run on a small scene; the 95%
   intervals from its first N steps are compared with those from the whole chain.

Writes ``fit_speed.json``, ``fit_speed.md`` and ``fit_speed.png``.

    python experiments/study_fit_speed.py --config configs/studies/fit_speed.toml --out out/fit_speed
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import time
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

import tofjax
from tofjax.config import from_dict, load_toml
from tofjax.fit._start import envelope_candidates, timing_start
from tofjax.fit.calibrate import Calibrator, FitConfig, _anchor, fit_problem
from tofjax.scene import SensorModel, load_scene
from tofjax.simulate import simulate

TARGETS = ("n1", "mu_s_per_m", "mu_a_per_m")
LINEAR = ("gain", "ambient_counts", "crosstalk_counts")


@dataclass(frozen=True)
class Setting:
    """One fit setting: FitConfig keys that differ from the defaults."""

    label: str
    solver: str = "levenberg-marquardt"
    rtol: float = 1e-7
    atol: float = 1e-7
    loss_tol: float = 1e-3
    gauss_newton_first: int = 10
    dtype: str = "float64"
    quadrature: int = 2


@dataclass(frozen=True)
class EmceeStudy:
    """Posterior on a small scene (``sensors`` of the scene, ``zones``, ``bins``)."""

    sensors: int = 3
    zones: int = 3
    bins: int = 96
    frames: int = 60
    max_steps: int = 3000
    walkers: int = 32
    steps: tuple[int, ...] = (250, 500, 1000, 2000)
    seed: int = 7


@dataclass(frozen=True)
class FitSpeedConfig:
    """``sensors``, ``zones``, ``bins``: cut the scene down (0 = as it is; tests use a small one)."""

    scene: str = "optoskin"
    sensors: int = 0
    zones: int = 0
    bins: int = 0
    frames: int = 100
    captures: int = 5
    seed: int = 100
    repeats: int = 3
    settings: tuple[Setting, ...] = (Setting("default"),)
    scipy_methods: tuple[str, ...] = ("trf", "lm")
    scipy_jacobians: tuple[str, ...] = ("jax", "2-point")
    scipy_tol: float = 1e-8
    emcee: EmceeStudy | None = EmceeStudy()


def _fit_config(s: Setting, **over) -> FitConfig:
    kw = {k: v for k, v in dataclasses.asdict(s).items() if k != "label"}
    return FitConfig(**(kw | over))


def _errors(res, ref, truth) -> dict:
    """Error of a fit against the reference fit (in its standard errors) and the truth."""
    names = [k for k in ref.free if k not in LINEAR]
    z = {k: float(np.max(np.abs(np.ravel(res.values[k]) - np.ravel(ref.values[k])) / np.ravel(ref.stderr[k]))) for k in names}
    mu_t = float(res.values["mu_s_per_m"] + res.values["mu_a_per_m"])
    return {
        "z_max_targets": max(z[k] for k in TARGETS),
        "z_max_all": max(z.values()),
        "n1_rel_error": abs(float(res.values["n1"]) / truth["n1"] - 1),
        "mu_t_rel_error": abs(mu_t / (truth["mu_s_per_m"] + truth["mu_a_per_m"]) - 1),
    }


def _data(calibrator: Calibrator, cap):
    dtype = calibrator.problem.model.geometry.ray_length.dtype
    mean = cap.mean()
    return jnp.asarray(mean, dtype), jnp.asarray(np.sqrt(np.maximum(mean, 1.0) / cap.n_frames), dtype)


def _start(calibrator: Calibrator, cap):
    """The calibration's own start: timing, then the envelope's best grid point."""
    problem = calibrator.problem
    base = calibrator.base_params()
    data, sigma = _data(calibrator, cap)
    start, found = timing_start(problem, np.asarray(data), cap.n_frames, calibrator.scene, base)
    anchor = _anchor(start, found, calibrator.config, data.dtype)
    if calibrator.config.envelope:
        start = envelope_candidates(problem, start, data, sigma, 1)[0]
    return (start, anchor), base


def _solve_runner(calibrator: Calibrator):
    """The compiled solve of ``calibrator``'s setting without the covariance (what scipy is
    compared with): start, solve, profile the end point."""
    cfg = calibrator.config
    problem, solver, objective = calibrator.problem, cfg.make_solver(), cfg.make_objective()

    def run(start_anchor, data, sigma, base):
        start, anchor = start_anchor
        sol = fit_problem(
            problem, objective, solver, start, data, sigma, base, anchor,
            max_steps=cfg.max_steps, loss_tol=cfg.loss_tol, gn_first=cfg.gn_first, with_cov=False,
        )
        return {"params": sol.params, "steps": sol.steps, "result": sol.result}

    return run


def _time_solve(calibrator: Calibrator, cap, repeats: int) -> tuple[float, object]:
    """Median warm time of the solve alone (start from the data included), and its end point."""
    run = _solve_runner(calibrator)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        start, base = _start(calibrator, cap)
        data, sigma = _data(calibrator, cap)
        out = jax.block_until_ready(run(start, data, sigma, base))
        times.append(time.perf_counter() - t)
    return float(np.median(times)), out


def _scipy_problem(calibrator: Calibrator):
    """Jitted residuals and JAX Jacobian of the same profiled problem, for scipy (compiled once)."""
    problem = calibrator.problem
    base = calibrator.base_params()
    u = problem.pack(base)
    _, unravel = jax.flatten_util.ravel_pytree(u)
    f = jax.jit(lambda x, args: problem.residuals(unravel(x), args))
    jac = jax.jit(jax.jacfwd(lambda x, args: problem.residuals(unravel(x), args)))
    return f, jac, unravel


def _scipy_solve(calibrator: Calibrator, sp, cap, method: str, tol: float, jacobian: str, repeats: int):
    """The same profiled residuals through scipy.optimize.least_squares from the same start,
    with the JAX Jacobian (``"jax"``) or scipy's own finite differences (``"2-point"``)."""
    from scipy.optimize import least_squares

    problem = calibrator.problem
    f, jac, _ = sp
    profile = jax.jit(lambda p, d, g: problem.profile(p, d, g)[0])
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        start, base = _start(calibrator, cap)
        data, sigma = _data(calibrator, cap)
        p0 = profile(start[0], data, sigma)
        args = (p0, data, sigma, {**problem.pack(base), "n1_anchor": start[1]})
        x0 = np.asarray(jax.flatten_util.ravel_pytree(problem.pack(p0))[0], np.float64)
        out = least_squares(
            lambda x: np.asarray(f(x, args), np.float64),
            x0,
            jac=(lambda x: np.asarray(jac(x, args), np.float64)) if jacobian == "jax" else jacobian,
            method=method,
            xtol=tol,
            ftol=tol,
            gtol=tol,
            max_nfev=2000,
        )
        times.append(time.perf_counter() - t)
    return float(np.median(times)), out.x, int(out.nfev)


_CALIBRATORS: dict = {}


def _calibrator(scene, config: FitConfig) -> Calibrator:
    """One calibrator (one compilation) per scene and setting."""
    key = (id(scene), config)
    if key not in _CALIBRATORS:
        _CALIBRATORS[key] = Calibrator(scene, config)
    return _CALIBRATORS[key]


def run_settings(config: FitSpeedConfig, scene, caps, refs, truth, progress: bool) -> list[dict]:
    rows = []
    for s in tqdm(config.settings, desc="settings", disable=not progress):
        cal = _calibrator(scene, _fit_config(s))
        t = time.perf_counter()
        cal.fit(caps[0])  # compiles
        first = time.perf_counter() - t
        _time_solve(cal, caps[0], 1)  # compiles the solve without covariance
        times, steps, errs, conv, solve_times = [], [], [], [], []
        for cap, ref in zip(caps, refs):
            ts = []
            for _ in range(config.repeats):
                t = time.perf_counter()
                res = cal.fit(cap)
                ts.append(time.perf_counter() - t)
            times.append(float(np.median(ts)))
            steps.append(res.steps)
            conv.append(res.converged)
            errs.append(_errors(res, ref, truth))
            solve_times.append(_time_solve(cal, cap, config.repeats)[0])
        rows.append(
            {
                "setting": dataclasses.asdict(s),
                "first_fit_s": first,
                "warm_fit_s_median": float(np.median(times)),
                "warm_fit_s": times,
                "warm_solve_s_median": float(np.median(solve_times)),
                "steps_median": float(np.median(steps)),
                "steps": steps,
                "converged": int(sum(conv)),
                "z_max_targets_median": float(np.median([e["z_max_targets"] for e in errs])),
                "z_max_targets_max": float(np.max([e["z_max_targets"] for e in errs])),
                "z_max_all_max": float(np.max([e["z_max_all"] for e in errs])),
                "n1_rel_error_max": float(np.max([e["n1_rel_error"] for e in errs])),
                "mu_t_rel_error_max": float(np.max([e["mu_t_rel_error"] for e in errs])),
            }
        )
    return rows


def run_scipy(config: FitSpeedConfig, scene, caps, refs) -> dict:
    """tofjax's default solve and scipy's, interleaved on the same captures and starts."""
    default = _calibrator(scene, FitConfig())
    default.fit(caps[0])
    _time_solve(default, caps[0], 1)
    sp = _scipy_problem(default)
    methods = [f"{m} {j}" for m in config.scipy_methods for j in config.scipy_jacobians]
    runs = []
    for cap, ref in zip(caps, refs):
        problem = default.problem
        ours, out = _time_solve(default, cap, config.repeats)
        x_ours = np.asarray(jax.flatten_util.ravel_pytree(problem.pack(out["params"]))[0])
        flat_ref = np.asarray(jax.flatten_util.ravel_pytree(problem.pack(ref.params))[0])
        sd = np.concatenate([np.ravel(ref.unconstrained_stderr[k]) for k in sorted(problem.pack(ref.params))])
        row = {"tofjax_solve_s": ours, "tofjax_steps": int(out["steps"]), "tofjax_z_max": float(np.max(np.abs(x_ours - flat_ref) / sd))}
        for m in methods:
            method, jacobian = m.split(" ")
            dt, x, nfev = _scipy_solve(default, sp, cap, method, config.scipy_tol, jacobian, config.repeats)
            row[f"scipy_{m}_s"] = dt
            row[f"scipy_{m}_nfev"] = nfev
            row[f"scipy_{m}_z_max"] = float(np.max(np.abs(x - flat_ref) / sd))
            row[f"scipy_{m}_vs_tofjax_z_max"] = float(np.max(np.abs(x - x_ours) / sd))
            row[f"ratio_scipy_{m}_over_tofjax"] = dt / ours
        runs.append(row)

    def med(key):
        return float(np.median([r[key] for r in runs]))

    return {
        "tofjax_warm_solve_s_median": med("tofjax_solve_s"),
        "tofjax_z_max_median": med("tofjax_z_max"),
        "methods": {
            m: {
                "warm_solve_s_median": med(f"scipy_{m}_s"),
                "nfev_median": med(f"scipy_{m}_nfev"),
                "ratio_over_tofjax_median": med(f"ratio_scipy_{m}_over_tofjax"),
                "z_max_vs_reference_median": med(f"scipy_{m}_z_max"),
                "z_max_vs_tofjax_median": med(f"scipy_{m}_vs_tofjax_z_max"),
            }
            for m in methods
        },
        "runs": runs,
    }


def small_scene(scene, sensors: int, zones: int, bins: int):
    """The scene cut down to a few sensors, zones and bins (same physics, faster); 0 keeps it."""
    sm = scene.sensor
    zones, bins, sensors = zones or sm.zones, bins or sm.n_bins, sensors or len(scene.sensors)
    if (zones, bins, sensors) == (sm.zones, sm.n_bins, len(scene.sensors)):
        return scene
    small = SensorModel(bin_width_s=sm.bin_width_s, n_bins=bins, zones=zones, fov_deg=sm.fov_deg * zones / sm.zones)
    return scene.replace(sensor=small, sensors=scene.sensors[:sensors])


def run_emcee(e: EmceeStudy, scene, progress: bool) -> dict:
    """95% intervals from the first N steps of one chain against those from the whole chain."""
    from tofjax.fit.posterior import PosteriorOptions, sample_posterior

    small = small_scene(scene, e.sensors, e.zones, e.bins)
    cap = simulate(small, e.frames, seed=e.seed)
    cal = Calibrator(small)
    fit = cal.fit(cap)
    t = time.perf_counter()
    post = sample_posterior(cal, cap, fit, PosteriorOptions(walkers=e.walkers, max_steps=e.max_steps, progress=progress))
    seconds = time.perf_counter() - t
    names = post.names
    chain = post.chain_physical  # (steps, walkers, P)
    cols = {k: chain[..., names.index(k)] for k in ("n1", "mu_s_per_m", "mu_a_per_m")}
    cols["mu_t"] = cols["mu_s_per_m"] + cols["mu_a_per_m"]
    tau = float(np.nanmax(post.tau))

    def interval(x, n):
        burn = min(int(2 * tau), n // 2)
        s = x[burn:n].ravel()
        return np.percentile(s, [2.5, 97.5])

    full = {k: interval(v, post.steps) for k, v in cols.items()}
    rows = []
    for n in [n for n in e.steps if n < post.steps] + [post.steps]:
        row = {"steps": n, "tau_multiple": n / tau}
        for k, v in cols.items():
            lo, hi = interval(v, n)
            width = full[k][1] - full[k][0]
            row[k] = {
                "interval95": [float(lo), float(hi)],
                "endpoint_error_over_width": float(max(abs(lo - full[k][0]), abs(hi - full[k][1])) / width),
                "width_ratio": float((hi - lo) / width),
            }
        rows.append(row)
    return {
        "scene": f"{e.sensors} sensors x {e.zones} zones x {e.bins} bins, {e.frames} frames (simulated)",
        "walkers": e.walkers,
        "steps_run": post.steps,
        "converged_50_tau": post.converged,
        "tau_max": tau,
        "acceptance": post.acceptance,
        "seconds": seconds,
        "truth": {k: float(getattr(small.waveguide, k)) for k in TARGETS},
        "rows": rows,
    }


def run(config: FitSpeedConfig, out: Path, progress: bool = True) -> dict:
    full = load_scene(config.scene)
    scene = small_scene(full, config.sensors, config.zones, config.bins)
    truth = {k: float(getattr(scene.waveguide, k)) for k in TARGETS}
    caps = [simulate(scene, config.frames, seed=config.seed + i) for i in range(config.captures)]
    # reference: Gauss-Newton run to its fixed point (12 steps, where it converges
    # quadratically; Levenberg-Marquardt would crawl for thousands of steps to the same point)
    ref_cal = _calibrator(scene, FitConfig(solver="gauss-newton", rtol=1e-12, atol=1e-12, loss_tol=0.0, max_steps=12))
    refs = [ref_cal.fit(c) for c in tqdm(caps, desc="reference fits", disable=not progress)]
    t0 = time.perf_counter()
    rows = run_settings(config, scene, caps, refs, truth, progress)
    scipy = run_scipy(config, scene, caps, refs)
    emcee_part = run_emcee(config.emcee, full, progress) if config.emcee is not None else None
    result = {
        "study": "calibration speed against accuracy",
        "data": "simulated",
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs shared with other jobs (load average at the end "
        f"{os.getloadavg()[0]:.1f}), JAX {jax.__version__} on {jax.devices()[0].device_kind}",
        "config": dataclasses.asdict(config),
        "scene": f"{config.scene}: {scene.shape[0]} sensors x {scene.shape[1]} zones x {scene.shape[2]} bins",
        "truth": truth,
        "references": [{"steps": r.steps, "reduced_chi2": r.reduced_chi2, "final_loss": r.loss_history[-1]} for r in refs],
        "settings": rows,
        "scipy": scipy,
        "emcee": emcee_part,
        "seconds": time.perf_counter() - t0,
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "fit_speed.json").write_text(json.dumps(result, indent=1))
    (out / "fit_speed.md").write_text(markdown(result))
    plot(result, out / "fit_speed.png")
    return result


def markdown(r: dict) -> str:
    c = r["config"]
    lines = [
        f"# Calibration speed against accuracy ({r['data']}, {r['scene']}, {c['frames']} frames, {c['captures']} captures)",
        "",
        f"Machine: {r['machine']}. Times are medians of {c['repeats']} warm runs per capture, then the median "
        "over captures; errors are against a tight reference fit, in units of its standard errors (z), and "
        "against the truth.",
        "",
        "| setting | solver | GN first | loss_tol | dtype | q | steps | warm fit ms | warm solve ms | compile+first fit s "
        "| z (n1, mu) median / max | z (all) max | n1 rel err max | mu_t rel err max | converged |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in r["settings"]:
        s = row["setting"]
        lines.append(
            f"| {s['label']} | {s['solver']} | {s['gauss_newton_first']} | {s['loss_tol']:g} | {s['dtype']} | {s['quadrature']} "
            f"| {row['steps_median']:.0f} | {1e3 * row['warm_fit_s_median']:.0f} | {1e3 * row['warm_solve_s_median']:.0f} "
            f"| {row['first_fit_s']:.1f} | {row['z_max_targets_median']:.3f} / {row['z_max_targets_max']:.3f} "
            f"| {row['z_max_all_max']:.3f} | {row['n1_rel_error_max']:.1e} | {row['mu_t_rel_error_max']:.1e} "
            f"| {row['converged']}/{len(row['steps'])} |"
        )
    sc = r["scipy"]
    lines += [
        "",
        "## Against scipy.optimize.least_squares",
        "",
        f"Same profiled residuals (jitted JAX), same start, interleaved on the same captures. tofjax default solve: "
        f"{1e3 * sc['tofjax_warm_solve_s_median']:.0f} ms (median), z vs reference {sc['tofjax_z_max_median']:.3f}.",
        "",
        "| method, Jacobian | warm solve ms | evaluations | scipy / tofjax time | z vs reference | z vs tofjax |",
        "|---|---|---|---|---|---|",
    ]
    for m, v in sc["methods"].items():
        lines.append(
            f"| {m} | {1e3 * v['warm_solve_s_median']:.0f} | {v['nfev_median']:.0f} | {v['ratio_over_tofjax_median']:.1f} | "
            f"{v['z_max_vs_reference_median']:.3f} | {v['z_max_vs_tofjax_median']:.3f} |"
        )
    e = r.get("emcee")
    if e:
        lines += [
            "",
            "## emcee steps against interval accuracy",
            "",
            f"{e['scene']}, {e['walkers']} walkers, {e['steps_run']} steps in {e['seconds']:.0f} s "
            f"(tau {e['tau_max']:.0f}, {'reached' if e['converged_50_tau'] else 'did NOT reach'} 50 tau, "
            f"acceptance {e['acceptance']:.2f}). Error of the 95% interval's end points from the first N steps "
            "against the whole chain's, as a fraction of the whole chain's interval width.",
            "",
            "| steps | x tau | n1 | mu_s + mu_a | mu_s | mu_a |",
            "|---|---|---|---|---|---|",
        ]
        for row in e["rows"]:
            lines.append(
                f"| {row['steps']} | {row['tau_multiple']:.0f} | "
                + " | ".join(f"{row[k]['endpoint_error_over_width']:.2f}" for k in ("n1", "mu_t", "mu_s_per_m", "mu_a_per_m"))
                + " |"
            )
    return "\n".join(lines) + "\n"


def plot(r: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = 2 if r.get("emcee") else 1
    fig, axes = plt.subplots(1, n, figsize=(6.5 * n, 4.5))
    ax = axes[0] if n == 2 else axes
    for row in r["settings"]:
        x, y = 1e3 * row["warm_solve_s_median"], max(row["z_max_targets_median"], 1e-4)
        ax.scatter(x, y, s=30)
        ax.annotate(row["setting"]["label"], (x, y), fontsize=7)
    for m, v in r["scipy"]["methods"].items():
        x, y = 1e3 * v["warm_solve_s_median"], max(v["z_max_vs_reference_median"], 1e-4)
        ax.scatter(x, y, marker="x", color="k")
        ax.annotate(f"scipy {m}", (x, y), fontsize=7)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("warm solve time [ms] (median)")
    ax.set_ylabel("error of n1, mu_s, mu_a [reference standard errors]")
    ax.set_title(f"fit settings and scipy ({r['data']})", fontsize=10)
    ax.axhline(0.1, color="0.7", lw=0.8, ls="--")
    if n == 2:
        ax = axes[1]
        e = r["emcee"]
        steps = [row["steps"] for row in e["rows"]]
        for k in ("n1", "mu_t", "mu_s_per_m", "mu_a_per_m"):
            ax.plot(steps, [max(row[k]["endpoint_error_over_width"], 1e-3) for row in e["rows"]], "o-", label=k)
        ax.axvline(50 * e["tau_max"], color="0.6", ls="--", lw=0.8, label="50 tau")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("emcee steps")
        ax.set_ylabel("95% interval end-point error / width")
        ax.set_title("emcee steps against interval accuracy", fontsize=10)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def load_config(path) -> FitSpeedConfig:
    return from_dict(FitSpeedConfig, load_toml(path), where=str(path))


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--config", default="configs/studies/fit_speed.toml")
    p.add_argument("--out", default="out/fit_speed")
    a = p.parse_args(argv)
    from tofjax.compile_cache import use_fast_cpu_compiler  # noqa: E402
    use_fast_cpu_compiler()  # the CLI's CPU compiler (before JAX's backend starts)
    tofjax.enable_x64()
    r = run(load_config(a.config), Path(a.out))
    print(markdown(r))


if __name__ == "__main__":
    main()
