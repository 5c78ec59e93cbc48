"""The compacting batch of calibration fits against the plain vmapped batch and the loop, on
**simulated** 100-frame baselines of the default OptoSkin scene (seeds 2000, 2001, ...: the first
of ``bench_fit.py --batch``'s), all from one fixed start (the envelope start of seed 1000's
capture, as ``bench_fit.py --batch`` does), with the default two-tail fit (which has stragglers:
docs/calibration.md, "Straggler fits").

Reported: lane-steps (sum over compiled calls of batch size x loop passes; the machine-independent
work a vmapped device does) of the plain vmap (n x the slowest fit's passes), the compacting batch
(counted as it runs) and the ideal (each fit's own passes); the same accounting replayed from the
fits' step counts for other ``CompactBatch`` options (exact: a fit's steps do not depend on how
the batch is cut); the warm wall time of the loop, the vmapped batch and the compacting batch on
this machine (interleaved, medians); the compiles (count and seconds) of the first calls; and the
agreement of the compacting batch with the vmapped one.

    TOFJAX_PROGRAM_STORE=0 python experiments/bench_batch_compact.py --out docs/results/batch_compact_cpu.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EVENT = "/jax/core/compile/backend_compile_duration"


def _progress(msg):
    print(f"[batch_compact {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


class Compiles:
    """Counts XLA compilations and their seconds while active."""

    def __enter__(self):
        import jax

        self.n, self.s = 0, 0.0
        jax.monitoring.register_event_duration_secs_listener(self._on)
        return self

    def _on(self, event, secs, **_):
        if event == EVENT:
            self.n += 1
            self.s += secs

    def __exit__(self, *exc):
        from jax._src import monitoring

        monitoring.unregister_event_duration_listener(self._on)


def replay(fit_passes, options, max_passes=None) -> dict:
    """The compacting batch's calls and lane-steps for ``options``, replayed from each fit's own
    loop passes (a fit's trajectory does not depend on the batch it runs in)."""
    import numpy as np

    left = np.asarray(fit_passes, int).copy()
    n, calls = left.size, []
    while (left > 0).any():
        active = left > 0
        size = options.bucket(n, int(active.sum()))
        run = np.minimum(left[active], options.chunk_steps)
        calls.append((size, int(run.max())))
        left[active] -= run
    return {"chunk_steps": options.chunk_steps, "min_bucket": options.min_bucket, "growth": options.growth,
            "calls": len(calls), "programs": len({b for b, _ in calls}), "lane_steps": sum(b * p for b, p in calls),
            "calls_detail": calls}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=40, help="fits in the batch (seeds 2000 .. 2000 + n - 1)")
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--repeats", type=int, default=2, help="warm calls of each mode (interleaved)")
    p.add_argument("--chunk-steps", type=int, default=16)
    p.add_argument("--min-bucket", type=int, default=8)
    p.add_argument("--growth", type=int, default=2)
    p.add_argument("--no-vmap", action="store_true", help="skip the plain vmapped batch (its lane-steps need no run)")
    p.add_argument("--out", default="docs/results/batch_compact_cpu.json")
    a = p.parse_args(argv)
    os.environ.setdefault("TOFJAX_PROGRAM_STORE", "0")
    import jax

    from tofjax.compile_cache import use_fast_cpu_compiler  # noqa: E402
    use_fast_cpu_compiler()  # the CLI's CPU compiler (before JAX's backend starts)
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    from tofjax.fit import CompactBatch
    from tofjax.fit._start import envelope_candidates, timing_start
    from tofjax.fit.calibrate import Calibrator, _anchor, _data, fit_problem_batch, fit_problem_compact
    from tofjax.scene import load_scene
    from tofjax.simulate import simulate

    scene = load_scene("optoskin")
    cal = Calibrator(scene)
    pb, cfg = cal.problem, cal.config
    solver, objective = cfg.make_solver(), cfg.make_objective()
    base, dtype = cal.base_params(), pb.model.geometry.ray_length.dtype
    c0 = simulate(scene, a.frames, seed=1000)
    d0, s0 = _data(c0, dtype)
    st, found = timing_start(pb, np.asarray(d0), a.frames, scene, base)
    start = envelope_candidates(pb, st, d0, s0, 1)[0]
    anchor = _anchor(st, found, cfg, dtype)
    pairs = [_data(simulate(scene, a.frames, seed=2000 + i), dtype) for i in range(a.n)]
    D, G = jnp.stack([x for x, _ in pairs]), jnp.stack([g for _, g in pairs])
    starts = jax.tree_util.tree_map(lambda x: jnp.stack([x] * a.n), start)
    A = jnp.stack([anchor] * a.n)
    kw = dict(max_steps=cfg.max_steps, loss_tol=cfg.loss_tol, gn_first=cfg.gn_first, with_cov=False)
    opts = CompactBatch(chunk_steps=a.chunk_steps, min_bucket=a.min_bucket, growth=a.growth)
    _progress(f"{a.n} baselines simulated; compiling")

    def vmap_call():
        return jax.block_until_ready(fit_problem_batch(pb, objective, solver, starts, D, G, base, A, **kw))

    def compact_call():
        sol, stats = fit_problem_compact(pb, objective, solver, starts, D, G, base, A, options=opts, return_stats=True, **kw)
        return jax.block_until_ready(sol), stats

    path = ROOT / a.out if not Path(a.out).is_absolute() else Path(a.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    code = lambda s: np.asarray(jax.tree_util.tree_leaves(s.result)[0])  # noqa: E731
    out = {
        "what": "compacting batch of calibration fits (stopped fits dropped every chunk_steps) vs the plain vmapped batch",
        "simulated": True,
        "data": f"simulated: tofjax.simulate.simulate(load_scene('optoskin'), {a.frames}, seed=s), s = 2000 .. {2000 + a.n - 1}; "
                "one fixed start (envelope start of seed 1000), default FitConfig (two-tail pulse), no covariance",
        "command": "TOFJAX_PROGRAM_STORE=0 python experiments/bench_batch_compact.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "options": {"chunk_steps": opts.chunk_steps, "min_bucket": opts.min_bucket, "growth": opts.growth, "buckets": opts.buckets(a.n)},
        "phases_done": [],
    }

    def write(phase):
        out["phases_done"].append(phase)
        out["machine"] = (f"{platform.node()} ({os.cpu_count()} CPU cores, shared with other jobs); jax {jax.__version__} "
                          f"{jax.default_backend()}; load average at this write {os.getloadavg()}")
        path.write_text(json.dumps(out, indent=1) + "\n")
        _progress(f"{phase}: wrote {path}")

    # 1. the compacting batch, first call (compiles): every fit's own steps, hence all lane-step figures
    with Compiles() as cc:
        t = time.perf_counter()
        comp, stats = compact_call()
        wall = time.perf_counter() - t
    comp = jax.device_get(comp)
    steps = np.asarray(comp.steps)
    passes = np.asarray(stats.fit_steps)
    options = [CompactBatch(chunk_steps=c, min_bucket=m, growth=g) for c in (4, 8, 16, 32) for m, g in ((1, 2), (8, 2), (4, 4))]
    out |= {
        "steps": {"per_fit": steps.tolist(), "mean": float(steps.mean()), "max": int(steps.max()),
                  "at_limit": int(np.sum(steps >= cfg.max_steps)), "successful": int(np.sum(code(comp) == 0))},
        "lane_steps": {"vmap": stats.vmap_lane_steps, "compact": stats.lane_steps, "ideal": stats.ideal_lane_steps,
                       "vmap_over_compact": stats.vmap_lane_steps / stats.lane_steps,
                       "compact_over_ideal": stats.lane_steps / stats.ideal_lane_steps,
                       "note": "steps = loop passes, the start's own first pass included (each fit's steps + 1); "
                               "vmap = n x the slowest fit's passes (what one vmapped while_loop runs)"},
        "compact_first_call": {"wall_s": wall, "compiles": cc.n, "compile_s": cc.s, "calls": [list(c) for c in stats.calls],
                               "call_s": stats.call_s},
        "replay_matches_run": replay(passes, opts)["lane_steps"] == stats.lane_steps,
        "replayed_options": [replay(passes, o) for o in options],
    }
    _progress(f"compact first call {wall:.1f} s, {cc.n} compiles ({cc.s:.1f} s); lane-steps vmap {stats.vmap_lane_steps}, "
              f"compact {stats.lane_steps}, ideal {stats.ideal_lane_steps}")
    write("compact_first_call")
    # 2. warm compacting calls: per call, its batch size, passes and seconds -> seconds per pass at each size
    warm = {"compact": [], "vmap": []}
    per_pass = {}
    for _ in range(a.repeats):
        t = time.perf_counter()
        _, st2 = compact_call()
        warm["compact"].append(time.perf_counter() - t)
        for (size, npass), sec in zip(st2.calls, st2.call_s):
            per_pass.setdefault(size, []).append(sec / max(npass, 1))
        _progress(f"warm compact: {warm['compact'][-1]:.1f} s (load {os.getloadavg()[0]:.1f})")
    if warm["compact"]:
        pp = {str(k): statistics.median(v) for k, v in per_pass.items()}
        out["compact_warm_s"] = warm["compact"]
        out["seconds_per_pass_by_batch_size"] = pp
        out["vmap_estimated_from_per_pass_s"] = stats.vmap_lane_steps / a.n * pp[str(a.n)]
        out["note_estimate"] = ("the plain vmap's time estimated as (slowest fit's passes) x (warm seconds per pass of "
                                "the compacting batch's full-size calls); an estimate from this machine's warm per-pass time, "
                                "not a measured vmapped call")
        write("compact_warm")
    # 3. the plain vmapped batch (compiles, then warm), and the agreement
    if not a.no_vmap:
        with Compiles() as cc:
            t = time.perf_counter()
            plain = jax.device_get(vmap_call())
            wall = time.perf_counter() - t
        out["vmap_first_call"] = {"wall_s": wall, "compiles": cc.n, "compile_s": cc.s}
        out["agreement"] = {
            "steps_equal": bool(np.array_equal(np.asarray(plain.steps), steps)),
            "result_codes_equal": bool(np.array_equal(code(comp), code(plain))),
            "max_abs_n1_diff_compact_vs_vmap": float(np.max(np.abs(np.asarray(comp.params.n1) - np.asarray(plain.params.n1)))),
            "max_rel_chi2_diff_compact_vs_vmap": float(np.max(np.abs(np.asarray(comp.chi2) / np.asarray(plain.chi2) - 1))),
        }
        write("vmap_first_call")
        for _ in range(a.repeats):
            t = time.perf_counter()
            vmap_call()
            warm["vmap"].append(time.perf_counter() - t)
            t = time.perf_counter()
            compact_call()
            warm["compact"].append(time.perf_counter() - t)
            _progress(f"warm vmap {warm['vmap'][-1]:.1f} s, compact {warm['compact'][-1]:.1f} s (load {os.getloadavg()[0]:.1f})")
            out["warm_s"] = warm
            out["warm_median_s"] = {k: statistics.median(v) for k, v in warm.items() if v}
            out["warm_ratio_vmap_over_compact"] = out["warm_median_s"]["vmap"] / out["warm_median_s"]["compact"]
            write("warm_pair")
    return 0


if __name__ == "__main__":
    sys.exit(main())
