"""Benchmark: the calibration fit's speed (issue 13): warm fit, compile, and a batch of fits in
one call against separate calls, optionally side by side with another checkout of tofjax.

On simulated 100-frame baselines of the default OptoSkin scene (6 sensors x 7 zones x 128 bins,
twelve nonlinear parameters), in one process per checkout:

* ``warm_fit_s``: ``Calibrator(scene).fit(capture)`` (timing start, envelope, fit, covariance,
  result) after a first fit, median over ``--captures`` captures x ``--repeats``;
* ``compile_s``: the first ``fit_problem`` call (with covariance) minus a warm one: what the
  compiled fit costs to trace and compile (the first whole fit is ``first_fit_s``);
* ``batch``: ``fit_problem`` (no covariance) on ``--separate`` captures one call each, and
  ``fit_problem_batch`` on ``--batch`` captures in one call, all from the same start (the
  envelope start of the first capture); ``speedup = batch x mean separate / batch call``.
  The batched fit is compiled by a first call, timed separately (``batch_compile_s``).
  With ``--batch-mode both`` (the default) or ``compact``, the same batch also runs through
  ``fit_problem_compact`` (the fits that have stopped dropped from the batch every 16 steps):
  ``batch.compact`` holds its time, compile, speed-up and lane-steps beside the vmapped call's.
* the estimates and standard errors of every capture's fit, so the parent can compare two
  checkouts in standard errors, and (``--reference``) a tight refit of each capture
  (``loss_tol = 0``, tolerances 1e-12, from the default fit's end point) as the yardstick.

With ``--baseline DIR`` (another checkout, e.g. ``git worktree add /tmp/fsbase <commit>``) each
checkout runs as its own process with its own ``PYTHONPATH``, alternating, and the JSON holds
both and their ratios. Writes ``fit_bench.json`` to ``--out``. **Simulated** data.

    python experiments/bench_fit.py --out out/bench_fit --baseline /tmp/fsbase
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _flat(values: dict) -> dict:
    import numpy as np

    return {k: np.asarray(v, np.float64).ravel().tolist() for k, v in values.items()}


def worker(a) -> dict:
    import jax

    from tofjax.compile_cache import use_fast_cpu_compiler  # noqa: E402
    use_fast_cpu_compiler()  # the CLI's CPU compiler (before JAX's backend starts)
    jax.config.update("jax_enable_x64", True)
    import numpy as np

    from tofjax.fit._start import envelope_candidates, timing_start
    from tofjax.fit.calibrate import Calibrator, _anchor, _data
    from tofjax.scene import load_scene

    from tofjax.fit.calibrate import FitConfig

    scene = load_scene(a.scene)
    cal = Calibrator(scene, FitConfig(pulse_tails=a.pulse_tails if a.pulse_tails == "auto" else int(a.pulse_tails)))
    pb, cfg = cal.problem, cal.config
    solver, objective = cfg.make_solver(), cfg.make_objective()
    dtype = pb.model.geometry.ray_length.dtype
    base = cal.base_params()
    kw = dict(max_steps=cfg.max_steps, loss_tol=cfg.loss_tol, gn_first=cfg.gn_first)
    out: dict = {"solver": type(solver).__name__, "jax": jax.__version__, "backend": jax.default_backend(),
                 "device_kind": jax.devices()[0].device_kind}

    caps = [("own", simulated(a, scene, 1000 + i)) for i in range(a.captures)]
    if a.indep:
        sys.path.insert(0, str(ROOT / "tests"))
        from indep_sim import IndepRig
        from indep_sim import simulate as simulate_independent
        from tofjax.capture import Capture

        for i in range(a.indep):
            rig = IndepRig.from_scene(scene, seed=200 + i)
            c = simulate_independent(rig, contacts=np.zeros((0, 3)), frames=a.frames, seed=300 + i)
            caps.append(("independent", c if isinstance(c, Capture) else Capture(scene, np.asarray(c))))
    t = time.perf_counter()
    cal.fit(caps[0][1])
    out["first_fit_s"] = time.perf_counter() - t
    _progress(f"first Calibrator.fit (compiles) {out['first_fit_s']:.1f} s")
    fits, times = [], []
    for r in range(a.repeats):
        for i, (kind, c) in enumerate(caps):
            t = time.perf_counter()
            res = cal.fit(c)
            times.append(time.perf_counter() - t)
            if r == 0:
                fits.append({"data": kind, "steps": res.steps, "result": res.result, "reduced_chi2": res.reduced_chi2,
                             "values": _flat(res.values), "stderr": _flat(res.stderr),
                             "loss": res.loss_history[-1], "loss_history": res.loss_history,
                             "stages": res.stages})
    out["warm_fit_s"] = statistics.median(times)
    out["warm_fit_all_s"] = times
    out["fits"] = fits
    _progress(f"warm Calibrator.fit median {out['warm_fit_s']:.3f} s")
    if not a.no_stages:
        st_solver = solver
        if a.lambda_trials:
            import dataclasses

            st_solver = dataclasses.replace(solver, lambda_trials=tuple(a.lambda_trials))
            out["stage_solver"] = repr(st_solver)
        out["stage_times"] = stage_times(a, cal, caps, scene, base, cfg, st_solver, objective, dtype)
    # compile of the fit program alone: a new problem object of the same structure is a
    # cache hit in eqx.filter_jit, so compile through a fresh jit of the same function
    d0, s0 = _data(caps[0][1], dtype)
    st, found = timing_start(pb, np.asarray(d0), caps[0][1].n_frames, scene, base)
    start = envelope_candidates(pb, st, d0, s0, 1)[0]
    anchor = _anchor(st, found, cfg, dtype)
    import equinox as eqx

    calmod = sys.modules["tofjax.fit.calibrate"]
    if a.no_compile:
        return _rest(a, out, cal, caps, pb, objective, solver, start, base, anchor, cfg, scene, dtype, kw)
    fresh = eqx.filter_jit(calmod._fit)
    args = (pb, objective, solver, start, d0, s0, base, anchor, cfg.max_steps, cfg.loss_tol, cfg.gn_first, True)
    t = time.perf_counter()
    jax.block_until_ready(fresh(*args))
    first = time.perf_counter() - t
    t = time.perf_counter()
    jax.block_until_ready(fresh(*args))
    out["compile_s"] = first - (time.perf_counter() - t)
    return _rest(a, out, cal, caps, pb, objective, solver, start, base, anchor, cfg, scene, dtype, kw)


def _progress(msg: str) -> None:
    """One line to stderr as the worker goes (a run stopped by a time limit still shows how far it got)."""
    print(f"[bench_fit worker {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def _rest(a, out, cal, caps, pb, objective, solver, start, base, anchor, cfg, scene, dtype, kw):
    import jax
    import jax.numpy as jnp
    import numpy as np

    from tofjax.fit.calibrate import _data, fit_problem, fit_problem_batch

    fits = out["fits"]
    if a.reference:
        from tofjax.fit.solve import MarquardtLM

        tight = MarquardtLM(rtol=1e-12, atol=1e-12)
        refs = []
        for (_, c), f in zip(caps, fits):
            d, g = _data(c, dtype)
            res = cal.fit(c)
            sol = jax.device_get(fit_problem(pb, objective, tight, res.params, d, g, base, anchor_of(cfg, pb, scene, base, c, dtype),
                                             max_steps=a.reference_steps, loss_tol=0.0, gn_first=0, with_cov=False))
            vals = {k: np.asarray(sol.linear[k] if k in sol.linear else getattr(sol.params, k)) for k in pb.free}
            refs.append({"values": _flat(vals), "steps": int(sol.steps), "loss": float(0.5 * sol.chi2)})
        out["reference"] = refs

    if a.batch and cfg.pulse_tails == "auto":
        out["batch"] = batch_auto(a, cal, scene, objective, solver, dtype)
    elif a.batch:
        D, G = batch_data(a, scene, dtype)
        nocov = dict(kw, with_cov=False)
        jax.block_until_ready(fit_problem(pb, objective, solver, start, D[0], G[0], base, anchor, **nocov))
        _progress("batch: data simulated, fit_problem compiled")
        sep, sep_steps = [], []
        for i in range(a.separate):
            t = time.perf_counter()
            sol = jax.block_until_ready(fit_problem(pb, objective, solver, start, D[i], G[i], base, anchor, **nocov))
            sep.append(time.perf_counter() - t)
            sep_steps.append(int(sol.steps))
            _progress(f"separate fit {i}: {sep[-1]:.3f} s, {sep_steps[-1]} steps")
        starts = jax.tree_util.tree_map(lambda x: jnp.stack([x] * a.batch), start)
        A = jnp.stack([anchor] * a.batch)
        t = time.perf_counter()
        jax.block_until_ready(fit_problem_batch(pb, objective, solver, starts, D, G, base, A, **nocov))
        first = time.perf_counter() - t
        _progress(f"batch of {a.batch}, first call (compiles) {first:.1f} s")
        t = time.perf_counter()
        sols = jax.block_until_ready(fit_problem_batch(pb, objective, solver, starts, D, G, base, A, **nocov))
        batch_s = time.perf_counter() - t
        _progress(f"batch of {a.batch}: {batch_s:.3f} s; speed-up {a.batch * statistics.mean(sep) / batch_s:.2f}x")
        steps = np.asarray(sols.steps)
        # the batch against the same fits one by one (the first --separate)
        n1_sep = [float(fit_problem(pb, objective, solver, start, D[i], G[i], base, anchor, **nocov).params.n1)
                  for i in range(min(a.separate, 5))]
        out["batch"] = {
            "n": a.batch, "separate_n": a.separate, "separate_s": sep, "separate_mean_s": statistics.mean(sep),
            "separate_steps": sep_steps, "batch_s": batch_s, "batch_compile_s": first - batch_s,
            "batch_steps_max": int(steps.max()), "batch_steps_mean": float(steps.mean()),
            "speedup": a.batch * statistics.mean(sep) / batch_s,
            "successful": int(np.sum(np.asarray(jax.tree_util.tree_leaves(sols.result)[0]) == 0)),
            "max_n1_diff_batch_vs_separate": float(np.max(np.abs(np.asarray(sols.params.n1)[: len(n1_sep)] - n1_sep))),
        }
        if a.batch_mode in ("compact", "both"):
            out["batch"]["compact"] = compact_batch(a, pb, objective, solver, starts, D, G, base, A, nocov, sols, statistics.mean(sep))
    return out


def batch_auto(a, cal, scene, objective, solver, dtype) -> dict:
    """The batch with ``pulse_tails = "auto"`` (:func:`tofjax.fit.calibrate.fit_batch_tails`): one
    one-tail batch, the score test per fit, a two-tail batch for the fits it sends on; each from
    the one-tail envelope start of the first capture. ``--separate`` fits through the same rule
    one at a time (``fit_problem_loop``). Steps per stage: the one-tail fits', the two-tail fits'."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from tofjax.fit._start import envelope_candidates, timing_start
    from tofjax.fit._tails import one_tail_problem
    from tofjax.fit.calibrate import (_anchor, _data, base_params, fit_batch_tails, fit_problem_batch, fit_problem_compact,
                                      fit_problem_loop, tail_configs)

    cfg = cal.config
    cfg1 = tail_configs(cfg)[0]
    one = one_tail_problem(cal.problem, cfg1.free)
    base1 = base_params(scene, cfg1, dtype)
    D, G = batch_data(a, scene, dtype)
    d0, s0 = _data(simulate_first(a, scene), dtype)
    st, found = timing_start(one, np.asarray(d0), a.frames, scene, base1)
    start = envelope_candidates(one, st, d0, s0, 1)[0]
    anchor = _anchor(st, found, cfg, dtype)

    def rule(n, fit_batch, i0=0):
        starts = jax.tree_util.tree_map(lambda x: jnp.stack([x] * n), start)
        A = jnp.stack([anchor] * n)
        return fit_batch_tails(cal.problem, cfg, objective, solver, starts, D[i0:i0 + n], G[i0:i0 + n], A, fit_batch,
                               scene=scene, with_cov=False)

    rule(1, fit_problem_loop)  # compiles the one-tail fit and the test
    sep, sep_steps = [], []
    for i in range(a.separate):
        t = time.perf_counter()
        f = rule(1, fit_problem_loop, i)[0]
        sep.append(time.perf_counter() - t)
        sep_steps.append([s["steps"] for s in f.stages if "steps" in s])
        _progress(f"separate fit {i} (auto): {sep[-1]:.3f} s, steps per stage {sep_steps[-1]}")
    modes = {"vmap": fit_problem_batch, "compact": fit_problem_compact}
    timed = {}
    for mode in (("vmap", "compact") if a.batch_mode == "both" else (a.batch_mode,)):
        t = time.perf_counter()
        rule(a.batch, modes[mode])
        first = time.perf_counter() - t
        _progress(f"batch of {a.batch} (auto, {mode}), first call (compiles) {first:.1f} s")
        t = time.perf_counter()
        fits = rule(a.batch, modes[mode])
        batch_s = time.perf_counter() - t
        timed[mode] = {"batch_s": batch_s, "batch_first_call_s": first, "speedup": a.batch * statistics.mean(sep) / batch_s}
        _progress(f"batch of {a.batch} (auto, {mode}): {batch_s:.3f} s; speed-up {timed[mode]['speedup']:.2f}x")
    s1 = [f.stages[0]["steps"] for f in fits]
    s2 = [f.stages[-1]["steps"] for f in fits if f.config.pulse_tails == 2]
    return {
        "pulse_tails": "auto", "n": a.batch, "separate_n": a.separate, "separate_s": sep, "separate_mean_s": statistics.mean(sep),
        "separate_steps_per_stage": sep_steps, "batch_s": batch_s, "batch_first_call_s": first,
        "speedup": a.batch * statistics.mean(sep) / batch_s, "modes": timed,
        "one_tail_steps_max": max(s1), "one_tail_steps_mean": statistics.mean(s1),
        "chose_two": len(s2), "two_tail_steps_max": max(s2) if s2 else None,
        "two_tail_steps_mean": statistics.mean(s2) if s2 else None,
        "z": [f.test["z"] for f in fits],
        "successful": sum(int(np.asarray(jax.tree_util.tree_leaves(f.solution.result)[0])) == 0 for f in fits),
    }


def simulate_first(a, scene):
    return simulated(a, scene, 1000)


def simulated(a, scene, seed):
    """One baseline of ``scene``, with ``--slow-tail W`` a second, slow pulse tail of share W at 4x
    the fast time constant (what a real SPAD has and the default scene does not state)."""
    import numpy as np

    from tofjax.model import ModelOptions, Params
    from tofjax.simulate import simulate

    if not a.slow_tail:
        return simulate(scene, a.frames, seed=seed)
    truth = Params.from_scene(scene, np.float64)
    truth = truth.replace(pulse_slow_weight=np.asarray(a.slow_tail), pulse_slow_tail_s=np.asarray(4.0 * float(truth.pulse_tail_s)))
    return simulate(scene, a.frames, seed=seed, options=ModelOptions(pulse_tails=2), params=truth)


def compact_batch(a, pb, objective, solver, starts, D, G, base, A, nocov, vmapped, separate_mean_s) -> dict:
    """The same batch through ``fit_problem_compact`` (the stopped fits dropped every
    ``chunk_steps``): its first call (compiles), a warm call, its lane-steps and its agreement
    with the vmapped batch ``vmapped``."""
    import jax
    import numpy as np

    from tofjax.fit import CompactBatch, fit_problem_compact

    opts = CompactBatch()

    def call():
        sol, stats = fit_problem_compact(pb, objective, solver, starts, D, G, base, A, options=opts, return_stats=True, **nocov)
        return jax.block_until_ready(sol), stats

    t = time.perf_counter()
    call()
    first = time.perf_counter() - t
    _progress(f"compact batch of {a.batch}, first call (compiles) {first:.1f} s")
    t = time.perf_counter()
    sol, stats = call()
    batch_s = time.perf_counter() - t
    _progress(f"compact batch of {a.batch}: {batch_s:.3f} s; speed-up {a.batch * separate_mean_s / batch_s:.2f}x; "
              f"lane-steps {stats.lane_steps} (vmap {stats.vmap_lane_steps}, ideal {stats.ideal_lane_steps})")
    code = lambda s: np.asarray(jax.tree_util.tree_leaves(s.result)[0])  # noqa: E731
    return {"options": {"chunk_steps": opts.chunk_steps, "min_bucket": opts.min_bucket, "growth": opts.growth},
            "batch_s": batch_s, "batch_compile_s": first - batch_s, "speedup": a.batch * separate_mean_s / batch_s,
            **stats.as_dict(),
            "steps_equal_vmap": bool(np.array_equal(np.asarray(sol.steps), np.asarray(vmapped.steps))),
            "result_codes_equal_vmap": bool(np.array_equal(code(sol), code(vmapped))),
            "max_n1_diff_vs_vmap": float(np.max(np.abs(np.asarray(sol.params.n1) - np.asarray(vmapped.params.n1))))}


def batch_data(a, scene, dtype):
    """The batch's ``--batch`` (mean, sigma) pairs, simulated with seeds 2000, 2001, ...

    With ``--batch-data FILE`` (an ``.npz``), they are read from that file when it holds this scene,
    frame count and batch, and simulated and written to it otherwise: a machine whose time is short
    (a lent GPU) reads the data simulated beforehand elsewhere (the same seeds and the same code,
    so the same numbers up to the backend's rounding) instead of simulating 100 baselines itself.
    """
    import jax.numpy as jnp
    import numpy as np

    from tofjax.fit.calibrate import _data

    key = {"scene": a.scene, "frames": a.frames, "batch": a.batch, "seed0": 2000}
    if a.slow_tail:
        key["slow_tail"] = a.slow_tail
    path = Path(a.batch_data) if a.batch_data else None
    if path is not None and path.exists():
        with np.load(path) as z:
            stored = json.loads(str(z["key"]))
            if stored == key:
                _progress(f"batch: data read from {path}")
                return jnp.asarray(z["mean"], dtype), jnp.asarray(z["sigma"], dtype)
        _progress(f"batch: {path} holds {stored}, not {key}: simulating")
    pairs = [_data(simulated(a, scene, 2000 + i), dtype) for i in range(a.batch)]
    D = jnp.stack([p[0] for p in pairs])
    G = jnp.stack([p[1] for p in pairs])
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, mean=np.asarray(D), sigma=np.asarray(G), key=json.dumps(key))
        _progress(f"batch: data written to {path}")
    return D, G


def stage_times(a, cal, caps, scene, base, cfg, solver, objective, dtype) -> list:
    """Per capture: the time of each stage of a warm fit (timing start, envelope, the compiled fit
    without and with the covariance), the fit's steps and time per step, and (where this
    checkout's solver has ``trace``) the damping, gain ratio and Gauss-Newton predicted decrease
    of every step."""
    import inspect

    import jax
    import jax.flatten_util
    import numpy as np

    from tofjax.fit import solve as solve_mod
    from tofjax.fit._start import envelope_candidates, timing_start
    from tofjax.fit.calibrate import _anchor, _data, fit_problem

    pb = cal.problem
    kw = dict(max_steps=cfg.max_steps, loss_tol=cfg.loss_tol, gn_first=cfg.gn_first)
    traced = "trace" in inspect.signature(solve_mod.solve_marquardt).parameters
    rows = []
    for kind, c in caps:
        d, g = _data(c, dtype)
        row = {"data": kind}
        t = time.perf_counter()
        st, found = timing_start(pb, np.asarray(d), c.n_frames, scene, base)
        row["timing_s"] = time.perf_counter() - t
        t = time.perf_counter()
        start = envelope_candidates(pb, st, d, g, 1)[0]
        row["envelope_s"] = time.perf_counter() - t
        anchor = _anchor(st, found, cfg, dtype)
        for cov in (False, True):
            best = None
            for _ in range(max(a.repeats, 2)):
                t = time.perf_counter()
                sol = jax.block_until_ready(fit_problem(pb, objective, solver, start, d, g, base, anchor, **kw, with_cov=cov))
                dt = time.perf_counter() - t
                best = dt if best is None else min(best, dt)
            row["fit_with_cov_s" if cov else "fit_s"] = best
        row["steps"] = int(sol.steps)
        row["fit_s_per_step"] = row["fit_s"] / max(int(sol.steps), 1)
        h = np.asarray(sol.history)
        row["loss_history"] = h[np.isfinite(h)].tolist()
        if traced:
            row["trace"] = _trace(pb, solver, start, d, g, base, anchor, cfg)
        rows.append(row)
    return rows


def _trace(pb, solver, start, d, g, base, anchor, cfg) -> dict:
    """The first fit from ``start`` again with ``solve_marquardt(trace=True)``."""
    import equinox as eqx
    import jax
    import jax.flatten_util
    import numpy as np

    from tofjax.fit.solve import solve_marquardt

    @eqx.filter_jit
    def run(pb, solver, start, data, sigma, prior_params, anchor):
        p0, _, _, _ = pb.profile(start, data, sigma)
        u0 = pb.pack_jax(p0, pb.nonlinear)
        prior = pb.pack_jax(prior_params, pb.nonlinear)
        prior["n1_anchor"] = anchor
        f0, unravel = jax.flatten_util.ravel_pytree(u0)
        return solve_marquardt(lambda f, a: pb.residuals(unravel(f), a), solver, f0, (p0, data, sigma, prior),
                               max_steps=cfg.max_steps, loss_tol=cfg.loss_tol, trace=True)

    out = jax.device_get(run(pb, solver, start, d, g, base, anchor))
    n = int(out.steps) + 1  # a stop by the Gauss-Newton rule records its last look too
    return {k: np.asarray(v)[:n].tolist() for k, v in out.trace.items() if k != "y"}


def anchor_of(cfg, pb, scene, base, capture, dtype):
    import numpy as np

    from tofjax.fit._start import timing_start
    from tofjax.fit.calibrate import _anchor, _data

    d, _ = _data(capture, dtype)
    st, found = timing_start(pb, np.asarray(d), capture.n_frames, scene, base)
    return _anchor(st, found, cfg, dtype)


def _compare(fa: list, fb: list) -> dict:
    """Largest difference of the estimates of ``fa`` and ``fb`` in ``fa``'s standard errors:
    over n1 and mu_s + mu_a's parts, and over every free parameter."""
    import numpy as np

    worst, worst_key, named = 0.0, None, {}
    for x, y in zip(fa, fb):
        for k, v in x["values"].items():
            if k not in y["values"]:  # a parameter only one checkout fits (e.g. a new one)
                continue
            se = np.maximum(np.asarray(x["stderr"][k]), 1e-300)
            d = float(np.max(np.abs(np.asarray(v) - np.asarray(y["values"][k])) / se))
            named[k] = max(named.get(k, 0.0), d)
            if d > worst:
                worst, worst_key = d, k
    return {"max_stderr": worst, "where": worst_key, "per_parameter": named}


def compare_study(before: Path, after: Path) -> dict:
    """Two runs of experiments/study_calib_independent.py (e.g. main and this branch) on the same
    slice: per truth and column, both end points and the change of mu_t in its Laplace standard
    error (the study reports mu_t's) and of n1."""
    b, a = json.loads(before.read_text()), json.loads(after.read_text())
    rows = {}
    for col in ("own", "independent"):
        out = []
        for rb, ra, t in zip(b[col]["fits"], a[col]["fits"], b["truths"]):
            se = (rb["mu_t_stderr_rel"] or float("nan")) * t["mu_t_per_m"]
            out.append({"truth": t, "result": [rb["result"], ra["result"]], "n1": [rb["n1"], ra["n1"]],
                        "mu_t_per_m": [rb["mu_t_per_m"], ra["mu_t_per_m"]], "mu_t_stderr": se,
                        "mu_t_change_in_stderr": (ra["mu_t_per_m"] - rb["mu_t_per_m"]) / se,
                        "n1_change": ra["n1"] - rb["n1"], "reduced_chi2": [rb["reduced_chi2"], ra["reduced_chi2"]]})
        rows[col] = {"fits": out, "max_abs_mu_t_change_in_stderr": max(abs(r["mu_t_change_in_stderr"]) for r in out),
                     "max_abs_n1_change": max(abs(r["n1_change"]) for r in out),
                     "summary_before": b[col]["summary"], "summary_after": a[col]["summary"]}
    return {"what": "study_calib_independent slice, before (first file) and after (second file)", "simulated": True,
            "before": str(before), "after": str(after), "scene": b["scene"], "machine": b["machine"],
            "load_average": [b["load_average"], a["load_average"]]} | rows


def _collect(name, proc, runs, a):
    p_, dest, tree, t = proc
    _, err = p_.communicate()
    if p_.returncode:
        raise SystemExit(f"{name} ({tree}) failed:\n{err[-3000:]}")
    runs[name] = json.loads(dest.read_text()) | {"tree": tree, "process_s": time.perf_counter() - t}
    print(f"{name}: warm fit {runs[name]['warm_fit_s']*1e3:.0f} ms, compile {runs[name].get('compile_s', float('nan')):.1f} s"
          + (f", batch speed-up {runs[name]['batch']['speedup']:.2f}x" if a.batch else ""), flush=True)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True)
    p.add_argument("--baseline", help="another tofjax checkout to run side by side")
    p.add_argument("--scene", default="optoskin")
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--captures", type=int, default=3)
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--batch", type=int, default=100)
    p.add_argument("--separate", type=int, default=10, help="separate calls timed (their mean x batch is the serial time)")
    p.add_argument("--batch-mode", choices=("vmap", "compact", "both"), default="both",
                   help="vmap: the batch as one vmapped call; compact or both (default): also through fit_problem_compact, side by side")
    p.add_argument("--batch-data", help="an .npz of the batch's simulated data: read if it matches, else written")
    p.add_argument("--pulse-tails", choices=("1", "2", "auto"), default="2",
                   help="FitConfig.pulse_tails of the worker (default 2, what earlier runs measured); auto: the batch "
                        "runs the auto rule (fit_batch_tails) and records steps per stage")
    p.add_argument("--slow-tail", type=float, default=0.0,
                   help="simulate every baseline with a slow pulse tail of this share (4x the fast time constant; default 0: none)")
    p.add_argument("--simulate-batch-only", action="store_true",
                   help="with --batch-data: only simulate the batch's data and write the file (no fits)")
    p.add_argument("--reference", action="store_true", help="also a tight refit of every capture (slow)")
    p.add_argument("--reference-steps", type=int, default=400)
    p.add_argument("--indep", type=int, default=0, help="also this many independent baselines (tests/indep_sim.py)")
    p.add_argument("--no-compile", action="store_true", help="skip the compile-time measurement")
    p.add_argument("--no-stages", action="store_true", help="skip the per-stage times and the trace")
    p.add_argument("--lambda-trials", type=float, nargs="+", help="the per-stage times with MarquardtLM(lambda_trials=...)")
    p.add_argument("--parallel", action="store_true", help="run the two checkouts at the same time (a loaded machine: same load for both)")
    p.add_argument("--compare-study", nargs=2, type=Path, metavar=("BEFORE", "AFTER"),
                   help="instead: compare two calib_independent.json of the same slice; writes fit_bench_study_slice.json")
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if not 0.0 <= a.slow_tail < 0.5:
        p.error(f"--slow-tail: a share in [0, 0.5), got {a.slow_tail}")
    if a.compare_study:
        from tofjax.outputs import atomic_write_text

        Path(a.out).mkdir(parents=True, exist_ok=True)
        rep = compare_study(*a.compare_study)
        atomic_write_text(Path(a.out) / "fit_bench_study_slice.json", json.dumps(rep, indent=2))
        print(json.dumps({k: {kk: vv for kk, vv in v.items() if kk.startswith("max")} for k, v in rep.items() if k in ("own", "independent")}))
        return 0
    if a.simulate_batch_only:
        if not a.batch_data:
            p.error("--simulate-batch-only needs --batch-data FILE")
        import jax

        from tofjax.compile_cache import use_fast_cpu_compiler  # noqa: E402
        use_fast_cpu_compiler()  # the CLI's CPU compiler (before JAX's backend starts)
        jax.config.update("jax_enable_x64", True)
        from tofjax.scene import load_scene

        batch_data(a, load_scene(a.scene), jax.numpy.float64)
        return 0
    if a.worker:
        Path(a.out).write_text(json.dumps(worker(a)))
        return 0
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    trees = {"this": str(ROOT)} | ({"baseline": str(Path(a.baseline).resolve())} if a.baseline else {})
    runs = {}
    with tempfile.TemporaryDirectory() as tmp:
        procs = {}
        for name, tree in trees.items():
            dest = Path(tmp) / f"{name}.json"
            cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", "--out", str(dest),
                   "--scene", a.scene, "--frames", str(a.frames), "--captures", str(a.captures),
                   "--repeats", str(a.repeats), "--batch", str(a.batch), "--separate", str(a.separate), "--batch-mode", a.batch_mode,
                   *(["--batch-data", str(Path(a.batch_data).resolve())] if a.batch_data else []),
                   "--reference-steps", str(a.reference_steps), "--indep", str(a.indep), "--pulse-tails", a.pulse_tails, "--slow-tail", str(a.slow_tail)] \
                + (["--reference"] if a.reference and name == "this" else []) + (["--no-compile"] if a.no_compile else []) \
                + (["--no-stages"] if a.no_stages else []) \
                + (["--lambda-trials", *map(str, a.lambda_trials)] if a.lambda_trials else [])
            env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, (tree, os.environ.get("PYTHONPATH")))), TOFJAX_COMPILATION_CACHE="0", TOFJAX_PROGRAM_STORE="0")
            procs[name] = (subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True), dest, tree,
                           time.perf_counter())
            if not a.parallel:
                _collect(name, procs[name], runs, a)
        if a.parallel:
            for name, p_ in procs.items():
                _collect(name, p_, runs, a)
    report = {
        "what": "calibration fit speed on simulated baselines (issue 13 targets)",
        "simulated": True,
        "scene": a.scene, "frames": a.frames, "captures": a.captures, "repeats": a.repeats,
        "runs": runs,
        "targets": {"warm_fit_s": 0.05, "compile_s": 10.0, "batch_speedup": 10.0},
        "load_average_1min_end": os.getloadavg()[0], "parallel": a.parallel,
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "python": sys.version.split()[0]},
    }
    this = runs["this"]
    if "reference" in this:
        report["this_vs_reference"] = _compare(this["fits"], [{"values": r["values"]} for r in this["reference"]])
    if "baseline" in runs:
        b = runs["baseline"]
        report["ratios_baseline_over_this"] = {"warm_fit": b["warm_fit_s"] / this["warm_fit_s"]} | (
            {"compile": b["compile_s"] / this["compile_s"]} if "compile_s" in this else {}
        ) | ({"batch_call": b["batch"]["batch_s"] / this["batch"]["batch_s"]} if a.batch else {})
        report["this_vs_baseline"] = _compare(this["fits"], b["fits"])
        for kind in ("own", "independent"):
            pairs = [(x, y) for x, y in zip(this["fits"], b["fits"]) if x.get("data", "own") == kind]
            if pairs:
                report[f"this_vs_baseline_{kind}"] = _compare([x for x, _ in pairs], [y for _, y in pairs])
        report["steps"] = {name: {"warm_fits": [f["steps"] for f in r["fits"]],
                                  "fit_alone": [st["steps"] for st in r["stage_times"]],
                                  "fit_s_per_step": [st["fit_s_per_step"] for st in r["stage_times"]]}
                           for name, r in runs.items() if "stage_times" in r}
        report["warm_steps"] = {name: [f["steps"] for f in r["fits"]] for name, r in runs.items()}
        report["stage_medians_s"] = {
            name: {k: statistics.median(st[k] for st in r["stage_times"]) for k in ("timing_s", "envelope_s", "fit_s", "fit_with_cov_s")}
            for name, r in runs.items() if "stage_times" in r}
        if "reference" in this:
            report["baseline_vs_reference"] = _compare(
                [{"values": r["values"], "stderr": f["stderr"]} for r, f in zip(this["reference"], this["fits"])], b["fits"])
            report["this_vs_reference"] = _compare(
                [{"values": r["values"], "stderr": f["stderr"]} for r, f in zip(this["reference"], this["fits"])], this["fits"])
    from tofjax.outputs import atomic_write_text

    atomic_write_text(out / "fit_bench.json", json.dumps(report, indent=2))
    print(json.dumps({k: v for k, v in report.items() if k != "runs"}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
