"""``tofjax mc`` (scenes and ``mc slab``), ``tofjax prune`` and ``tofjax bench tradeoff``: thin wrappers of the library.

The full trade-off study (ladders, fits, contacts) is ``experiments/study_tradeoff.py``;
``tofjax bench tradeoff`` (:mod:`tofjax.mc.bench`) is its small fixed benchmark: analytic
against Monte Carlo for the default and guided optics, and the forward cost."""

from __future__ import annotations

import json

from ..config import ConfigError


def _cmd_mc(a) -> int:
    from ..capture import write_capture
    from ..scene import load_scene
    from .capture import mc_capture
    from .transport import MCOptions

    if a.scene == "slab":
        return _cmd_mc_slab(a)
    if a.out is None:
        raise ConfigError("--out: required (the output capture), except for 'tofjax mc slab'")
    slab_only = [f"--{k.replace('_', '-')}" for k in _SLAB_ONLY if getattr(a, k) is not None]
    if slab_only:
        raise ConfigError(f"{', '.join(slab_only)}: only for 'tofjax mc slab'")
    scene = load_scene(a.scene).require_waveguide("tofjax mc", a.scene)
    if a.frames < 1:
        raise ConfigError(f"--frames: must be >= 1, got {a.frames}")
    from ..cli import _check_size, _check_some_light

    _check_size(scene, a.frames)
    from ..capture import check_capture_target

    check_capture_target(a.out, a.overwrite)
    opts = MCOptions(photons=a.photons, seed=a.seed, g=a.g, edges=a.edges, dtype=a.dtype, batch=a.batch)
    cap = mc_capture(scene, a.frames, a.seed, opts, progress=True)
    _check_some_light(cap, a.scene)
    write_capture(a.out, cap, overwrite=a.overwrite)
    t = cap.truth
    print(
        f"wrote {a.out}: {cap.n_frames} frames of {scene.shape} (sensors, zones, bins), scene '{scene.name}', "
        f"{a.photons} photons per sensor, {t['mc_events']} events in {t['mc_seconds']:.1f} s "
        f"({t['mc_events'] / max(t['mc_seconds'], 1e-9):.3g} events/s)"
    )
    print("where the light went: " + ", ".join(f"{k} {v:.3g}" for k, v in t["mc_ledger"].items()))
    return 0


_SLAB_ONLY = ("n", "thickness_m", "mu_s_per_m", "mu_a_per_m", "json")


def _cmd_mc_slab(a) -> int:
    from .slab import SlabOptions, run_slab

    if a.out is not None or a.frames != 1 or a.edges != "diffuse":
        raise ConfigError("--out, --frames, --edges: not for 'tofjax mc slab' (it writes --json)")
    if a.json is None:
        raise ConfigError("--json: required for 'tofjax mc slab' (the output file)")
    given = {k: getattr(a, k) for k in ("n", "thickness_m", "mu_s_per_m", "mu_a_per_m") if getattr(a, k) is not None}
    opts = SlabOptions(**given, g=a.g, photons=a.photons, seed=a.seed, dtype=a.dtype, batch=a.batch)
    res = run_slab(opts, progress=True)
    res.write_json(a.json)
    for k in ("diffuse_reflectance", "total_transmittance", "absorbed"):
        print(f"{k:20s} {getattr(res, k):.5f} +- {getattr(res, k + '_se'):.5f}")
    print(f"(specular {res.specular_reflectance:.5f} not included; {res.events} events in {res.seconds:.1f} s, "
          f"{res.events_per_second:.3g} events/s); wrote {a.json}")
    return 0


def _cmd_prune(a) -> int:
    from ..model import ModelOptions
    from ..scene import load_scene
    from .prune import PruneOptions, prune_model

    scene = load_scene(a.scene).require_waveguide("tofjax prune", a.scene)
    report = prune_model(
        scene,
        PruneOptions(noise_floor=a.noise_floor, frames=a.frames, model=ModelOptions(quadrature=a.quadrature), timing=a.timing),
    )
    print(report.table())
    if a.out:
        from ..outputs import atomic_write_text

        atomic_write_text(a.out, json.dumps(report.to_json(), indent=1))
        print(f"wrote {a.out}")
    return 0


def _frontier(text):
    from .bench import DEFAULT_FRONTIER

    if text is None:
        return DEFAULT_FRONTIER
    return () if text.strip().lower() == "none" else tuple(f for f in text.split(",") if f.strip())


def _cmd_bench_tradeoff(a) -> int:
    from ..outputs import atomic_write_text
    from .bench import BenchOptions, run_bench_tradeoff, summary

    if a.json is None:
        raise ConfigError("--json: required (the output file)")
    opts = BenchOptions(scene=a.scene, touch_scene=a.touch_scene, photons=a.photons, seed=a.seed, seeds=a.seeds,
                        g=a.g, nee_points=a.nee_points, repeats=a.repeats, elevations=a.elevations, batch=a.batch,
                        frontier=_frontier(a.frontier))
    result = run_bench_tradeoff(opts, progress=True)
    atomic_write_text(a.json, json.dumps(result, indent=1), overwrite=a.overwrite)
    print(summary(result))
    print(f"wrote {a.json}")
    return 0


def register(sub) -> None:
    """Add ``mc``, ``prune`` and ``bench tradeoff`` to the ``tofjax`` command."""
    s = sub.add_parser("mc", help="Monte Carlo photon transport: a reference capture from a scene file, or 'slab'")
    s.add_argument("scene", help="scene TOML file, a built-in name, or 'slab' (a slab in air, pencil beam; --json)")
    s.add_argument("--photons", type=int, default=100_000, help="photon packets per sensor (accuracy; default 1e5)")
    s.add_argument("--frames", type=int, default=1, help="frames drawn with photon noise (default 1)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--g", type=float, default=0.0, help="Henyey-Greenstein anisotropy (default 0)")
    s.add_argument("--edges", choices=["diffuse", "specular", "absorb"], default="diffuse")
    s.add_argument("--batch", type=int, default=32_768, help="packets followed at once (memory)")
    s.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    s.add_argument("--out", help="output capture (.h5)")
    slab = s.add_argument_group("slab", "'tofjax mc slab': a slab in air lit by a pencil beam at normal incidence")
    slab.add_argument("--n", type=float, help="refractive index of the slab (default 1.4)")
    slab.add_argument("--thickness-m", type=float, help="thickness (default 0.005)")
    slab.add_argument("--mu-s-per-m", type=float, help="scattering coefficient (default 200)")
    slab.add_argument("--mu-a-per-m", type=float, help="absorption coefficient (default 2)")
    slab.add_argument("--json", help="output JSON: diffuse_reflectance, total_transmittance, absorbed with *_se")
    s.set_defaults(func=_cmd_mc)

    s = sub.add_parser("prune", help="which model components a scene needs, against the photon noise")
    s.add_argument("scene", help="scene TOML file, or a built-in name")
    s.add_argument("--noise-floor", type=float, default=1.0, help="largest effect dropped, in noise sigmas (default 1)")
    s.add_argument("--frames", type=int, default=1, help="frames averaged in the data (default 1)")
    s.add_argument("--quadrature", type=int, default=2)
    s.add_argument("--timing", action="store_true", help="time the full and the pruned model")
    s.add_argument("--out", help="also write the report as JSON")
    s.set_defaults(func=_cmd_prune)

    s = sub.add_parser("bench", help="benchmarks: 'tradeoff' (the analytic model against the Monte Carlo; cost)")
    bsub = s.add_subparsers(dest="bench", metavar="BENCH", required=True)
    t = bsub.add_parser("tradeoff", help="analytic (default and guided optics) against Monte Carlo; forward cost")
    t.add_argument("--json", help="output JSON (analytic_vs_mc_relative_l2, forward_cost, reference, ...)")
    t.add_argument("--scene", default="optoskin", help="baseline scene (contacts removed; default optoskin)")
    t.add_argument("--touch-scene", default="touch-three-line", help="scene with contacts (default touch-three-line)")
    t.add_argument("--photons", type=int, default=100_000, help="Monte Carlo packets per sensor and scene")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--seeds", type=int, default=4, help="independent runs the photons are split over (their spread: the noise)")
    t.add_argument("--g", type=float, default=0.0, help="Henyey-Greenstein anisotropy of the Monte Carlo (default 0)")
    t.add_argument("--nee-points", type=int, default=24, help="Monte Carlo elevation nodes (default 24)")
    t.add_argument("--elevations", type=int, default=8, help="guided optics' elevation nodes (default 8)")
    t.add_argument("--repeats", type=int, default=31, help="timed pairs of forward evaluations (default 31)")
    t.add_argument("--batch", type=int, default=32_768, help="Monte Carlo packets followed at once (memory)")
    t.add_argument("--frontier", help="cheaper guided fidelities to measure too, comma-separated "
                   "ELEVATIONS:ANGLES:QUADRATURE:DTYPE (e.g. 4:4:1:float32), or 'none' (default: a built-in set)")
    t.set_defaults(func=_cmd_bench_tradeoff)
