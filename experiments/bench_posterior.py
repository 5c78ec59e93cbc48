"""Benchmark: NUTS against emcee on the same calibration posterior, in one run.

Simulates the default OptoSkin baseline (100 frames), fits it, builds the posterior once
(:func:`tofjax.fit.posterior.log_density`: the linear parameters integrated out with the
log-uniform gain prior (``--gain-prior``), the fit's weak prior, the nuisance prior of width
``--nuisance-width``), measures the cost of one value and gradient (a NUTS leapfrog step)
and of one batch of ``--walkers`` values (an emcee step) side by side, and samples it with both:

- NUTS (:func:`tofjax.fit.nuts.sample_nuts`): started at the log-density's mode,
  ``--chains`` x (``--warmup`` + ``--draws``), target acceptance ``--target-accept``;
  compiled ahead of time, so ``wall_s`` is warm (finding the mode, warm-up and draws;
  ``compile_s`` beside it). ``gradient_evaluations`` counts every one (mode included).
- emcee (:func:`tofjax.fit.posterior.sample_posterior`'s sampler): ``--walkers`` walkers for
  ``--emcee-steps`` steps, no early stop; the first quarter is discarded as burn-in. The
  stretch move (emcee's default, a = 2), vectorised over the walkers, which start at the fit
  jittered by 0.1 Laplace sd; its generator seeded (``seed`` in the JSON): unseeded (before),
  its min ESS varied between 79 and 256 over two runs of the same settings.

Both are diagnosed by ArviZ on the physical parameters (bulk and tail ESS, rank-normalised
split R-hat; emcee's walkers count as chains, which they are not quite: they are coupled
through the stretch move). ``wall_s`` is the sampling time (NUTS: warm-up included; emcee:
burn-in included). ESS per gradient (NUTS) and per log-density value (emcee) are the
load-independent figures. Writes ``posterior.json`` in ``--out``. NUTS's settings are
:class:`~tofjax.fit.nuts.NutsOptions`' defaults unless given (4 x (250 + 700) at target
acceptance 0.9 (0.95 before issue 16's nuts10x branch), chains in threads, one per core, dense mass matrix,
the ridge shear; the light-entry width held at the fit); ``--compare`` runs other NUTS settings
side by side in the same run (e.g. main's before: ``'{"label": "main_settings", "target_accept": 0.95, "threads": 1}'``);
with 32 walkers x 3000 steps they made about 55k gradients and 96k values on the default
baseline (docs/results/posterior.json; before the shear: posterior_noshear.json, posterior_idle.json,
posterior_loaded.json).

    python experiments/bench_posterior.py --out out/bench_posterior
    python experiments/bench_posterior.py --collect RUN1/posterior.json RUN2/posterior.json --out summary.json

On a loaded machine the two samplers' wall times, minutes apart, vary with the load (three
runs at load 7-18, the same draws (same seeds), gave NUTS over emcee 4.3x-7.1x per second): ``interleaved_cost``
measures a NUTS gradient and an emcee value (on one thread and on two) interleaved, and
``nuts_over_emcee_ess_min_per_s_load_robust`` is the per-evaluation ratio times their cost
ratio. ``--threads`` runs NUTS's chains that many at a time (NutsOptions.threads; default: one per
core; on the idle VM two threads made a gradient 1.75x cheaper, posterior_idle_main.json, while
emcee's batch split over two threads gained nothing); ``--emcee-threads`` splits emcee's batch
over threads (default 1, as before: the reference).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

import tofjax
from tofjax.fit.calibrate import Calibrator, FitConfig
from tofjax.fit.nuts import NutsOptions, NutsOptionsError, _threads, diagnostics, sample_nuts
from tofjax.fit.posterior import GAIN_PRIOR, GAIN_PRIORS, HELD, NUISANCE_WIDTH, log_density
from tofjax.outputs import atomic_write_text, check_output
from tofjax.scene import load_scene
from tofjax.simulate import simulate


def threaded_batch(batch, threads: int):
    """``batch`` (points (N, P) -> values (N,)) with the points split into ``threads`` parts
    evaluated at the same time, one thread each (1: ``batch`` itself)."""
    if threads <= 1:
        return batch
    from concurrent.futures import ThreadPoolExecutor

    pool = ThreadPoolExecutor(max_workers=threads)

    def run(flats):
        parts = np.array_split(np.asarray(flats), threads)
        return np.concatenate(list(pool.map(batch, parts)))

    return run


def run_emcee(ld, walkers: int, steps: int, seed: int = 0, threads: int = 1) -> dict:
    import emcee

    P = ld.flat0.size
    rng = np.random.default_rng(seed)
    scale = np.sqrt(np.diag(ld.laplace_cov))
    start = ld.flat0[None, :] + 0.1 * scale[None, :] * rng.normal(size=(walkers, P))
    fn = threaded_batch(ld.batch, threads)
    fn(start)  # compile outside the timing
    # emcee's stretch move evaluates half the walkers at a time: a second shape, compiled here
    # too (before, it compiled inside emcee's timed run, against emcee)
    t = time.perf_counter()
    fn(start[: walkers // 2])
    half_compile = time.perf_counter() - t
    sampler = emcee.EnsembleSampler(walkers, P, fn, vectorize=True)
    # emcee draws its stretch moves from NumPy's global generator, unseeded: its min ESS varied
    # 79-256 between two runs of the same settings. Seeded, a rerun gives the same chain.
    sampler.random_state = np.random.RandomState(seed).get_state()
    t = time.perf_counter()
    sampler.run_mcmc(start, steps, progress=False)
    wall = time.perf_counter() - t
    chain = sampler.get_chain()  # (steps, walkers, P)
    keep = chain[steps // 4 :]
    phys = ld.to_physical(keep.reshape(-1, P)).reshape(keep.shape[0], walkers, -1).transpose(1, 0, 2)
    d = diagnostics(ld.names, phys)
    tau = sampler.get_autocorr_time(tol=0)
    return {
        "walkers": walkers,
        "steps": steps,
        "move": "stretch (emcee's default, a = 2)",
        "seed": seed,
        "threads": threads,
        "half_batch_first_call_s": half_compile,
        "burn_in": steps // 4,
        "wall_s": wall,
        "ess_min": d["ess_min"],
        "ess_min_per_s": d["ess_min"] / wall,
        "rhat_max": d["rhat_max"],
        "ess_bulk": d["ess_bulk"],
        "ess_tail": d["ess_tail"],
        "rhat": d["rhat"],
        "acceptance": float(np.mean(sampler.acceptance_fraction)),
        "tau_max_steps": float(np.nanmax(tau)),
        "steps_over_tau": float(steps / np.nanmax(tau)),
        "ess_emcee_tau": float(keep.shape[0] * walkers / np.nanmax(tau)),
        "log_prob_calls": steps,
        "log_density_evaluations": steps * walkers,
        "ess_min_per_evaluation": d["ess_min"] / (steps * walkers),
    }


def evaluation_cost(ld, walkers: int, repeats: int = 20) -> dict:
    """Median seconds of one log-density value and gradient (what a NUTS leapfrog step costs)
    and of one batched call of ``walkers`` values (one emcee step), measured side by side."""
    import jax
    import jax.numpy as jnp

    vg = jax.jit(jax.value_and_grad(ld.fn))
    f0 = jnp.asarray(ld.flat0)
    rng = np.random.default_rng(0)
    pts = ld.flat0[None, :] + 0.1 * np.sqrt(np.diag(ld.laplace_cov))[None, :] * rng.normal(size=(walkers, ld.flat0.size))
    jax.block_until_ready(vg(f0))
    ld.batch(pts)
    tg, tb = [], []
    for i in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(vg(jnp.asarray(pts[i % walkers])))
        tg.append(time.perf_counter() - t)
        t = time.perf_counter()
        ld.batch(pts)
        tb.append(time.perf_counter() - t)
    return {"value_and_gradient_s": float(np.median(tg)), "batch_of_walkers_values_s": float(np.median(tb)),
            "value_per_point_in_batch_s": float(np.median(tb)) / walkers, "walkers": walkers, "repeats": repeats}


def interleaved_cost(ld, walkers: int, repeats: int = 9, n: int = 40, threads: int = 2) -> dict:
    """Seconds per log-density gradient as NUTS spends them (``n`` value-and-gradients in one
    compiled scan, no dispatch between them) and per value as emcee spends them (one call of
    half the walkers, the stretch move's batch), each on one thread and on ``threads``
    threads at once (gradients: ``threads`` scans concurrently; values: the batch split),
    measured interleaved, repeat after repeat, so that a changing load hits all four alike.
    Medians. On a loaded machine the samplers' own wall times, minutes apart, can differ by
    the load alone; these costs times the per-evaluation ratio give a load-robust ratio."""
    import jax
    import jax.numpy as jnp
    from concurrent.futures import ThreadPoolExecutor

    vg = jax.value_and_grad(ld.fn)

    @jax.jit
    def grads(x0):
        def body(c, _):
            v, g = vg(c)
            return c + 1e-12 * g, v
        return jax.lax.scan(body, x0, None, length=n)[1]

    rng = np.random.default_rng(1)
    pts = ld.flat0[None, :] + 0.1 * np.sqrt(np.diag(ld.laplace_cov))[None, :] * rng.normal(size=(walkers // 2, ld.flat0.size))
    x0 = [jnp.asarray(p) for p in pts[:threads]]
    pool = ThreadPoolExecutor(max_workers=threads)
    tb = threaded_batch(ld.batch, threads)
    jax.block_until_ready(grads(x0[0]))
    ld.batch(pts), tb(pts)
    k = max(1, int(round(n / len(pts))))  # about as many values as gradients per timing
    rows = {"gradient_1_thread_s": [], f"gradient_{threads}_threads_s": [], "value_1_thread_s": [], f"value_{threads}_threads_s": []}
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(grads(x0[0]))
        rows["gradient_1_thread_s"].append((time.perf_counter() - t) / n)
        t = time.perf_counter()
        list(pool.map(lambda x: jax.block_until_ready(grads(x)), x0))
        rows[f"gradient_{threads}_threads_s"].append((time.perf_counter() - t) / (n * threads))
        t = time.perf_counter()
        for _ in range(k):
            ld.batch(pts)
        rows["value_1_thread_s"].append((time.perf_counter() - t) / (k * len(pts)))
        t = time.perf_counter()
        for _ in range(k):
            tb(pts)
        rows[f"value_{threads}_threads_s"].append((time.perf_counter() - t) / (k * len(pts)))
    pool.shutdown()
    out = {key: float(np.median(v)) for key, v in rows.items()}
    out.update(threads=threads, repeats=repeats, gradients_per_timing=n, batch=len(pts))
    return out


def small_scene_of(scene_name: str, small=None):
    """The scene, or with ``small = (sensors, zones, bins)`` a smaller one of the same physics;
    and its label."""
    scene = load_scene(scene_name)
    if not small:
        return scene, f"{scene_name} baseline"
    from tofjax.scene import SensorModel

    S, Z, B = small
    sm = scene.sensor
    scene = scene.replace(sensor=SensorModel(bin_width_s=sm.bin_width_s, n_bins=B, zones=Z, fov_deg=sm.fov_deg * Z / sm.zones),
                          sensors=scene.sensors[:S])
    return scene, f"{scene_name} reduced to {S} sensors x {Z} zones x {B} bins (not the default baseline)"


def nuts_row_of(cal, cap, fit, ld, nuts: NutsOptions) -> dict:
    """One NUTS run on ``ld`` with ``nuts``: its row of the JSON."""
    t = time.perf_counter()
    warm = sample_nuts(cal, cap, fit, nuts, density=ld)
    warm_total = time.perf_counter() - t
    s = warm.summary()
    row = {
        "chains": nuts.chains,
        "warmup": nuts.warmup,
        "draws": nuts.draws,
        "target_accept": nuts.target_accept,
        "max_tree_depth": nuts.max_tree_depth,
        "threads": _threads(nuts),
        "wall_s": warm.wall_s,
        "wall_s_with_compile_and_diagnostics": warm_total,
        "compile_s": warm.compile_s,
        "ess_min": s["ess_min"],
        "ess_min_per_s": s["ess_min_per_s"],
        "rhat_max": s["rhat_max"],
        "ess_bulk": s["ess_bulk"],
        "ess_tail": s["ess_tail"],
        "rhat": s["rhat"],
        "divergences": warm.divergences,
        "step_size": s["step_size"],
        "mean_tree_depth": warm.mean_tree_depth,
        "mean_accept": warm.mean_accept,
        "pilot": nuts.pilot,
        "pilot_warmup": nuts.pilot_warmup,
        "pilot_draws": nuts.pilot_draws,
        "pilot_adapt_mass": nuts.pilot_adapt_mass,
        "adapt_mass": nuts.adapt_mass,
        "seed": nuts.seed,
        "shear": nuts.shear,
        "start_info": s["start_info"],
        "gradient_evaluations": warm.gradient_evaluations,
        "ess_min_per_gradient": s["ess_min"] / warm.gradient_evaluations,
        "gradient_evaluations_per_s": warm.gradient_evaluations / warm.wall_s,
        # where the gradients go: the warm-up's share (its trees are deeper than the draws')
        "warmup_gradient_evaluations": warm.warmup_gradient_evaluations,
        "warmup_share_of_gradients": warm.warmup_gradient_evaluations / warm.gradient_evaluations,
        "gradients_per_draw": (warm.gradient_evaluations - warm.warmup_gradient_evaluations
                               - int(s["start_info"].get("gradient_evaluations", 0))) / (nuts.chains * nuts.draws),
    }
    print(f"NUTS warm {warm.wall_s:.1f} s, min ESS {s['ess_min']:.0f}, max R-hat {s['rhat_max']:.3f}, "
          f"{row['gradient_evaluations']} gradients ({row['warmup_gradient_evaluations']} in warm-up)", flush=True)
    return row


def run(scene_name: str, frames: int, nuts: NutsOptions, walkers: int, emcee_steps: int, out: Path, small=None,
        gain_prior: str = GAIN_PRIOR, note: str = "", emcee_threads: int = 1, compare=()) -> dict:
    scene, label = small_scene_of(scene_name, small)
    cap = simulate(scene, frames, seed=1)
    cal = Calibrator(scene, FitConfig())
    t = time.perf_counter()
    fit = cal.fit(cap)
    fit_s = time.perf_counter() - t
    print(f"fit {fit_s:.1f} s: {fit.result}", flush=True)
    load_start = os.getloadavg()[0]
    ld = log_density(cal, cap, fit, nuts.nuisance_width, nuts.hold, gain_prior)
    cost = evaluation_cost(ld, walkers)
    print(f"value+gradient {1e3 * cost['value_and_gradient_s']:.2f} ms, {walkers} values batched "
          f"{1e3 * cost['batch_of_walkers_values_s']:.2f} ms", flush=True)
    nuts_row = nuts_row_of(cal, cap, fit, ld, nuts)
    others = {f"nuts_{label}": nuts_row_of(cal, cap, fit, ld, o) for label, o in compare}  # side by side, same run
    em = run_emcee(ld, walkers, emcee_steps, threads=emcee_threads)
    ratio = nuts_row["ess_min_per_s"] / em["ess_min_per_s"] if em["ess_min_per_s"] > 0 else float("inf")
    per_eval = nuts_row["ess_min_per_gradient"] / em["ess_min_per_evaluation"] if em["ess_min_per_evaluation"] > 0 else float("inf")
    ic = interleaved_cost(ld, walkers, threads=max(2, _threads(nuts)))
    T = ic["threads"]
    print("interleaved costs (ms):", {k: round(1e3 * v, 3) for k, v in ic.items() if k.endswith("_s")}, flush=True)
    g_nuts = ic[f"gradient_{T}_threads_s"] if _threads(nuts) > 1 else ic["gradient_1_thread_s"]
    v_em = ic[f"value_{T}_threads_s"] if emcee_threads > 1 else ic["value_1_thread_s"]
    ic["per_evaluation_ratio_times_cost_ratio"] = {
        "as_run": per_eval * v_em / g_nuts,  # the samplers as configured in this run
        "nuts_1_thread_emcee_1_thread": per_eval * ic["value_1_thread_s"] / ic["gradient_1_thread_s"],
        f"nuts_{T}_threads_emcee_1_thread": per_eval * ic["value_1_thread_s"] / ic[f"gradient_{T}_threads_s"],
        f"nuts_{T}_threads_emcee_{T}_threads": per_eval * ic[f"value_{T}_threads_s"] / ic[f"gradient_{T}_threads_s"],
    }
    targets = {
        "nuts_ess_min_ge_1000": nuts_row["ess_min"] >= 1000,
        "nuts_wall_le_60s": nuts_row["wall_s"] <= 60,
        "nuts_rhat_le_1.01": nuts_row["rhat_max"] <= 1.01,
        "nuts_no_divergences": nuts_row["divergences"] == 0,
        "nuts_over_emcee_ess_per_s_ge_10": ratio >= 10,
    }
    result = {
        **({"note": note} if note else {}),
        "benchmark": "calibration posterior: NUTS (blackjax) against emcee on the same log-density",
        "data": f"simulated {label}, {frames} frames (seed 1)",
        "machine": f"{platform.machine()} CPU, {os.cpu_count()} cores shared with other jobs "
        f"(load average {load_start:.1f} before sampling, {os.getloadavg()[0]:.1f} at the end); JAX {__import__('jax').__version__}",
        "load_average": {"before_sampling": load_start, "end": os.getloadavg()[0]},
        "posterior": {"coordinates": list(ld.coords), "parameters": ld.names, "nuisance_width": nuts.nuisance_width,
                      "held_at_fit": list(nuts.hold), "gain_prior": gain_prior,
                      "linear_parameters": "integrated out analytically (gain: log-uniform prior; counts: uniform)"
                      if gain_prior == "log-uniform" else "integrated out analytically (flat priors)"},
        "fit_s": fit_s,
        "evaluation_cost": cost,
        "samplers": {"nuts": nuts_row, **others, "emcee": em},
        "nuts_over_emcee_ess_min_per_s": ratio,
        **({"compared_nuts_over_emcee_ess_min_per_s": {k: v["ess_min_per_s"] / em["ess_min_per_s"] for k, v in others.items()},
            "compared_nuts_over_emcee_ess_min_per_evaluation": {
                k: v["ess_min_per_gradient"] / em["ess_min_per_evaluation"] for k, v in others.items()}} if others else {}),
        "nuts_over_emcee_ess_min_per_evaluation": per_eval,
        "interleaved_cost": ic,
        "nuts_over_emcee_ess_min_per_s_load_robust": ic["per_evaluation_ratio_times_cost_ratio"]["as_run"],
        "targets": targets,
    }
    atomic_write_text(out / "posterior.json", json.dumps(result, indent=1))
    return result


def collect(paths, out: Path, note: str = "") -> dict:
    """One summary of several runs' ``posterior.json`` (side by side: per run, per sampler
    ``ess_min``, ``ess_min_per_s``, ``wall_s``, ``rhat_max``, and the ratios); ``.jsonl`` files
    are experiments/posterior_variants.py's rows (NUTS only), kept as ``nuts_variants``."""
    import json as _json

    runs, variants = [], []
    for p in paths:
        if str(p).endswith(".jsonl"):  # experiments/posterior_variants.py's NUTS-only rows
            for line in Path(p).read_text().splitlines():
                if line.strip():
                    v = _json.loads(line)
                    variants.append({k: v.get(k) for k in ("label", "options", "divergences", "gradient_evaluations",
                                                           "warmup_gradient_evaluations", "ess_min",
                                                           "rhat_max", "ess_min_per_gradient", "wall_s", "mean_tree_depth",
                                                           "mean_accept", "load_average", "draws_over_laplace_variance",
                                                           "widest_direction", "narrowest_direction")} | {"source": str(p)})
            continue
        r = _json.loads(Path(p).read_text())
        row = {"source": str(p), "note": r.get("note", ""), "machine": r["machine"],
               "nuts_over_emcee_ess_min_per_s": r["nuts_over_emcee_ess_min_per_s"],
               "nuts_over_emcee_ess_min_per_evaluation": r["nuts_over_emcee_ess_min_per_evaluation"],
               "nuts_over_emcee_ess_min_per_s_load_robust": r.get("nuts_over_emcee_ess_min_per_s_load_robust"),
               "compared_nuts_over_emcee_ess_min_per_s": r.get("compared_nuts_over_emcee_ess_min_per_s"),
               "compared_nuts_over_emcee_ess_min_per_evaluation": r.get("compared_nuts_over_emcee_ess_min_per_evaluation"),
               "load_average": r.get("load_average"),
               "interleaved_cost": r.get("interleaved_cost"), "targets": r["targets"]}
        for k, v in r["samplers"].items():
            row[k] = {q: v.get(q) for q in ("ess_min", "ess_min_per_s", "wall_s", "rhat_max", "threads", "divergences",
                                            "gradient_evaluations", "log_density_evaluations", "target_accept",
                                            "warmup_gradient_evaluations", "gradients_per_draw", "mean_tree_depth")}
        runs.append(row)
    res = {**({"note": note} if note else {}), "runs": runs, **({"nuts_variants": variants} if variants else {})}
    atomic_write_text(out, _json.dumps(res, indent=1))
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    dflt = NutsOptions()  # the library's defaults (one place)
    ap.add_argument("--scene", default="optoskin")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--chains", type=int, default=dflt.chains)
    ap.add_argument("--warmup", type=int, default=dflt.warmup)
    ap.add_argument("--draws", type=int, default=dflt.draws)
    ap.add_argument("--nuisance-width", type=float, default=NUISANCE_WIDTH)
    ap.add_argument("--target-accept", type=float, default=dflt.target_accept)
    ap.add_argument("--max-tree-depth", type=int, default=dflt.max_tree_depth)
    ap.add_argument("--shear", action=argparse.BooleanOptionalAction, default=dflt.shear,
                    help="NUTS: shear the coordinates along the albedo ridge (NutsOptions.shear)")
    ap.add_argument("--hold", nargs="*", default=list(HELD), help="coordinates held at the fit (none: sample all)")
    ap.add_argument("--gain-prior", choices=GAIN_PRIORS, default=GAIN_PRIOR)
    ap.add_argument("--pilot", action=argparse.BooleanOptionalAction, default=dflt.pilot,
                    help="NUTS: a pilot run first (its chains' pooled draws whiten the kept run)")
    ap.add_argument("--threads", type=int, default=dflt.threads,
                    help="NUTS: chains run at the same time (NutsOptions.threads; default: one per core)")
    ap.add_argument("--emcee-threads", type=int, default=1,
                    help="emcee: its batch of walkers split over this many threads (default 1: one call, the reference)")
    ap.add_argument("--seed", type=int, default=dflt.seed, help="NUTS: its key (the draws are fixed by it)")
    ap.add_argument("--pilot-warmup", type=int, default=dflt.pilot_warmup, help="NUTS: the pilot's warm-up (with --pilot)")
    ap.add_argument("--pilot-draws", type=int, default=dflt.pilot_draws, help="NUTS: the pilot's draws (with --pilot)")
    ap.add_argument("--pilot-adapt-mass", action=argparse.BooleanOptionalAction, default=dflt.pilot_adapt_mass)
    ap.add_argument("--adapt-mass", action=argparse.BooleanOptionalAction, default=dflt.adapt_mass)
    ap.add_argument("--compare", nargs="*", default=[], metavar="JSON",
                    help='NUTS settings run too, side by side in the same run: JSON objects of NutsOptions fields '
                         'overriding the run\'s, with a "label" (e.g. \'{"label": "main", "threads": 1}\')')
    ap.add_argument("--walkers", type=int, default=32)
    ap.add_argument("--emcee-steps", type=int, default=3000)
    ap.add_argument("--small", type=int, nargs=3, metavar=("SENSORS", "ZONES", "BINS"),
                    help="a reduced scene instead of the default baseline (e.g. 3 3 96)")
    ap.add_argument("--note", default="", help="a line stored as the JSON's 'note' (how and where it was run)")
    ap.add_argument("--out", default="out/bench_posterior")
    ap.add_argument("--overwrite", action="store_true")
    ap.add_argument("--collect", nargs="+", metavar="POSTERIOR_JSON",
                    help="only summarise these runs' posterior.json side by side into --out (a .json file)")
    a = ap.parse_args(argv)
    if a.collect:
        check_output(Path(a.out), overwrite=a.overwrite)
        collect(a.collect, Path(a.out), a.note)
        return
    from tofjax.compile_cache import use_fast_cpu_compiler  # noqa: E402
    use_fast_cpu_compiler()  # the CLI's CPU compiler (before JAX's backend starts)
    tofjax.enable_x64()
    from tofjax.compile_cache import enable_compilation_cache

    enable_compilation_cache()  # the user cache: a rerun skips compiling the model, the fit and NUTS
    out = Path(a.out)
    check_output(out / "posterior.json", overwrite=a.overwrite)
    out.mkdir(parents=True, exist_ok=True)
    nuts = NutsOptions(chains=a.chains, warmup=a.warmup, draws=a.draws, nuisance_width=a.nuisance_width,
                       target_accept=a.target_accept, max_tree_depth=a.max_tree_depth, hold=tuple(a.hold), pilot=a.pilot,
                       shear=a.shear, threads=a.threads, seed=a.seed, pilot_warmup=a.pilot_warmup, pilot_draws=a.pilot_draws,
                       pilot_adapt_mass=a.pilot_adapt_mass, adapt_mass=a.adapt_mass)
    compare = []
    for spec in a.compare:
        try:
            kw = json.loads(spec)
            label = str(kw.pop("label"))
            kw = {k: tuple(v) if k == "hold" else v for k, v in kw.items()}
            compare.append((label, dataclasses.replace(nuts, **kw)))
        except (ValueError, KeyError, TypeError, NutsOptionsError) as e:
            raise SystemExit(f"--compare: a JSON object of NutsOptions fields with a label, got {spec!r} ({e})")
    r = run(a.scene, a.frames, nuts, a.walkers, a.emcee_steps, out, a.small, a.gain_prior, a.note, a.emcee_threads, compare)
    print(json.dumps({k: v for k, v in r.items() if k != "samplers"}, indent=1))
    for k, v in r["samplers"].items():
        print(k, {q: v[q] for q in ("wall_s", "ess_min", "ess_min_per_s", "rhat_max")})


if __name__ == "__main__":
    main()
