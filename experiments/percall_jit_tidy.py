"""Per-call compiles removed from the greedy fit detector and the sensor fit's ``lm_fit``: the
second call's time, before (7dc992e) and after, and the outputs' bit identity.

Before, ``FitDetector`` made a ``jax.jit`` of a closure over the model, the optics and the baseline's
sigma for the model change and another for its Jacobian, so every new detector (another baseline or
calibration of the same scene) traced and compiled both again; ``lm_fit`` made
``jax.jit(jax.jacfwd(resid))`` on every call, so its Jacobian was traced and compiled on every fit
(``fit_sensor`` itself passed compiled functions cached per problem, so it was not affected: it is
timed here as a check that it stays so). After, module-level compiled functions take the model (an
``eqx.Module``) or the residual function and the data as arguments.

Cases (each call from scratch in one process, both calls timed):

- ``greedy``: ``build_fit_detector`` on the three-sensor small scene (tests/small_scenes.py) with the
  guided optics and 4 contact slots, then ``process`` of one two-contact frame; the second call with
  a baseline 10% brighter (new data, same shapes).
- ``greedy_change_call``: one evaluation of the detector's weighted model change, median of 200 (the
  dispatch cost of ``eqx.filter_jit`` over the model pytree against ``jax.jit`` of a closure).
- ``lm_fit``: ``lm_fit`` of the sensor fit's per-zone residual (14 frames, 64 bins, 2 knots per bin)
  on a synthetic capture; the second on fresh noise.
- ``fit_sensor``: the whole sensor fit of that capture (fast options); the second on fresh noise.

``lm_fit`` and ``fit_sensor`` are called five times (``later_median_s``: calls 2-5). Then, in one process of
this tree (``in_one_process``): ``lm_fit``'s residual and Jacobian per call, compiled as before and
module-level; and one detector's change and Jacobian compiled both ways (module-level,
and a ``jax.jit`` of a closure as before): the per-evaluation difference, the detections and chi-square
of the same frames, and the time per frame and per model evaluation, interleaved (module-level
arguments are not folded in as constants: each evaluation computes what the closure's program had
folded at compile time).

Each variant runs in its own process (``before``: the package at 7dc992e from ``git archive``;
``after``: this tree), alternating ``--rounds`` times. Float64, no persistent compilation cache.
Simulated scenes and histograms, no data. Writes JSON.

    python experiments/percall_jit_tidy.py --out docs/results/percall_jit_tidy.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
from pathlib import Path

from percall_jit import run_variants, worker_env

BASE = "7dc992e"
CASES = ("greedy", "lm_fit", "fit_sensor")
ROOT = Path(__file__).resolve().parents[1]


def _greedy_case():
    """The small scene (guided, skin contacts, 16x exposure), its baseline, two contacts' expected frame
    and the guided optics (as tests/test_invert_fit.py's slow test)."""
    import dataclasses

    import numpy as np
    from small_scenes import three_sensor_square

    from tofjax.invert.correction import OpticalParams
    from tofjax.model import ModelOptions
    from tofjax.model.contact import SkinContact
    from tofjax.scene import Touch
    from tofjax.simulate import expected_counts

    sc = three_sensor_square()
    sc = sc.replace(waveguide=dataclasses.replace(sc.waveguide, volume_backscatter_fraction=0.5))
    base = expected_counts(sc, ModelOptions(optics="guided")) * 16
    truth = np.array([[0.06, 0.09, 0.9], [0.10, 0.05, 0.8]])
    touch = expected_counts(sc.replace(touches=tuple(Touch((x, y), 0.006, s) for x, y, s in truth)),
                            ModelOptions(optics="guided", skin=SkinContact())) * 16
    optical = dataclasses.replace(OpticalParams.from_scene(sc), optics="guided")
    optical = dataclasses.replace(optical, gain=tuple(g * 16 for g in optical.gain))
    return sc, base, truth, touch, optical


def _setup():
    import jax

    jax.config.update("jax_enable_x64", True)
    sys.path.insert(0, str(ROOT / "tests"))  # the small scene and the synthetic sensor (not the package)


def ab_worker() -> dict:
    """In one process (this tree), one detector with its model change and Jacobian compiled both ways:
    module-level (as now) and a ``jax.jit`` of a closure over the model, optics and sigma (as before, so
    XLA folds them in as constants); ``process`` of the same frames by each, interleaved."""
    import time

    import jax
    import jax.numpy as jnp
    import numpy as np

    _setup()
    from tofjax.invert.greedy import FitDetectOptions, _contact_change, build_fit_detector

    sc, base, truth, touch, optical = _greedy_case()
    frames = np.random.default_rng(1).poisson(np.stack([touch] * 3 + [base])).astype(float)
    new = build_fit_detector(sc, base, optical, FitDetectOptions(cell_m=0.01, max_contacts=4), n_baseline=100)
    old = new.with_options(new.options)
    change, _ = _contact_change(sc, optical, 4, 0.006)
    sig = jnp.asarray(new.sigma)

    def weighted(t):
        return change(t) / sig

    old._change, old._jac = jax.jit(weighted), jax.jit(jax.jacfwd(weighted))
    rng = np.random.default_rng(0)
    thetas = [jnp.asarray(np.r_[rng.uniform(0.02, 0.13, 8), rng.uniform(0, 1, 4)]) for _ in range(8)]
    dc = max(float(np.max(np.abs(new._change(t) - old._change(t)) / np.max(np.abs(old._change(t))))) for t in thetas)
    dj = max(float(np.max(np.abs(new._jac(t) - old._jac(t)) / np.max(np.abs(old._jac(t))))) for t in thetas)
    ra, rb = new.process(frames), old.process(frames)  # (also compiles both)
    pos = [np.abs(a.positions() - b.positions()).max(initial=0.0) if a.positions().shape == b.positions().shape
           else np.inf for a, b in zip(ra.detections, rb.detections)]
    per = {"module_level": [], "closure": []}
    for _ in range(4):
        for k, d in (("module_level", new), ("closure", old)):
            t = time.perf_counter()
            d.process(frames)
            per[k].append((time.perf_counter() - t) / len(frames))
    ev = {"module_level": [], "closure": []}
    for _ in range(5):
        for k, d in (("module_level", new), ("closure", old)):
            t = time.perf_counter()
            for th in thetas * 10:
                jax.block_until_ready(d._change(th))
            ev[k].append((time.perf_counter() - t) / 80)
    # the greedy case's second call (baseline x1.1: a poor fit, chi-square ~3e4, four contacts): how far
    # rounding alone moves the search there: module-level, closure, and closure with sigma moved by 1 ulp
    b2 = build_fit_detector(sc, base * 1.1, optical, FitDetectOptions(cell_m=0.01, max_contacts=4), n_baseline=100)
    second = {"module_level": b2}
    for name, eps in (("closure", 0.0), ("closure_sigma_plus_1ulp", np.finfo(float).eps)):
        d = b2.with_options(b2.options)
        d.sigma = b2.sigma * (1.0 + eps)
        sg = jnp.asarray(d.sigma)

        def w2(t, sg=sg):
            return change(t) / sg

        d._change, d._jac = jax.jit(w2), jax.jit(jax.jacfwd(w2))
        second[name] = d
    x11 = {k: d.process(frames[:1]) for k, d in second.items()}
    # lm_fit's residual and Jacobian of the sensor fit's zone problem: as fit_pulse compiled them before
    # (a jax.jit of the cached residual) and module-level now, per call, interleaved
    from test_sensor_fit import FAST, _truth_model

    from tofjax.sensor import expected_counts as sensor_counts
    from tofjax.sensor.fit import _jacobian, _residual, _zone_problem

    h = np.random.default_rng(3).poisson(sensor_counts(_truth_model(), np.linspace(0.05, 0.35, 14))).astype(float)[:, 0]
    q = FAST.knots_per_bin
    K = int(round(FAST.pulse_bins * q)) + 1
    resid = _zone_problem(K, 14, -FAST.pulse_before_bins, 1.0 / q, h.shape[1], FAST.pile_up, FAST.smoothness, FAST.dnl,
                          FAST.order, False)[2]
    x = np.concatenate([np.ones(K), [15.0], np.full(14, 20.0), np.full(14, 8.0), np.full(14, 100.0)])
    args = (jnp.asarray(h), jnp.ones(14), jnp.full(14, 20.0), jnp.asarray(0.0))
    fns = {"residual_closure": jax.jit(resid), "residual_module_level": lambda *a: _residual(resid, *a),
           "jacobian_closure": jax.jit(jax.jacfwd(resid)), "jacobian_module_level": lambda *a: _jacobian(resid, *a)}
    lm_same = all(np.array_equal(fns[f"{k}_closure"](x, *args), fns[f"{k}_module_level"](x, *args)) for k in ("residual", "jacobian"))
    lm_t = {k: [] for k in fns}
    for _ in range(5):
        for k, f in fns.items():
            t = time.perf_counter()
            for _ in range(50):
                np.asarray(f(x, *args))
            lm_t[k].append((time.perf_counter() - t) / 50)
    return {
        "lm_fit_bit_identical": lm_same, "lm_fit_call_s_median": {k: statistics.median(v) for k, v in lm_t.items()},
        "baseline_x1.1_chi2": {k: float(r.chi2[0]) for k, r in x11.items()},
        "baseline_x1.1_positions_m": {k: r.detections[0].positions().round(6).tolist() for k, r in x11.items()},
        "change_max_rel_difference": dc, "jacobian_max_rel_difference": dj,
        "contacts_found": [[len(a.touches), len(b.touches)] for a, b in zip(ra.detections, rb.detections)],
        "position_max_abs_difference_m": [float(p) for p in pos],
        "chi2_max_rel_difference": float(np.max(np.abs(ra.chi2 / rb.chi2 - 1))),
        "process_s_per_frame": per, "process_s_per_frame_median": {k: statistics.median(v) for k, v in per.items()},
        "change_eval_s": ev, "change_eval_s_median": {k: statistics.median(v) for k, v in ev.items()},
    }


def worker(dump: str) -> dict:
    import time

    import jax
    import numpy as np

    _setup()
    import jax.numpy as jnp
    from test_sensor_fit import FAST, _truth_model

    from tofjax.invert.greedy import FitDetectOptions, build_fit_detector
    from tofjax.sensor import expected_counts as sensor_counts
    from tofjax.sensor import fit_sensor
    from tofjax.sensor.fit import _zone_problem, lm_fit, line_fit, peak_positions

    sc, base, truth, touch, optical = _greedy_case()
    frame = np.random.default_rng(1).poisson(touch)[None].astype(float)
    dets = []

    def greedy(i):
        det = build_fit_detector(sc, base * (1.0 + 0.1 * i), optical, FitDetectOptions(cell_m=0.01, max_contacts=4),
                                 n_baseline=100)
        dets.append(det)
        res = det.process(frame)
        return np.concatenate([np.ravel(res.detections[0].positions()), res.chi2])

    strue = _truth_model()
    d = np.linspace(0.05, 0.35, 14)
    lam = sensor_counts(strue, d)

    def capture(i):
        return np.random.default_rng(3 + i).poisson(lam).astype(float)

    def lm(i):
        h = capture(i)[:, 0]
        a, b, *_ = line_fit(d, peak_positions(h[:, None])[:, 0])
        shift0 = a + b * d
        q, F, B = FAST.knots_per_bin, len(d), h.shape[1]
        K = int(round(FAST.pulse_bins * q)) + 1
        resid = _zone_problem(K, F, -FAST.pulse_before_bins, 1.0 / q, B, FAST.pile_up, FAST.smoothness, FAST.dnl,
                              FAST.order, False)[2]
        u = -FAST.pulse_before_bins + np.arange(K) / q
        prof = np.exp(-0.5 * ((u - 1.0) / 0.6) ** 2)
        amb0 = np.median(h[:, :6], 1)
        th0 = np.concatenate([prof / (prof.sum() / q), [np.log(4e6)], shift0, np.log(h.sum(1)), amb0])
        args = (jnp.asarray(h), jnp.ones(F), jnp.asarray(shift0), jnp.asarray(0.0))
        return lm_fit(resid, th0, args, max_iterations=FAST.max_iterations)[0]

    def sensor(i):
        m, _ = fit_sensor(capture(i), d, FAST, grid=(1, 1))
        return np.concatenate([[m.bin_width_s], np.ravel(m.pulse), np.ravel(m.zero_range_bins)])

    out, arrays = {}, {}
    for name, fn, calls in (("greedy", greedy, 2), ("lm_fit", lm, 5), ("fit_sensor", sensor, 5)):
        ts, ys = [], []
        for i in range(calls):
            t = time.perf_counter()
            ys.append(np.asarray(jax.block_until_ready(fn(i))))
            ts.append(time.perf_counter() - t)
        out[name] = {"first_s": ts[0], "second_s": ts[1], "later_median_s": statistics.median(ts[1:])}
        arrays[name] = np.concatenate(ys)
    theta = jnp.asarray(np.r_[truth[:, 0], 0.1, 0.1, truth[:, 1], 0.1, 0.1, truth[:, 2], 0.0, 0.0])
    det = dets[-1]
    calls = []
    for _ in range(200):
        t = time.perf_counter()
        jax.block_until_ready(det._change(theta))
        calls.append(time.perf_counter() - t)
    out["greedy_change_call"] = {"median_s": statistics.median(calls)}
    np.savez(dump, **arrays)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", help="JSON file to write (required unless --worker)")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--ab", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--dump", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        print(json.dumps(worker(a.dump)))
        return 0
    if a.ab:
        print(json.dumps(ab_worker()))
        return 0
    if not a.out:
        ap.error("--out is required")
    from tofjax.outputs import atomic_write_text, check_output

    check_output(a.out, overwrite=True)
    runs, identical, loads = run_variants(__file__, BASE, CASES, a.rounds, "percall_jit_tidy_", ["--worker"])
    r = subprocess.run([sys.executable, __file__, "--ab"], env=worker_env(ROOT), cwd=ROOT, capture_output=True, text=True)
    if r.returncode:
        raise SystemExit(f"A/B worker failed: {r.stderr.strip().splitlines()[-3:]}")
    ab = json.loads(r.stdout.strip().splitlines()[-1])
    print("ab", ab, flush=True)
    loads.append(os.getloadavg()[0])
    med = {v: {c: {t: statistics.median(x[c][t] for x in rs) for t in rs[0][c]} for c in CASES}
           for v, rs in runs.items()}
    for v, rs in runs.items():
        med[v]["greedy_change_call"] = {"median_s": statistics.median(x["greedy_change_call"]["median_s"] for x in rs)}
    out = {
        "what": "second-call time (each call from scratch in one process) of the greedy fit detector and lm_fit, "
                f"before ({BASE}: a jax.jit of a closure per detector / per fit) and after (module-level compiled "
                "functions taking the model or residual and the data as arguments); fit_sensor as a check",
        "data": "simulated (tofjax's guided model on the three-sensor small scene; a synthetic TMF882x sensor), no data",
        "cases": {"greedy": "build_fit_detector (small scene, guided, 4 slots, 1 cm cells) + process of one frame; "
                            "second call: baseline x1.1",
                  "lm_fit": "lm_fit of the sensor fit's zone residual (14 frames, 64 bins); second call: fresh noise",
                  "fit_sensor": "fit_sensor of that capture (fast options); second call: fresh noise",
                  "greedy_change_call": "one call of the detector's weighted model change (median of 200)"},
        "runs": runs, "median_s": med,
        "second_call_speedup_before_over_after": {c: med["before"][c]["second_s"] / med["after"][c]["second_s"] for c in CASES},
        "change_call_ratio_after_over_before": med["after"]["greedy_change_call"]["median_s"]
        / med["before"]["greedy_change_call"]["median_s"],
        "bit_identical": identical,
        "in_one_process": ab,
        "in_one_process_note": "lm_fit_*: the sensor fit's zone residual and Jacobian per call (14 frames, 64 bins), "
                               "compiled as fit_pulse did before and module-level, interleaved; the rest: one detector, its change and Jacobian compiled module-level (now) and as a "
                                      "jax.jit of a closure (before: the model, optics and sigma folded in as "
                                      "constants), process of the same 4 frames (3 two-contact, 1 no-touch) "
                                      "interleaved; per-evaluation differences relative to the largest value",
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "load_average_1min": loads,
                    "note": "the 2-core shared CPU VM, loaded by other helpers and the lead: compare only within one run"},
    }
    atomic_write_text(a.out, json.dumps(out, indent=1) + "\n")
    print(json.dumps(out["second_call_speedup_before_over_after"]), json.dumps(identical))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
