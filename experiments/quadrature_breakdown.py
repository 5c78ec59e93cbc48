"""Where tofjax's default quadrature (2 time nodes per bin) differs from 16, component by
component (``ForwardModel.breakdown``), on the low-attenuation study's scene (optoskin,
``study_calib_independent.FULL``) at mu_s + mu_a = 0.05 /m, n1 1.45: the zone-mean relative
error per bin of each component and of the total (simulated, noise-free, tofjax's own model).

    PYTHONPATH=$PWD python experiments/quadrature_breakdown.py --out docs/results/quadrature_breakdown.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
from pathlib import Path

import jax
import numpy as np

import tofjax
from tofjax.model import ModelOptions, Params, build_model, speed_in_guide
from tofjax.outputs import atomic_write_text, check_output
from tofjax.scene import load_scene

sys.path.insert(0, str(Path(__file__).resolve().parent))
from study_calib_independent import ALBEDO, FULL, _scene  # noqa: E402


def breakdown(scene, q: int) -> dict[str, np.ndarray]:
    model = build_model(scene, ModelOptions(quadrature=q))
    p = Params.from_scene(scene)
    parts = jax.jit(lambda p: model.breakdown(p))(p)
    out = {k: np.asarray(v) for k, v in parts.items()}
    out["total"] = np.asarray(jax.jit(lambda p: model(p))(p))
    return out


def profile(scene, q: int = 2, ref_q: int = 16) -> dict:
    lo, hi = breakdown(scene, q), breakdown(scene, ref_q)
    total = hi["total"]
    rows = {}
    for k in hi:
        if k == "ambient":
            continue
        # error of each component relative to the total counts (what a fit sees), and to itself
        d = lo[k] - hi[k]
        rows[k] = {
            "rel_to_total_by_bin": (d / np.maximum(total, 1.0)).mean((0, 1)).round(6).tolist(),
            "rel_to_itself_by_bin": (d / np.maximum(np.abs(hi[k]), 1e-3 * np.abs(hi[k]).max())).mean((0, 1)).round(6).tolist(),
        }
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="out/quadrature_breakdown.json")
    ap.add_argument("--mu-t", type=float, default=0.05)
    ap.add_argument("--n1", type=float, default=1.45)
    ap.add_argument("--q", type=int, default=2)
    ap.add_argument("--overwrite", action="store_true")
    ap.add_argument("--label", default="", help="what model version this is (e.g. before/after a fix)")
    args = ap.parse_args(argv)
    tofjax.enable_x64()
    path = check_output(Path(args.out), overwrite=args.overwrite)
    nominal = _scene(load_scene("optoskin"), FULL["sensors"], FULL["zones"], FULL["bins"])
    wg = dataclasses.replace(nominal.waveguide, n1=args.n1, mu_s_per_m=ALBEDO * args.mu_t, mu_a_per_m=(1 - ALBEDO) * args.mu_t)
    scene = nominal.replace(waveguide=wg)
    rows = profile(scene, args.q)
    c1 = speed_in_guide(args.n1)
    rpb = c1 * scene.sensor.bin_width_s / 2
    res = {
        "study": f"tofjax quadrature {args.q} against 16, per component (ForwardModel.breakdown), zone-mean relative error per bin",
        "label": args.label,
        "data": "simulated (tofjax expected counts, noise-free)",
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs ({platform.platform()}), CPU only, shared with other agents (loaded)",
        "load_average": list(os.getloadavg()),
        "truth": {"n1": args.n1, "mu_t_per_m": args.mu_t, "albedo": ALBEDO},
        "range_per_bin_m": rpb,
        "bin_range_m": [round((b + 0.5) * rpb, 4) for b in range(scene.sensor.n_bins)],
        "by_component": rows,
    }
    atomic_write_text(path, json.dumps(res, indent=1))
    for k, r in rows.items():
        print(k, "rel_to_total bins 10-30 (%):", np.round(100 * np.asarray(r["rel_to_total_by_bin"][10:30]), 3).tolist())


if __name__ == "__main__":
    main()
