"""Study: calibration speed against accuracy, and against scipy's least_squares.

On simulated baselines of one scene, every fit setting of the config (solver,
tolerances, the loss stopping rule, float32 / float64) is compiled once and timed
warm on the same captures. Its error is measured against a tight reference fit of
each capture (in units of the reference's Laplace standard errors: the error the
setting adds on top of the statistical one) and against the truth. The same
profiled residuals and Jacobian then go through ``scipy.optimize.least_squares``
from the same start, and the warm solve times are compared side by side.

Writes ``fit_speed.json``, ``fit_speed.md`` and ``fit_speed.png`` (time against error).

    python experiments/study_fit_speed.py --config configs/studies/fit_speed.toml --out out/fit_speed
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import time
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.flatten_util
import numpy as np
from tqdm import tqdm

import tofjax
from tofjax.config import from_dict, load_toml
from tofjax.fit.calibrate import Calibrator, FitConfig, _initial_params
from tofjax.scene import load_scene
from tofjax.simulate import simulate

TARGETS = ("n1", "mu_s_per_m", "mu_a_per_m")


@dataclass(frozen=True)
class Setting:
    """One fit setting: FitConfig keys that differ from the defaults."""

    label: str
    solver: str = "levenberg-marquardt"
    rtol: float = 1e-7
    atol: float = 1e-7
    loss_tol: float = 1e-3
    dtype: str = "float64"
    quadrature: int = 2


@dataclass(frozen=True)
class FitSpeedConfig:
    scene: str = "optoskin"
    frames: int = 100
    captures: int = 5
    seed: int = 100
    settings: tuple[Setting, ...] = (Setting("default"),)
    scipy_methods: tuple[str, ...] = ("trf", "lm")
    scipy_jacobians: tuple[str, ...] = ("jax", "2-point")
    scipy_tol: float = 1e-8


def _fit_config(s: Setting, **over) -> FitConfig:
    kw = {k: v for k, v in dataclasses.asdict(s).items() if k != "label"}
    return FitConfig(**(kw | over))


def _errors(res, ref, truth) -> dict:
    """Error of a fit against the reference fit (in its standard errors) and the truth."""
    names = [k for k in ref.free if k not in ("gain", "ambient_counts", "crosstalk_counts")]
    z = {k: float(np.max(np.abs(np.ravel(res.values[k]) - np.ravel(ref.values[k])) / np.ravel(ref.stderr[k]))) for k in names}
    mu_t = float(res.values["mu_s_per_m"] + res.values["mu_a_per_m"])
    return {
        "z_max_targets": max(z[k] for k in TARGETS),
        "z_max_all": max(z.values()),
        "n1_rel_error": abs(float(res.values["n1"]) / truth["n1"] - 1),
        "mu_t_rel_error": abs(mu_t / (truth["mu_s_per_m"] + truth["mu_a_per_m"]) - 1),
    }


def _time_solve(calibrator, cap) -> tuple[float, np.ndarray, object]:
    """Warm time of the solve alone (start from the data, no covariance), and its end point."""
    problem = calibrator._problem
    problem.set_data(cap.mean(), cap.n_frames)
    base = calibrator.base_params()
    start = problem.profile_jit(_initial_params(cap, calibrator.scene, base), problem.data, problem.sigma)
    cfg = calibrator.config
    run = problem.solver_for(problem.nonlinear, cfg.make_solver(), cfg.max_steps, cfg.solver == "poisson-deviance", cfg.loss_tol)
    args = (start, problem.data, problem.sigma, problem.pack(base))
    u0 = problem.pack(start)
    t = time.perf_counter()
    out = jax.block_until_ready(run(u0, args))
    dt = time.perf_counter() - t
    return dt, np.asarray(jax.flatten_util.ravel_pytree(out.value)[0]), (start, args, u0)


def _scipy_solve(problem, start_args, method: str, tol: float, jacobian: str) -> tuple[float, np.ndarray, int]:
    """The same profiled residuals (jitted JAX) through scipy.optimize.least_squares, with
    the JAX Jacobian (``jacobian = "jax"``) or scipy's own finite differences (``"2-point"``)."""
    from scipy.optimize import least_squares

    start, args, u0 = start_args
    flat0, unravel = jax.flatten_util.ravel_pytree(u0)
    f = jax.jit(lambda x: problem.residuals(unravel(x), args))
    jac = jax.jit(jax.jacfwd(lambda x: problem.residuals(unravel(x), args)))
    x0 = np.asarray(flat0, np.float64)
    f(x0).block_until_ready()
    jac(x0).block_until_ready()  # compile outside the timing, as for tofjax
    t = time.perf_counter()
    out = least_squares(
        lambda x: np.asarray(f(x), np.float64),
        x0,
        jac=(lambda x: np.asarray(jac(x), np.float64)) if jacobian == "jax" else jacobian,
        method=method,
        xtol=tol,
        ftol=tol,
        gtol=tol,
        max_nfev=2000,
    )
    return time.perf_counter() - t, out.x, int(out.nfev)


def run(config: FitSpeedConfig, out: Path, progress: bool = True) -> dict:
    scene = load_scene(config.scene)
    truth = {k: float(getattr(scene.waveguide, k)) for k in TARGETS}
    caps = [simulate(scene, config.frames, seed=config.seed + i) for i in range(config.captures)]

    # reference: tight tolerances, no loss rule
    ref_cal = Calibrator(scene, FitConfig(rtol=1e-10, atol=1e-10, loss_tol=0.0, max_steps=1000))
    refs = [ref_cal.fit(c) for c in tqdm(caps, desc="reference fits", disable=not progress)]

    rows = []
    for s in tqdm(config.settings, desc="settings", disable=not progress):
        cal = Calibrator(scene, _fit_config(s))
        t = time.perf_counter()
        cal.fit(caps[0])  # compiles
        first = time.perf_counter() - t
        times, steps, errs, conv, solve_times = [], [], [], [], []
        for cap, ref in zip(caps, refs):
            t = time.perf_counter()
            res = cal.fit(cap)
            times.append(time.perf_counter() - t)
            steps.append(res.steps)
            conv.append(res.converged)
            errs.append(_errors(res, ref, truth))
            solve_times.append(_time_solve(cal, cap)[0])
        rows.append(
            {
                "setting": dataclasses.asdict(s),
                "first_fit_s": first,
                "warm_fit_s_median": float(np.median(times)),
                "warm_solve_s_median": float(np.median(solve_times)),
                "steps_median": float(np.median(steps)),
                "converged": int(sum(conv)),
                "z_max_targets_median": float(np.median([e["z_max_targets"] for e in errs])),
                "z_max_all_max": float(np.max([e["z_max_all"] for e in errs])),
                "n1_rel_error_max": float(np.max([e["n1_rel_error"] for e in errs])),
                "mu_t_rel_error_max": float(np.max([e["mu_t_rel_error"] for e in errs])),
            }
        )

    # scipy against tofjax's default, side by side on the same captures and starts
    default = Calibrator(scene, FitConfig())
    default.fit(caps[0])
    breakdown = []
    comparisons = []
    for cap, ref in zip(caps, refs):
        t0 = time.perf_counter()
        res = default.fit(cap)
        total = time.perf_counter() - t0
        ours, x_ours, start_args = _time_solve(default, cap)
        breakdown.append({"fit_s": total, "solve_s": ours})
        problem = default._problem
        flat_ref = np.asarray(jax.flatten_util.ravel_pytree(problem.pack(ref.params))[0])
        sd = np.asarray(jax.flatten_util.ravel_pytree({k: v for k, v in ref.unconstrained_stderr.items() if k in problem.pack(ref.params)})[0])
        row = {"tofjax_solve_s": ours, "tofjax_z_max": float(np.max(np.abs(x_ours - flat_ref) / sd))}
        for m in (f"{m} {j}" for m in config.scipy_methods for j in config.scipy_jacobians):
            dt, x, nfev = _scipy_solve(problem, start_args, m.split(" ")[0], config.scipy_tol, m.split(" ")[1])
            row[f"scipy_{m}_s"] = dt
            row[f"scipy_{m}_nfev"] = nfev
            row[f"scipy_{m}_z_max"] = float(np.max(np.abs(x - flat_ref) / sd))
            row[f"scipy_{m}_vs_tofjax_z_max"] = float(np.max(np.abs(x - x_ours) / sd))
            row[f"ratio_scipy_{m}_over_tofjax"] = dt / ours
        comparisons.append(row)

    def med(key):
        return float(np.median([r[key] for r in comparisons]))

    scipy_summary = {
        m: {
            "warm_solve_s_median": med(f"scipy_{m}_s"),
            "ratio_over_tofjax_median": med(f"ratio_scipy_{m}_over_tofjax"),
            "z_max_vs_reference_median": med(f"scipy_{m}_z_max"),
            "z_max_vs_tofjax_median": med(f"scipy_{m}_vs_tofjax_z_max"),
        }
        for m in (f"{m} {j}" for m in config.scipy_methods for j in config.scipy_jacobians)
    }
    result = {
        "study": "calibration speed against accuracy",
        "data": "simulated",
        "machine": f"{platform.machine()}, {platform.processor() or 'cpu'}, {jax.device_count()} JAX device(s): {jax.devices()[0].device_kind}",
        "config": dataclasses.asdict(config),
        "truth": truth,
        "settings": rows,
        "default_breakdown": {
            "warm_fit_s_median": float(np.median([b["fit_s"] for b in breakdown])),
            "warm_solve_s_median": float(np.median([b["solve_s"] for b in breakdown])),
        },
        "scipy": {"tofjax_warm_solve_s_median": med("tofjax_solve_s"), "methods": scipy_summary, "runs": comparisons},
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "fit_speed.json").write_text(json.dumps(result, indent=1))
    (out / "fit_speed.md").write_text(markdown(result))
    plot(result, out / "fit_speed.png")
    return result


def markdown(r: dict) -> str:
    lines = [
        f"# Calibration speed against accuracy ({r['data']}, {r['config']['scene']}, {r['config']['frames']} frames, "
        f"{r['config']['captures']} captures)",
        "",
        f"Machine: {r['machine']}. Times are medians of warm runs; errors are against a tight reference fit, "
        "in units of its standard errors (z), and against the truth.",
        "",
        "| setting | solver | rtol/atol | loss_tol | dtype | steps | warm fit s | warm solve s | first fit s | z (n1, mu) | z (all) | n1 rel err | mu_t rel err |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in r["settings"]:
        s = row["setting"]
        lines.append(
            f"| {s['label']} | {s['solver']} | {s['rtol']:g} | {s['loss_tol']:g} | {s['dtype']} | {row['steps_median']:.0f} "
            f"| {row['warm_fit_s_median']:.3f} | {row['warm_solve_s_median']:.3f} | {row['first_fit_s']:.1f} "
            f"| {row['z_max_targets_median']:.3f} | {row['z_max_all_max']:.3f} | {row['n1_rel_error_max']:.2e} "
            f"| {row['mu_t_rel_error_max']:.2e} |"
        )
    sc = r["scipy"]
    lines += [
        "",
        f"## Against scipy.optimize.least_squares (same residuals, Jacobian and start; tofjax default solve "
        f"{sc['tofjax_warm_solve_s_median']:.3f} s)",
        "",
        "| method, Jacobian | warm solve s | scipy / tofjax time | z vs reference | z vs tofjax |",
        "|---|---|---|---|---|",
    ]
    for m, v in sc["methods"].items():
        lines.append(
            f"| {m} | {v['warm_solve_s_median']:.3f} | {v['ratio_over_tofjax_median']:.2f} | "
            f"{v['z_max_vs_reference_median']:.3f} | {v['z_max_vs_tofjax_median']:.3f} |"
        )
    return "\n".join(lines) + "\n"


def plot(r: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for row in r["settings"]:
        ax.scatter(row["warm_solve_s_median"], max(row["z_max_targets_median"], 1e-6), s=30)
        ax.annotate(row["setting"]["label"], (row["warm_solve_s_median"], max(row["z_max_targets_median"], 1e-6)), fontsize=7)
    for m, v in r["scipy"]["methods"].items():
        ax.scatter(v["warm_solve_s_median"], max(v["z_max_vs_reference_median"], 1e-6), marker="x", color="k")
        ax.annotate(f"scipy {m}", (v["warm_solve_s_median"], max(v["z_max_vs_reference_median"], 1e-6)), fontsize=7)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("warm solve time [s] (median)")
    ax.set_ylabel("error of n1, mu_s, mu_a [reference standard errors]")
    ax.set_title(f"Calibration: speed against accuracy ({r['data']})", fontsize=10)
    ax.axhline(0.1, color="0.7", lw=0.8, ls="--")
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
    tofjax.enable_x64()
    r = run(load_config(a.config), Path(a.out))
    print(markdown(r))


if __name__ == "__main__":
    main()
