"""Where the guided optics' remaining error against the Monte Carlo comes from (issue 14).

Three checks behind the figures in docs/tradeoff.md ("Guided optics"), all simulated:

1. the Monte Carlo's next-event elevation quadrature (``nee_points`` 6 against 24) on the clear
   optoskin slab (far edge only), against the guided model;
2. the guided optics' near field on the optoskin baseline: the thickness-based one at several
   ``NEAR_FIELD_PER_THICKNESS`` (``NEAR_FIELD_APERTURE`` off) and the aperture's (on, the default);
3. contacts: touch scene minus baseline per sensor (counts added and removed), Monte Carlo and
   guided model with the skin model.

    python experiments/study_mc_guided.py --photons 50000 --json docs/results/study_mc_guided.json

Two more modes (issue 14, touch scenes):

* ``--contacts``: one skin contact on sensor S0's axis (S0 alone), at several distances, diffuse and
  absorbing edges: the counts the contact adds and removes (touch minus bare slab, same seeds), from
  the analog Monte Carlo (``nee=False``: no next-event estimation, unbiased, noisy), the Monte Carlo
  with next-event estimation as it is and with the contact flag fixed (below), and the guided optics;
* ``--bench``: ``tofjax bench tradeoff`` (:func:`tofjax.mc.bench.run_bench_tradeoff`) with the Monte
  Carlo as it is (``--transport as-is``) or with the contact flag fixed (``--transport fixed``).

**The contact flag.** After a diffuse event the Monte Carlo scores the direct flight to the sensor by
next-event estimation, contact frustration on the way included (``_nee_scores``: each top-face hit
under a contact reflects ``fc Rs + (1 - fc) R_air``), and marks the packet so that its later direct
detection is not scored twice. A contact *mirror* (the packet reflected under a contact) clears that
mark (``diffuse = jnp.where(cn, into, diffuse)`` in ``tofjax/mc/transport.py``), so a packet that
scattered (or left a diffuse edge), then mirrored under a contact and reached the aperture is scored
twice: once by next-event estimation, once directly. The fix keeps the mark on a mirror
(``jnp.where(cn & into, True, diffuse)``), now in transport.py itself (regression test
``tests/test_mc.py::test_mirror_under_a_contact_is_not_scored_twice``); :func:`fixed_transport` returns
the module, and ``--transport as-is`` rebuilds the old line in a copy of it to reproduce the figures made
before the fix.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time

import numpy as np


FLAG_OLD = "diffuse = jnp.where(cn, into, diffuse)"
FLAG_NEW = "diffuse = jnp.where(cn & into, True, diffuse)"


def fixed_transport():
    """:mod:`tofjax.mc.transport`, which has the contact flag fixed (see the module docstring)."""
    import tofjax.mc.transport as T

    if FLAG_NEW not in open(T.__file__).read():
        raise RuntimeError("tofjax/mc/transport.py changed: the contact flag line was not found")
    return T


def transport_before_fix():
    """A copy of :mod:`tofjax.mc.transport` with the contact flag as it was before the fix (a mirror
    under a contact cleared the next-event mark): reproduces the figures made before it."""
    import sys
    import types

    T = fixed_transport()
    name = "tofjax.mc._transport_before_contact_flag_fix"
    if name in sys.modules:
        return sys.modules[name]
    src = open(T.__file__).read()
    m = types.ModuleType(name)
    m.__package__, m.__file__ = "tofjax.mc", T.__file__
    sys.modules[name] = m
    exec(compile(src.replace(FLAG_NEW, FLAG_OLD), T.__file__, "exec"), m.__dict__)
    return m


class CachedTransport:
    """``MCOptions`` and ``run_mc`` of a transport module, the counts cached on disk by scene, options and
    module (re-evaluating the analytic model against the same references costs no Monte Carlo)."""

    def __init__(self, module, cache_dir):
        self.module, self.cache = module, cache_dir
        self.__name__ = module.__name__
        self.MCOptions = module.MCOptions

    def run_mc(self, scene, options, progress=False):
        import hashlib
        import types

        key = hashlib.sha256((self.__name__ + scene.to_toml() + repr(options)).encode()).hexdigest()[:20]
        path = os.path.join(self.cache, key + ".npz")
        if os.path.exists(path):
            z = np.load(path)
            return types.SimpleNamespace(counts=z["counts"], seconds=float(z["seconds"]))
        r = self.module.run_mc(scene, options, progress=progress)
        os.makedirs(self.cache, exist_ok=True)
        np.savez(path + ".tmp.npz", counts=np.asarray(r.counts), seconds=r.seconds)
        os.replace(path + ".tmp.npz", path)
        return r


def contacts(photons: int, analog_photons: int, seeds: int, distances=(0.05, 0.15), edges=("diffuse", "absorb"),
             cache: str | None = None) -> dict:
    """One skin contact on S0's axis (S0 alone): counts added / removed / net, analog Monte Carlo,
    next-event Monte Carlo as is and fixed, guided optics (mean and standard error over seeds)."""
    import tofjax
    import tofjax.mc.transport as T
    from tofjax.mc.bench import _machine
    from tofjax.model import ModelOptions, Params, build_model
    from tofjax.model.contact import SkinContact
    from tofjax.scene import Touch, load_scene

    tofjax.enable_x64()
    t0 = time.perf_counter()
    F = fixed_transport()
    if cache:
        T, F = CachedTransport(T, cache), CachedTransport(F, cache)
    full = load_scene("optoskin").without_touches()
    s0 = full.sensors[0]
    ang = np.radians(s0.direction_deg)
    skin = SkinContact()
    comps = ("volume", "multiple_scattering", "end")
    out = {"what": "one skin contact (radius 6 mm, strength 1) on sensor S0's axis, S0 alone, optoskin slab: "
                   "touch minus bare slab (same seeds), transported light, counts of S0",
           "data": "simulated", "machine": _machine(), "photons_nee": photons, "photons_analog": analog_photons,
           "seeds": seeds, "contact_model": dataclasses.asdict(skin), "rows": []}

    def sig(d):
        return {"added": float(np.clip(d, 0, None).sum()), "removed": float(np.clip(d, None, 0).sum()), "net": float(d.sum())}

    for edge in edges:
        wg = dataclasses.replace(full.waveguide, volume_backscatter_fraction=0.5,
                                 end_reflectance=full.waveguide.end_reflectance if edge == "diffuse" else 0.0)
        sc = full.replace(sensors=(s0,), waveguide=wg)
        gb = np.asarray(build_model(sc, ModelOptions(optics="guided"), comps)(Params.from_scene(sc)), np.float64)
        for D in distances:
            t = sc.replace(touches=(Touch((s0.position_m[0] + D * np.cos(ang), s0.position_m[1] + D * np.sin(ang)), 0.006, 1.0),))
            row = {"edges": edge, "distance_m": D}
            g = np.asarray(build_model(t, ModelOptions(optics="guided", skin=skin), comps + ("touch", "shadowing"))(
                Params.from_scene(t)), np.float64)
            row["guided"] = sig((g - gb)[0])
            for name, mod, nee, n in (("analog", T, False, analog_photons), ("nee_as_is", T, True, photons),
                                      ("nee_fixed", F, True, photons)):
                ds = []
                for k in range(seeds):
                    kw = dict(photons=n, seed=k, nee=nee, edges=edge)
                    if nee:
                        kw.update(nee_points=24, nee_aperture=4)
                    b = mod.run_mc(sc, mod.MCOptions(**kw)).counts
                    c = mod.run_mc(t, mod.MCOptions(contact=skin, **kw)).counts
                    ds.append((c - b)[0])
                sigs = [sig(d) for d in ds]
                row[name] = {k: float(np.mean([x[k] for x in sigs])) for k in ("added", "removed", "net")}
                row[name]["net_se"] = float(np.std([x["net"] for x in sigs], ddof=1) / np.sqrt(seeds))
                row[name]["mean_signal"] = sig(np.mean(ds, 0))
            out["rows"].append(row)
            print(json.dumps(row), flush=True)
    out["wall_s"] = time.perf_counter() - t0
    return out


def contacts_guided(distances=(0.05, 0.15), edges=("diffuse", "absorb")) -> dict:
    """The guided column of :func:`contacts` alone (no Monte Carlo), with the model's switches
    (``EDGE_SECOND``, ``DISCRETE_HITS``) as they are and each one flipped."""
    import tofjax
    import tofjax.model.guided as guided
    from tofjax.mc.bench import _machine
    from tofjax.model import ModelOptions, Params, build_model
    from tofjax.model.contact import SkinContact
    from tofjax.scene import Touch, load_scene

    tofjax.enable_x64()
    full = load_scene("optoskin").without_touches()
    s0 = full.sensors[0]
    ang = np.radians(s0.direction_deg)
    comps = ("volume", "multiple_scattering", "end")
    keep = (guided.EDGE_SECOND, guided.DISCRETE_HITS)
    variants = {"first_bounce_edge": (False, False), "second_bounce_edge": (True, False),
                "second_bounce_edge_discrete_hits": (True, True)}
    out = {"what": "guided optics, the scene of --contacts: net counts of one skin contact (touch minus bare slab)",
           "data": "simulated", "machine": _machine(), "default_switches": {"EDGE_SECOND": keep[0], "DISCRETE_HITS": keep[1]},
           "rows": []}
    try:
        for edge in edges:
            wg = dataclasses.replace(full.waveguide, volume_backscatter_fraction=0.5,
                                     end_reflectance=full.waveguide.end_reflectance if edge == "diffuse" else 0.0)
            sc = full.replace(sensors=(s0,), waveguide=wg)
            for D in distances:
                t = sc.replace(touches=(Touch((s0.position_m[0] + D * np.cos(ang), s0.position_m[1] + D * np.sin(ang)), 0.006, 1.0),))
                row = {"edges": edge, "distance_m": D}
                for name, (es, dh) in variants.items():
                    guided.EDGE_SECOND, guided.DISCRETE_HITS = es, dh
                    gb = np.asarray(build_model(sc, ModelOptions(optics="guided"), comps)(Params.from_scene(sc)), np.float64)
                    g = np.asarray(build_model(t, ModelOptions(optics="guided", skin=SkinContact()), comps + ("touch", "shadowing"))(
                        Params.from_scene(t)), np.float64)
                    row[name] = float((g - gb).sum())
                out["rows"].append(row)
    finally:
        guided.EDGE_SECOND, guided.DISCRETE_HITS = keep
    return out


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
    keep = guided.NEAR_FIELD_PER_THICKNESS, guided.NEAR_FIELD_APERTURE
    out["near_field_per_thickness"] = {}
    try:
        # the thickness-based near field (the aperture's off: with it on, r0 only shapes the ended rays' far field)
        guided.NEAR_FIELD_APERTURE = False
        for f in (0.1, 0.2, 0.3, 0.45, 0.6):
            guided.NEAR_FIELD_PER_THICKNESS = f
            out["near_field_per_thickness"][str(f)] = profiled_relative_l2(ref_base, analytic(base, comps))[0]
        guided.NEAR_FIELD_APERTURE = True
        out["near_field_aperture"] = profiled_relative_l2(ref_base, analytic(base, comps))[0]
    finally:
        guided.NEAR_FIELD_PER_THICKNESS, guided.NEAR_FIELD_APERTURE = keep
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
    ap.add_argument("--contacts", action="store_true", help="the one-contact checks (see the module docstring)")
    ap.add_argument("--contacts-guided", action="store_true", help="the guided column of --contacts alone, each switch")
    ap.add_argument("--analog-photons", type=int, default=2_000_000)
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--bench", action="store_true", help="tofjax bench tradeoff with --transport")
    ap.add_argument("--transport", choices=("as-is", "fixed"), default="fixed")
    ap.add_argument("--repeats", type=int, default=31, help="--bench: timed pairs of forward evaluations")
    ap.add_argument("--touch-scene", default="touch-three-line", help="--bench: the scene with contacts")
    ap.add_argument("--cache", help="folder caching the Monte Carlo runs (e.g. out/mc_cache)")
    a = ap.parse_args(argv)
    from tofjax.outputs import atomic_write_text, check_output

    check_output(a.json, overwrite=a.overwrite, flag="--json")
    if a.contacts_guided:
        r = contacts_guided()
        atomic_write_text(a.json, json.dumps(r, indent=1), overwrite=a.overwrite)
        print(json.dumps(r["rows"], indent=1))
        return 0
    if a.contacts:
        r = contacts(a.photons, a.analog_photons, a.seeds, cache=a.cache)
        atomic_write_text(a.json, json.dumps(r, indent=1), overwrite=a.overwrite)
        return 0
    if a.bench:
        import tofjax
        from tofjax.mc.bench import BenchOptions, run_bench_tradeoff, summary

        tofjax.enable_x64()
        mod = fixed_transport() if a.transport == "fixed" else transport_before_fix()
        if a.cache:
            mod = CachedTransport(mod, a.cache)
        r = run_bench_tradeoff(BenchOptions(photons=a.photons, seeds=a.seeds, repeats=a.repeats, touch_scene=a.touch_scene), transport=mod)
        r["monte_carlo_note"] = ("tofjax.mc.transport as it was before the contact flag fix" if a.transport == "as-is" else
                                 "tofjax.mc.transport (contact flag fixed)")
        atomic_write_text(a.json, json.dumps(r, indent=1), overwrite=a.overwrite)
        print(summary(r))
        return 0
    r = run(a.photons)
    atomic_write_text(a.json, json.dumps(r, indent=1), overwrite=a.overwrite)
    print(json.dumps({k: r[k] for k in ("nee_points", "near_field_per_thickness", "touch_relative_l2")}, indent=1))
    return 0


if __name__ == "__main__":
    os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=2")
    raise SystemExit(main())
