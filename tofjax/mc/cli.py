"""``tofjax mc``, ``tofjax prune`` and ``tofjax bench tradeoff``: thin wrappers of the library."""

from __future__ import annotations

import json
from pathlib import Path

from ..config import ConfigError


def _cmd_mc(a) -> int:
    from ..capture import write_capture
    from ..scene import load_scene
    from .capture import mc_capture
    from .transport import MCOptions

    scene = load_scene(a.scene)
    if a.frames < 1:
        raise ConfigError(f"--frames: must be >= 1, got {a.frames}")
    from ..cli import _check_size

    _check_size(scene, a.frames)
    from ..capture import check_capture_target

    check_capture_target(a.out, a.overwrite)
    opts = MCOptions(photons=a.photons, seed=a.seed, g=a.g, edges=a.edges, dtype=a.dtype, batch=a.batch)
    cap = mc_capture(scene, a.frames, a.seed, opts, progress=True)
    write_capture(a.out, cap, overwrite=a.overwrite)
    t = cap.truth
    print(
        f"wrote {a.out}: {cap.n_frames} frames of {scene.shape} (sensors, zones, bins), scene '{scene.name}', "
        f"{a.photons} photons per sensor, {t['mc_events']} events in {t['mc_seconds']:.1f} s "
        f"({t['mc_events'] / max(t['mc_seconds'], 1e-9):.3g} events/s)"
    )
    print("where the light went: " + ", ".join(f"{k} {v:.3g}" for k, v in t["mc_ledger"].items()))
    return 0


def _cmd_prune(a) -> int:
    from ..model import ModelOptions
    from ..scene import load_scene
    from .prune import PruneOptions, prune_model

    scene = load_scene(a.scene)
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


def _cmd_tradeoff(a) -> int:
    from ..scene import load_scene
    from .tradeoff import TradeoffConfig, load_tradeoff_config, run_tradeoff

    cfg = load_tradeoff_config(a.config) if a.config else TradeoffConfig()
    changes = {}
    if a.scene:
        changes["scene"] = a.scene
    if a.budget is not None:
        changes["budget"] = a.budget
    if a.photons is not None:
        changes["reference_photons"] = a.photons
    if a.quick:
        changes.update(quick=True)
    if changes:
        import dataclasses

        cfg = dataclasses.replace(cfg, **changes)
    load_scene(cfg.scene)  # fail early on a bad scene
    result = run_tradeoff(cfg, Path(a.out), progress=True)
    print(Path(a.out, "tradeoff.md").read_text())
    print(f"wrote tradeoff.json, tradeoff.md and tradeoff.png to {a.out}/ ({result['wall_s']:.0f} s)")
    return 0


def register(sub) -> None:
    """Add ``mc``, ``prune`` and ``bench`` to the ``tofjax`` command."""
    s = sub.add_parser("mc", help="Monte Carlo photon transport: a reference capture from a scene file")
    s.add_argument("scene", help="scene TOML file, or a built-in name")
    s.add_argument("--photons", type=int, default=100_000, help="photon packets per sensor (accuracy; default 1e5)")
    s.add_argument("--frames", type=int, default=1, help="frames drawn with photon noise (default 1)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--g", type=float, default=0.0, help="Henyey-Greenstein anisotropy (default 0)")
    s.add_argument("--edges", choices=["diffuse", "specular", "absorb"], default="diffuse")
    s.add_argument("--batch", type=int, default=32_768, help="packets followed at once (memory)")
    s.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    s.add_argument("--out", required=True, help="output capture (.h5)")
    s.set_defaults(func=_cmd_mc)

    s = sub.add_parser("prune", help="which model components a scene needs, against the photon noise")
    s.add_argument("scene", help="scene TOML file, or a built-in name")
    s.add_argument("--noise-floor", type=float, default=1.0, help="largest effect dropped, in noise sigmas (default 1)")
    s.add_argument("--frames", type=int, default=1, help="frames averaged in the data (default 1)")
    s.add_argument("--quadrature", type=int, default=2)
    s.add_argument("--timing", action="store_true", help="time the full and the pruned model")
    s.add_argument("--out", help="also write the report as JSON")
    s.set_defaults(func=_cmd_prune)

    b = sub.add_parser("bench", help="benchmarks of speed against accuracy")
    bsub = b.add_subparsers(dest="bench", metavar="BENCH")
    bsub.required = True
    s = bsub.add_parser("tradeoff", help="fidelity ladder, fits and Monte Carlo against a Monte Carlo reference")
    s.add_argument("--scene", help="scene TOML file or built-in name (default optoskin)")
    s.add_argument("--config", help="trade-off config TOML (configs/studies/tradeoff.toml)")
    s.add_argument("--budget", type=float, help="error budget: relative L2 error against the reference")
    s.add_argument("--photons", type=int, help="reference photons per sensor")
    s.add_argument("--quick", action="store_true", help="a small run (minutes): fewer photons, no fit study")
    s.add_argument("--out", required=True, help="output folder")
    s.set_defaults(func=_cmd_tradeoff)
