"""The near field's shape: noise-free calibrations with ``Params.near_field_shape`` fixed at the
scene's 2 ("before": seed 000's ``1/(r^2 + d^2)``, ``d`` fitted) and free ("after":
``G = (r^p + d^p)^(-2/p)``, ``p`` and ``d`` fitted), at mu_s + mu_a = 0.05 /m (``--mu-t``),
n1 1.3 / 1.45 / 1.6, on

* ``own``: tofjax's own simulator (expected counts at quadrature 8, its time discretisation
  converged; the truth's law is ``p = 2``): the shape must cost no bias here;
* ``independent max``: ``tests/indep_sim.py`` at ``indep_sim.CONVERGED``, its default near field
  ``1/max(r, 0.6 h)^2`` (the calibration study's rig per n1, seed 200 + grid index);
* ``independent gaussian`` / ``independent exponential``: the same rigs with a near-field law that
  neither tofjax's family nor the rig's default is (``IndepOptions.near_field_law``):
  ``(1 - exp(-r^2/r0^2)) / r^2`` and ``(1 - exp(-r/r0))^2 / r^2``, ``r0 = 0.6 h``.

Noise-free: the expected counts as ``frames`` identical frames (the estimator's limit, the bias
no frame count removes; ``mu_t_stderr_rel`` is the Laplace standard error at that many frames,
i.e. what the extra freedom costs in precision).

    PYTHONPATH=$PWD python experiments/near_field_shape.py --out out/nf/near_field_shape.json \\
        [--n1 1.3 1.45 1.6] [--data own max gaussian exponential] [--variants before after]
    python experiments/near_field_shape.py --merge out/nf/a.json out/nf/b.json --out docs/results/near_field_shape.json

**Simulated** data.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

import tofjax
from tofjax.fit import Calibrator, FitConfig
from tofjax.outputs import atomic_write_text, check_output

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from indep_sim import CONVERGED, IndepRig  # noqa: E402
from study_calib_independent import ALBEDO  # noqa: E402
from study_mu_low import MU_T, _fit_row, _full_scene, _noise_free, _truth  # noqa: E402

DATA = ("own", "max", "gaussian", "exponential")
LAWS = {"own": "tofjax (p = 2, d = h)", "max": "1 / max(r, 0.6 h)^2 (indep_sim default)",
        "gaussian": "(1 - exp(-r^2 / r0^2)) / r^2, r0 = 0.6 h", "exponential": "(1 - exp(-r / r0))^2 / r^2, r0 = 0.6 h"}


def configs() -> dict[str, FitConfig]:
    base = tuple(k for k in FitConfig().free if k != "near_field_shape")
    return {"before": FitConfig(free=base), "after": FitConfig(free=base + ("near_field_shape",))}


def expected(data: str, truth, k: int) -> np.ndarray:
    if data == "own":
        from tofjax.model import ModelOptions
        from tofjax.simulate import expected_counts

        return np.asarray(expected_counts(truth, ModelOptions(quadrature=8)))
    rig = IndepRig.from_scene(truth, seed=200 + k, options=dataclasses.replace(CONVERGED, near_field_law=data))
    return rig.expected(np.zeros((0, 3)))


def run(out: Path, n1s, data, variants, frames: int, mu_t: float, overwrite: bool) -> dict:
    path = check_output(out, overwrite=overwrite)
    t0 = time.perf_counter()
    nominal = _full_scene()
    cfgs = configs()
    cals = {v: Calibrator(nominal, cfgs[v]) for v in variants}
    rows: dict = {}
    for n1 in n1s:
        truth, k = _truth(nominal, n1, mu_t)
        for dname in data:
            t = time.perf_counter()
            lam = expected(dname, truth, k)
            sim_s = time.perf_counter() - t
            cap = _noise_free(lam, truth, frames, f"simulated ({dname}), noise-free")
            for v in variants:
                r = _fit_row(cals[v], cap, n1, mu_t)
                rows.setdefault(str(n1), {}).setdefault(dname, {})[v] = r | {"simulate_seconds": sim_s}
                print(f"n1 {n1:.2f} {dname:12s} {v:6s}: mu_t {100 * r['mu_t_rel_error']:+7.2f}% "
                      f"(stderr {100 * (r['mu_t_stderr_rel'] or np.nan):5.1f}%) n1 {100 * r['n1_rel_error']:+.3f}% "
                      f"chi2 {r['reduced_chi2']:.4f} p {r.get('near_field_shape', np.nan):.2f} d {1e3 * r.get('near_field_m', np.nan):.2f} mm "
                      f"{r['seconds']:.1f}s", flush=True)
            result = _result(rows, n1s, data, variants, frames, mu_t, cfgs, t0)
            atomic_write_text(path, json.dumps(result, indent=2))
    return result


def _result(rows, n1s, data, variants, frames, mu_t, cfgs, t0) -> dict:
    return {
        "study": "the near field's shape: noise-free calibrations with near_field_shape fixed at 2 (before) and free (after)",
        "data": "simulated (own: tofjax expected counts at quadrature 8; independent: tests/indep_sim.py at CONVERGED "
                "with near_field_law max / gaussian / exponential); noise-free, weighted as frames_weighting frames",
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs ({platform.platform()}), CPU only, shared with other agents (loaded)",
        "load_average": list(os.getloadavg()),
        "truth": {"mu_t_per_m": mu_t, "albedo": ALBEDO, "frames_weighting": frames, "n1": list(n1s)},
        "near_field_laws": {d: LAWS[d] for d in data},
        "variants": {v: {"free": list(cfgs[v].free)} for v in variants},
        "tofjax_law": "G = (r^p + d^p)^(-2/p), d = near_field_m, p = near_field_shape (before: p = 2 fixed)",
        "note": "mu_t_stderr_rel: the Laplace standard error at frames_weighting frames; reduced_chi2 of a noise-free fit is the misfit alone",
        "by_n1": rows,
        "summary": _summary(rows, variants),
        "seconds": time.perf_counter() - t0,
    }


def _summary(rows, variants) -> dict:
    out = {}
    for v in variants:
        for n1, per in rows.items():
            for dname, r in per.items():
                if v in r:
                    out.setdefault(v, {}).setdefault(dname, {})[n1] = round(100 * r[v]["mu_t_rel_error"], 2)
    return {"mu_t_error_percent": out}


def merge(parts, out: Path, overwrite: bool) -> dict:
    path = check_output(out, overwrite=overwrite)
    docs = [json.loads(Path(p).read_text()) for p in parts]
    rows: dict = {}
    for d in docs:
        for n1, per in d["by_n1"].items():
            for dname, r in per.items():
                rows.setdefault(n1, {}).setdefault(dname, {}).update(r)
    res = dict(docs[0])
    res["by_n1"] = rows
    res["summary"] = _summary(rows, sorted({v for d in docs for v in d["variants"]}))
    res["variants"] = {k: v for d in docs for k, v in d["variants"].items()}
    res["near_field_laws"] = {k: v for d in docs for k, v in d["near_field_laws"].items()}
    res["load_average"] = [d["load_average"] for d in docs]
    res["seconds"] = [d["seconds"] for d in docs]
    res["parts"] = [str(p) for p in parts]
    atomic_write_text(path, json.dumps(res, indent=2))
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/near_field_shape.json")
    ap.add_argument("--n1", type=float, nargs="+", default=[1.3, 1.45, 1.6])
    ap.add_argument("--data", nargs="+", default=list(DATA), choices=DATA)
    ap.add_argument("--variants", nargs="+", default=["before", "after"], choices=["before", "after"])
    ap.add_argument("--frames", type=int, default=960)
    ap.add_argument("--mu-t", type=float, default=MU_T)
    ap.add_argument("--merge", nargs="+", type=Path)
    ap.add_argument("--overwrite", action="store_true")
    args = ap.parse_args(argv)
    if args.merge:
        merge(args.merge, Path(args.out), args.overwrite)
        return
    tofjax.enable_x64()
    run(Path(args.out), args.n1, args.data, args.variants, args.frames, args.mu_t, args.overwrite)


if __name__ == "__main__":
    main()
