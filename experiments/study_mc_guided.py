"""Where the guided optics' remaining error against the Monte Carlo comes from (issue 14).

Three checks behind the figures in docs/tradeoff.md ("Guided optics"), all simulated:

1. the Monte Carlo's next-event elevation quadrature (``nee_points`` 6 against 24) on the clear
   optoskin slab (far edge only), against the guided model;
2. the guided optics' near field (``NEAR_FIELD_PER_THICKNESS``) on the optoskin baseline;
3. contacts: touch scene minus baseline per sensor (counts added and removed), Monte Carlo and
   guided model with the skin model.

    python experiments/study_mc_guided.py --photons 50000 --json docs/results/study_mc_guided.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time

import numpy as np


def run(photons: int, seed: int = 0) -> dict:
    import tofjax
    import tofjax.model.guided as guided
    from tofjax.mc import MCOptions, run_mc
    from tofjax.mc.bench import _machine, profiled_relative_l2
    from tofjax.model import ModelOptions, Params, build_model
    from tofjax.model.contact import SkinContact
    from tofjax.scene import load_scene

    tofjax.enable_x64()
    t0 = time.perf_counter()
    base = load_scene("optoskin")
    clear = base.replace(waveguide=dataclasses.replace(base.waveguide, mu_s_per_m=0.0))
    touch = load_scene("touch-three-line")
    def iso(sc):  # isotropic scattering, as the Monte Carlo with g = 0
        return sc.replace(waveguide=dataclasses.replace(sc.waveguide, volume_backscatter_fraction=0.5))

    def analytic(sc, comps, skin=None):
        m = build_model(iso(sc), ModelOptions(optics="guided", skin=skin), comps)
        return np.asarray(m(Params.from_scene(iso(sc))), np.float64)

    out = {"data": "simulated (monte carlo and analytic model)", "machine": _machine(), "photons_per_sensor": photons}
    # 1. the Monte Carlo's elevation quadrature
    g_clear = analytic(clear, ("end",))
    out["nee_points"] = {}
    for k in (6, 24):
        ref = run_mc(clear, MCOptions(photons=photons, seed=seed, nee_points=k)).counts
        out["nee_points"][str(k)] = profiled_relative_l2(ref, g_clear)[0]
    # 2. the near field, against a 24-node reference of the baseline
    comps = ("volume", "multiple_scattering", "end")
    ref_base = run_mc(base, MCOptions(photons=photons, seed=seed, nee_points=24)).counts
    keep = guided.NEAR_FIELD_PER_THICKNESS
    out["near_field_per_thickness"] = {}
    try:
        for f in (0.1, 0.2, 0.3, 0.45, 0.6):
            guided.NEAR_FIELD_PER_THICKNESS = f
            out["near_field_per_thickness"][str(f)] = profiled_relative_l2(ref_base, analytic(base, comps))[0]
    finally:
        guided.NEAR_FIELD_PER_THICKNESS = keep
    # 3. contacts: with minus without, per sensor
    skin = SkinContact()
    ref_touch = run_mc(touch, MCOptions(photons=photons, seed=seed, nee_points=24, contact=skin)).counts
    d_mc = ref_touch - ref_base
    d_an = analytic(touch, comps + ("touch", "shadowing"), skin) - analytic(base, comps)
    out["touch_relative_l2"] = profiled_relative_l2(ref_touch, analytic(touch, comps + ("touch", "shadowing"), skin))[0]
    def add(x):
        return float(np.clip(x, 0, None).sum())

    out["contacts_per_sensor"] = [{"sensor": s, "mc_added": add(d_mc[s]), "mc_removed": add(-d_mc[s]),
                                   "guided_added": add(d_an[s]), "guided_removed": add(-d_an[s])}
                                  for s in range(d_mc.shape[0])]
    out["wall_s"] = time.perf_counter() - t0
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--photons", type=int, default=50_000)
    ap.add_argument("--json", required=True)
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)
    from tofjax.outputs import atomic_write_text, check_output

    check_output(a.json, overwrite=a.overwrite, flag="--json")
    r = run(a.photons)
    atomic_write_text(a.json, json.dumps(r, indent=1), overwrite=a.overwrite)
    print(json.dumps({k: r[k] for k in ("nee_points", "near_field_per_thickness", "touch_relative_l2")}, indent=1))
    return 0


if __name__ == "__main__":
    os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=2")
    raise SystemExit(main())
