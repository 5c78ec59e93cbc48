"""One contact's signal, guided optics against the Monte Carlo, from the interior to a corner (issue 14).

On Monte Carlo data the contact fit misplaces contacts near the guide's corners towards the corner,
at the strength cap (``docs/results/eval_mc_data_fit_exposure64_12configs_mc.json``): there the
Monte Carlo's contact shows more light than the guided model expects. The guided model's contact
terms: the first order (sensor -> contact -> sensor) and, behind ``guided.SECOND_ORDER`` (off by
default), light a diffuse wall sends across the contact (sensor -> wall -> contact -> sensor);
``guided.SECOND_ORDER_RECIPROCAL`` adds each such path's reverse (sensor -> contact -> wall ->
sensor: by reciprocity the same amplitude and delay, detected in the wall point's zone);
``guided.EDGE_SECOND_SHADOW`` (off by default: no better detection, 1.55x its cost) lets contacts frustrate the far edge's second bounce on its
wall-to-wall legs (a contact in a corner sits on the legs across it), and the second bounce's
receiving rays now carry their return leg's frustration only (before, also their outbound leg's,
which that path does not travel: ``docs/results/mc_contact_walls_before_leg_shadow.json`` is the
run before both changes).

For each contact position (one contact, radius 6 mm, strength 1, the skin contact model) this
compares the **touch signal** (touch minus baseline; Monte Carlo: the mean over ``--seeds`` seeds of
touch minus baseline with the same seed, common random numbers) of the Monte Carlo with the guided
model's variants: first order only (the default), the same with the second bounce's legs frustrated
(``EDGE_SECOND_SHADOW``), plus the forward second order, plus both orders. The
figure is the relative L2 of the signal with the contact's strength profiled (one scale per
variant: ``||d - s g|| / ||d||`` at the best ``s``), with ``s`` itself and the Monte Carlo's own
noise (the seeds' spread: the L2 a perfect model would show). All data **simulated**; Monte Carlo
runs cached as ``experiments/eval_mc_data.py`` caches them.

    python experiments/mc_contact_walls.py --out docs/results/mc_contact_walls.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
#: (SECOND_ORDER, SECOND_ORDER_RECIPROCAL, EDGE_SECOND_SHADOW, REVERB_LEGS) of tofjax.model.guided
VARIANTS = {"first_order": (False, False, False, False), "first_order_legs_shadowed": (False, False, True, False),
            "field_legs_shadowed": (False, False, False, True),
            "second_order_forward": (True, False, False, False), "second_order_both": (True, True, False, False)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="JSON file to write")
    ap.add_argument("--photons", type=int, default=25_000, help="Monte Carlo packets per sensor and seed")
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--positions", default="", help="comma-separated position names (default: all)")
    ap.add_argument("--variants", default="", help=f"comma-separated model variants (default: all; {', '.join(VARIANTS)})")
    ap.add_argument("--cache", default=None, help="folder caching the Monte Carlo runs (default: eval_mc_data.py's)")
    ap.add_argument("--end-reflectance", type=float, default=None,
                    help="the edges' reflectance in both (default: the scene's); 0: absorbing edges")
    a = ap.parse_args(argv)
    if a.seeds < 2 or a.photons < 1:
        ap.error("--seeds must be >= 2 and --photons >= 1")
    a.variants = [v.strip() for v in a.variants.split(",") if v.strip()] or list(VARIANTS)
    unknown = [v for v in a.variants if v not in VARIANTS]
    if unknown:
        ap.error(f"--variants: unknown {', '.join(unknown)} (known: {', '.join(VARIANTS)})")
    sys.path.insert(0, str(ROOT))
    sys.path.insert(0, str(ROOT / "experiments"))
    from tofjax.compile_cache import use_fast_cpu_compiler

    use_fast_cpu_compiler()
    from tofjax import enable_x64

    enable_x64()
    import eval_mc_data as E

    cache = E.CACHE
    if a.cache:
        E.CACHE = Path(a.cache)
    try:
        return _run(a, ap, E)
    finally:
        E.CACHE = cache


def _run(a, ap, E) -> int:
    import tofjax.model.guided as guided
    from tofjax.mc.bench import NOT_TRANSPORTED
    from tofjax.mc.capture import ANALYTIC_EXTRAS
    from tofjax.model import ModelOptions, Params, build_model
    from tofjax.model.contact import SkinContact
    from tofjax.outputs import atomic_write_text

    scene = E.guided_scene()
    if a.end_reflectance is not None:
        import dataclasses

        scene = scene.replace(waveguide=dataclasses.replace(scene.waveguide, end_reflectance=a.end_reflectance))
    W, H = scene.waveguide.size_m
    positions = {  # (x, y) in metres: the interior, then nearer a wall, then nearer a corner
        "centre": (W / 2, H / 2),
        "wall_5cm": (W / 2, H - 0.05),
        "wall_2cm": (W / 2, H - 0.02),
        "corner_5cm": (0.05, H - 0.05),
        "corner_3cm": (0.03, H - 0.03),
        "corner_2cm": (0.02, H - 0.02),
        # where the 64x six-contact run missed contacts (docs/results/eval_mc_data_fit_exposure64_12configs_mc_nolegs.json)
        "missed_a": (0.044, 0.249),
        "missed_b": (0.057, 0.273),
        "missed_c": (0.085, 0.263),
    }

    if a.positions:
        names = [n.strip() for n in a.positions.split(",") if n.strip()]
        unknown = [n for n in names if n not in positions]
        if unknown:
            ap.error(f"--positions: unknown {', '.join(unknown)} (known: {', '.join(positions)})")
        positions = {n: positions[n] for n in names}

    def extras(s):
        o = ModelOptions(quadrature=4, dtype="float32")
        return np.asarray(build_model(s, o, ANALYTIC_EXTRAS)(Params.from_scene(s, o.jnp_dtype)), np.float64)

    def guided_counts(s):
        o = ModelOptions(optics="guided", skin=SkinContact() if s.touches else None)
        comps = tuple(c for c in s.components() if c not in NOT_TRANSPORTED)
        return np.asarray(build_model(s, o, comps)(Params.from_scene(s, o.jnp_dtype)), np.float64)

    t0 = time.perf_counter()
    base = [E.mc_expected(scene, a.photons, k)[0] - extras(scene) for k in range(a.seeds)]
    rows = {}
    for name, (x, y) in positions.items():
        ts = E.touch_scene(scene, np.asarray([[x, y, 1.0]]))
        xt = extras(ts)
        d = [E.mc_expected(ts, a.photons, k)[0] - xt - base[k] for k in range(a.seeds)]
        dm = np.mean(d, 0)
        noise = float(np.sqrt(np.var(d, 0, ddof=1).sum() / a.seeds) / np.linalg.norm(dm))
        row = {"xy_m": [x, y], "mc_signal_added": float(dm.clip(0).sum()), "mc_signal_removed": float(dm.clip(None, 0).sum()),
               "mc_noise_relative": noise, "variants": {}}
        for v, (second, recip, legs, field_legs) in VARIANTS.items():
            if v not in a.variants:
                continue
            saved = guided.SECOND_ORDER, guided.SECOND_ORDER_RECIPROCAL, guided.EDGE_SECOND_SHADOW, guided.REVERB_LEGS
            (guided.SECOND_ORDER, guided.SECOND_ORDER_RECIPROCAL, guided.EDGE_SECOND_SHADOW,
             guided.REVERB_LEGS) = second, recip, legs, field_legs
            try:
                g = guided_counts(ts) - guided_counts(scene)
            finally:
                (guided.SECOND_ORDER, guided.SECOND_ORDER_RECIPROCAL, guided.EDGE_SECOND_SHADOW,
                 guided.REVERB_LEGS) = saved
            s = float(np.vdot(dm, g) / np.vdot(g, g))
            res = dm - s * g
            row["variants"][v] = {"relative_l2_strength_profiled": float(np.linalg.norm(res) / np.linalg.norm(dm)),
                                  "residual_share_by_sensor": np.round((res**2).sum((1, 2)) / (res**2).sum(), 3).tolist(),
                                  "signal_share_by_sensor_mc": np.round((dm**2).sum((1, 2)) / (dm**2).sum(), 3).tolist(),
                                  "signal_share_by_sensor_model": np.round((g**2).sum((1, 2)) / (g**2).sum(), 3).tolist(),
                                  "relative_l2_unscaled": float(np.linalg.norm(dm - g) / np.linalg.norm(dm)),
                                  "best_scale": s, "model_signal_added": float(g.clip(0).sum()),
                                  "model_signal_removed": float(g.clip(None, 0).sum())}
        rows[name] = row
        print(name, f"noise {noise:.3f}", {v: (round(r["relative_l2_strength_profiled"], 3), round(r["best_scale"], 2))
                                          for v, r in row["variants"].items()}, flush=True)
    import jax

    out = {"what": "one contact's touch signal (touch - baseline), guided optics variants against the Monte Carlo; "
                   "relative L2 with the strength profiled (best scale), the scale, and the Monte Carlo's noise",
           "simulated": True, "scene": "optoskin (guided optics, isotropic volume backscatter)", "photons_per_sensor_per_seed": a.photons,
           "seeds": a.seeds, "end_reflectance": scene.waveguide.end_reflectance, "mc_options": repr(E.mc_options(a.photons, 0)), "positions": rows,
           "machine": f"{platform.node()} {platform.machine()}, {os.cpu_count()} cores; jax {jax.__version__}",
           "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()), "seconds": time.perf_counter() - t0}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(Path(a.out), json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
