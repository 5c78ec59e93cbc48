"""``FitConfig.pulse_tails = "auto"`` against 1 and 2 (issue 13, straggler fits), on **simulated** data.

Runs the whole warm ``Calibrator(scene, FitConfig(pulse_tails=T)).fit`` on 100-frame baselines of
the default OptoSkin scene, seeds 2000-2039 (``bench_fit.py``'s batch seeds), and records per fit:
the steps of every fit stage and their sum, the wall time, the result, n1, mu_s + mu_a, the reduced
chi-square, the tails fitted and (``"auto"``) the score test. ``--data``:

* ``tailless``: the scene as it is (``pulse_slow_weight = 0``: no slow tail);
* ``slow``: the same seeds simulated with a slow tail of share 0.1 at 4x the fast time constant
  (``straggler_fits.py --slow-tail 0.1``);
* ``independent``: baselines of the independent simulator (``tests/indep_sim.py``, its own pulse),
  ``--indep`` rigs;
* ``tmf8820``: real histograms (not simulated), the score statistic on a one-EMG fit of each
  (:func:`tmf8820`).

A first fit of the first baseline (not recorded) compiles. One process per ``--data``:

    TOFJAX_PROGRAM_STORE=0 python experiments/pulse_tail_choice.py --data tailless --out /tmp/ptc_tailless.json
    TOFJAX_PROGRAM_STORE=0 python experiments/pulse_tail_choice.py --data slow --tails auto 2 --out /tmp/ptc_slow.json
    python experiments/pulse_tail_choice.py --merge /tmp/ptc_*.json --out docs/results/pulse_tail_choice.json
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


def _tails(v: str):
    return v if v == "auto" else int(v)


def fit_steps(res) -> int:
    """Steps of every fit the calibration ran (restarts and both tail models included)."""
    return sum(int(s["steps"]) for s in res.stages if str(s.get("stage", "")).startswith("fit from start"))


def captures(a, scene):
    import numpy as np

    from tofjax.simulate import simulate

    if a.data == "independent":
        sys.path.insert(0, str(ROOT / "tests"))
        from indep_sim import IndepRig
        from indep_sim import simulate as simulate_independent

        from tofjax.capture import Capture

        for i in range(a.indep):
            rig = IndepRig.from_scene(scene, seed=200 + i)
            c = simulate_independent(rig, contacts=np.zeros((0, 3)), frames=a.frames, seed=300 + i)
            yield 300 + i, (c if isinstance(c, Capture) else Capture(scene, np.asarray(c)))
        return
    kw = {}
    if a.data == "slow":
        from tofjax.model import ModelOptions, Params

        truth = Params.from_scene(scene, np.float64)
        kw = {"options": ModelOptions(pulse_tails=2),
              "params": truth.replace(pulse_slow_weight=np.asarray(0.1), pulse_slow_tail_s=np.asarray(4.0 * float(truth.pulse_tail_s)))}
    for s in a.seeds:
        yield s, simulate(scene, a.frames, seed=s, **kw)


def tmf8820(path: Path) -> dict:
    """The same score statistic on real TMF8820 histograms (``tests/data/tmf8820-plane-sweep``): each
    frame's reference histogram and centre zone, fitted with one binned EMG plus a constant (Poisson
    weights, bins as the time unit), then ``z = -j_perp . r / |j_perp|`` for the slow tail's share at
    0 at ratios 2, 4, 8 (:mod:`tofjax.fit._tails`'s formula, on this small model: a waveguide
    calibration needs a waveguide baseline, which the real data set is not)."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from scipy.optimize import least_squares

    from tofjax.fit._tails import SLOW_RATIOS
    from tofjax.model.pulse import pulse_cdf

    frames = json.loads(path.read_text())
    b = jnp.arange(128, dtype=jnp.float64)

    def model(th, w=0.0, ratio=4.0):
        la, t0, ls, lt, lc = th
        sig, tau = jnp.exp(ls), jnp.exp(lt)
        edge = lambda x: pulse_cdf(x - t0, sig, tau, w, ratio * tau)  # noqa: E731
        return jnp.exp(la) * (edge(b + 0.5) - edge(b - 0.5)) + jnp.exp(lc)

    rows = []
    for i, f in enumerate(frames):
        for name, h in (("reference", f["reference_hist"]), ("centre zone", f["hists"][4])):
            h = np.asarray(h, np.float64)
            sd = np.sqrt(np.maximum(h, 1.0))
            res = jax.jit(lambda th, h=h, sd=sd: (model(th) - h) / sd)
            jac = jax.jit(jax.jacfwd(lambda th, h=h, sd=sd: (model(th) - h) / sd))
            pk = int(np.argmax(h))
            th0 = np.array([np.log(h.sum()), pk, np.log(0.5), np.log(1.5), np.log(max(np.median(h[:5]), 1.0))])
            fit = least_squares(lambda t: np.asarray(res(t)), th0, jac=lambda t: np.asarray(jac(t)), method="lm", max_nfev=2000)
            th = jnp.asarray(fit.x)
            r, J = np.asarray(res(th)), np.asarray(jac(th))
            zs = []
            for q in SLOW_RATIOS:
                j = np.asarray(jax.jvp(lambda w, q=q, h=h, sd=sd: (model(th, w, q) - h) / sd, (0.0,), (1.0,))[1])
                perp = j - J @ np.linalg.lstsq(J, j, rcond=None)[0]
                zs.append(float(-(perp @ r) / np.linalg.norm(perp)))
            rows.append({"frame": i, "histogram": name, "distance_m": f["dist_to_plane"], "one_tail_reduced_chi2": float(r @ r / (r.size - 5)),
                         "z_per_ratio": dict(zip(map(str, SLOW_RATIOS), zs)), "z": max(zs)})
            print(f"[pulse_tail_choice] tmf8820 frame {i} {name}: z {max(zs):.1f}", file=sys.stderr, flush=True)
    return {"fits": rows, "z_min": min(r["z"] for r in rows), "z_max": max(r["z"] for r in rows)}


def run(a, save=lambda runs: None) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    from tofjax.fit.calibrate import Calibrator, FitConfig
    from tofjax.scene import load_scene

    scene = load_scene("optoskin")
    caps = list(captures(a, scene))
    out = {}
    for tails in a.tails:
        cal = Calibrator(scene, FitConfig(pulse_tails=tails))
        t = time.perf_counter()
        cal.fit(caps[0][1])  # compiles what this data needs (auto: both tail models on slow-tail data)
        first = time.perf_counter() - t
        rows = []
        for seed, cap in caps:
            t = time.perf_counter()
            r = cal.fit(cap)
            dt = time.perf_counter() - t
            p = r.params
            rows.append({"seed": seed, "steps": fit_steps(r), "final_steps": int(r.steps), "fit_s": dt, "result": r.result,
                         "pulse_tails": int(r.pulse_tails), "n1": float(p.n1), "n1_stderr": float(r.stderr["n1"]),
                         "mu_t": float(p.mu_s_per_m + p.mu_a_per_m), "reduced_chi2": float(r.reduced_chi2),
                         "z": None if r.pulse_tail_test is None else r.pulse_tail_test["z"],
                         "z_per_ratio": None if r.pulse_tail_test is None else r.pulse_tail_test["z_per_ratio"],
                         "slow_weight": float(p.pulse_slow_weight),
                         "stages": [{k: v for k, v in s.items() if k in ("stage", "steps", "result", "z", "two_tails")}
                                    for s in r.stages if "steps" in s or s.get("stage") == "pulse tails"]})
            print(f"[pulse_tail_choice] {a.data} tails {tails} seed {seed}: {rows[-1]['steps']} steps, {dt:.2f} s, "
                  f"{r.result}, chose {r.pulse_tails}, z {rows[-1]['z']}", file=sys.stderr, flush=True)
        out[str(tails)] = {"first_fit_s": first, "fits": rows, "summary": summary(rows)}
        save(out)  # a run stopped later keeps what it finished
    return out


def from_log(path: Path) -> dict:
    """A part from a run's progress log (a run stopped at a deadline before writing its JSON): per
    fit the seed, steps, wall time, result, tails chosen and z (no estimates)."""
    import re

    pat = re.compile(r"\] (\w+) tails (\w+) seed (\d+): (\d+) steps, ([\d.]+) s, (\w+), chose (\d), z (\S+)")
    runs: dict = {}
    data = None
    for line in path.read_text().splitlines():
        m = pat.search(line)
        if not m:
            continue
        data, tails = m.group(1), m.group(2)
        z = None if m.group(8) == "None" else float(m.group(8))
        runs.setdefault(tails, {"fits": []})["fits"].append(
            {"seed": int(m.group(3)), "steps": int(m.group(4)), "fit_s": float(m.group(5)), "result": m.group(6),
             "pulse_tails": int(m.group(7)), "z": z})
    for r in runs.values():
        r["summary"] = summary(r["fits"])
    return {"data": data, "simulated": True, "note": f"read from the progress log {path.name}: the run was stopped before it "
            "wrote its JSON (no estimates)", "runs": runs}


def summary(rows) -> dict:
    steps = [r["steps"] for r in rows]
    times = [r["fit_s"] for r in rows]
    zs = [r["z"] for r in rows if r["z"] is not None]
    return {"n": len(rows), "steps_mean": statistics.mean(steps), "steps_median": statistics.median(steps),
            "steps_min": min(steps), "steps_max": max(steps), "at_200_or_more": sum(s >= 200 for s in steps),
            "fit_s_median": statistics.median(times), "fit_s_mean": statistics.mean(times),
            "successful": sum(r["result"] == "successful" for r in rows),
            "chose_two": sum(r["pulse_tails"] == 2 for r in rows),
            "z_min": min(zs) if zs else None, "z_max": max(zs) if zs else None}


def agreement(runs: dict) -> dict:
    """Per data set: the largest n1 difference (in the reference's standard errors) and mu_t
    difference (relative) of each config against the others, fit by fit (same seeds only)."""
    out = {}
    for data, by in runs.items():
        names = [t for t in by if by[t]["fits"] and "n1" in by[t]["fits"][0]]
        for i, x in enumerate(names):
            for y in names[i + 1:]:
                seeds = {r["seed"] for r in by[x]["fits"]} & {r["seed"] for r in by[y]["fits"]}
                fx = [r for r in by[x]["fits"] if r["seed"] in seeds]
                fy = [r for r in by[y]["fits"] if r["seed"] in seeds]
                dn = [abs(p["n1"] - q["n1"]) / q["n1_stderr"] for p, q in zip(fx, fy)]
                dm = [abs(p["mu_t"] / q["mu_t"] - 1) for p, q in zip(fx, fy)]
                dc = [abs(p["reduced_chi2"] - q["reduced_chi2"]) for p, q in zip(fx, fy)]
                out[f"{data}: {x} vs {y}"] = {"n1_max_in_stderr": max(dn), "n1_median_in_stderr": statistics.median(dn),
                                              "mu_t_max_rel": max(dm), "reduced_chi2_max_abs_diff": max(dc)}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", choices=("tailless", "slow", "independent", "tmf8820"), default="tailless")
    p.add_argument("--tails", type=_tails, nargs="+", default=[2, "auto", 1])
    p.add_argument("--seeds", type=int, nargs="*", default=list(range(2000, 2040)))
    p.add_argument("--indep", type=int, default=3)
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--merge", nargs="+", help="part files of this script to merge into --out")
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)
    path = Path(a.out) if Path(a.out).is_absolute() else ROOT / a.out
    if a.merge:
        parts = [json.loads(Path(f).read_text()) if f.endswith(".json") else from_log(Path(f)) for f in a.merge]
        runs: dict = {}
        for q in parts:  # parts of one data set (e.g. its configs run in two processes) are joined
            runs.setdefault(q["data"], {}).update(q["runs"])
        merged = {"what": "FitConfig.pulse_tails = 'auto' against 1 and 2: warm Calibrator.fit per baseline (issue 13, straggler fits)",
                  "simulated": True, "parts": [{k: v for k, v in q.items() if k != "runs"} for q in parts],
                  "summary": {d: {t: r["summary"] for t, r in by.items()} for d, by in runs.items()},
                  "agreement": agreement(runs), "runs": runs}
        path.write_text(json.dumps(merged, indent=1) + "\n")
        return 0
    os.environ.setdefault("TOFJAX_PROGRAM_STORE", "0")
    t0 = time.perf_counter()
    if a.data == "tmf8820":
        import jax

        jax.config.update("jax_enable_x64", True)
        src = ROOT / "tests/data/tmf8820-plane-sweep/captures.json"
        out = {"data": "tmf8820", "simulated": False, "source": str(src.relative_to(ROOT)),
               "command": "python experiments/pulse_tail_choice.py --data tmf8820 --out ...", "runs": tmf8820(src)}
        path.write_text(json.dumps(out, indent=1) + "\n")
        return 0
    runs = run(a, lambda r: write(a, argv, path, t0, r))
    write(a, argv, path, t0, runs)
    return 0


def write(a, argv, path, t0, runs) -> None:
    data_note = {"tailless": "tofjax.simulate.simulate(load_scene('optoskin'), frames, seed=s): own model, no slow tail",
                 "slow": "the same with ModelOptions(pulse_tails=2), pulse_slow_weight 0.1, pulse_slow_tail_s 4x pulse_tail_s",
                 "independent": "tests/indep_sim.py (IndepRig.from_scene(scene, seed=200+i), seed 300+i): its own pulse"}[a.data]
    out = {"data": a.data, "simulated": True, "data_note": data_note, "frames": a.frames,
           "seeds": a.seeds if a.data != "independent" else [300 + i for i in range(a.indep)],
           "command": "TOFJAX_PROGRAM_STORE=0 nice -n 5 python experiments/pulse_tail_choice.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "machine": f"{platform.node()} ({os.cpu_count()} CPU cores, shared with other sessions)",
           "load_average_end": os.getloadavg(), "wall_s": time.perf_counter() - t0, "runs": runs}
    path.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    sys.exit(main())
